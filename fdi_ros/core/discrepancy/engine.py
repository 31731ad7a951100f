"""Discrepancy discovery: fit every catalogue extension, score it on held-out blocks, rank.

Procedure for each channel (greedy forward selection, at most ``max_findings`` steps):

1. The valid samples are cut into contiguous blocks of equal duration (about 5 s, at least
   24 blocks). In ``n_folds`` refits (default: one per block), fold k holds out the blocks
   k, k + n_folds, ...; the extensions are fitted on the other blocks minus a guard band of
   ``guard_s`` on each side of every held-out block (the residuals of 20 Hz data are strongly
   autocorrelated, so a training sample right next to the held-out block would leak its value
   into the test).
2. For every candidate (every catalogue effect, every explaining column, always on, after an
   onset time, or piecewise constant in time) the out-of-block predictions give per block the
   held-out mean squared error
   before (current model, refitted per fold) and after (current model + candidate).
3. Significance: one-sided Wilcoxon signed-rank test on the blockwise differences
   ``d_b = MSE_before_b - MSE_after_b`` (zero differences dropped). Blocks, not samples, are
   the units: within a block the residuals are correlated, the blocks (several seconds, long
   against the correlation time) are treated as independent. The p-value is
   Bonferroni-corrected over the channel's own candidates of the step and all channels (the
   errors of the model's input sensors are other carriers of the same shapes: they compete
   for the attribution, they do not add chances of a false discovery). A Diebold-Mariano
   test on the per-sample loss differential with a Newey-West variance is reported alongside
   (``p_dm``).
4. Choice: the candidate with the lowest held-out MSE; a special case of it (the same effect
   always on instead of after an onset, or after one onset instead of piecewise in time)
   replaces it when its MSE is within one standard error (the one-SE rule of
   cross-validation). Other effects within one standard error are reported as
   ``alternatives``: the data cannot tell them apart.
5. It becomes a finding if significant and its held-out gain ``100 (1 - RMSE_after /
   RMSE_before)`` is at least ``min_gain_pct``; it then joins the model and the next step
   looks for what is left. Nothing significant: the verdict is ``consistent``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
from scipy import stats

from fdi_ros.core.discrepancy.context import ChannelContext
from fdi_ros.core.discrepancy.effects import CATALOGUE, Effect, InputDependence, SensorError
from fdi_ros.core.discrepancy.joint import Hypothesis, fit_hypothesis, hypotheses
from fdi_ros.core.discrepancy.ties import tie_reason


@dataclass(frozen=True)
class DiscrepancyConfig:
    """Settings of :func:`analyse` (keyword-only, validated).

    Attributes
    ----------
    n_blocks : contiguous held-out blocks per channel (the units of the test); default: one
        block per ``block_s`` seconds, at least 24 and at most 60.
    n_folds : refits; fold k holds out the blocks k, k + n_folds, k + 2 n_folds, ...;
        default one fold per block (leave one block out: an onset time, fitted on the rest,
        is stable).
    block_s : target block duration [s] (long against the residual correlation time).
    alpha : family-wise significance level (Bonferroni over candidates and channels).
    min_gain_pct : smallest held-out RMSE gain [%] reported as a finding.
    max_findings : greedy steps per channel.
    guard_s : training samples closer than this to the held-out block are dropped [s];
        default a quarter of a block.
    effects : catalogue ids to try.
    onset : also try offset/gain/leak switching on at an unknown time (an abrupt fault).
    sensor_effects : catalogue ids tried as errors of the model's input sensors (contexts
        built with ``sensors=True``); default: ``effects``.
    """

    n_blocks: int | None = None
    block_s: float = 5.0
    n_folds: int | None = None
    alpha: float = 0.05
    min_gain_pct: float = 2.0
    max_findings: int = 3
    guard_s: float | None = None
    effects: tuple[str, ...] = CATALOGUE
    onset: bool = True
    sensor_effects: tuple[str, ...] | None = None
    penalty: bool = False

    def __post_init__(self) -> None:
        rules = ((self.n_blocks is None or self.n_blocks >= 4,
                  "n_blocks must be >= 4 for a paired test over blocks"),
                 (self.n_folds is None or self.n_folds >= 2, "n_folds must be >= 2"),
                 (0 < self.alpha < 1, "alpha must be in (0, 1)"),
                 (self.max_findings >= 1, "max_findings must be >= 1"))
        for ok, why in rules:
            if not ok:
                raise ValueError(why)
        bad = (set(self.effects) | set(self.sensor_effects or ())) - set(CATALOGUE)
        if bad:
            raise ValueError(f"unknown effects {sorted(bad)}; catalogue: {CATALOGUE}")


@dataclass(frozen=True)
class _Scored:
    """What an explanation is and how it scored on the held-out blocks."""

    effect: str
    label: str
    channel: str
    n_params: int
    rmse_before: float
    rmse_after: float
    gain_pct: float
    p_value: float
    p_adjusted: float
    p_dm: float


@dataclass(frozen=True)
class Candidate(_Scored):
    """Held-out score of one candidate extension in one greedy step."""

    mse_blocks: np.ndarray = field(repr=False)
    residuals: tuple[str, ...] = ()  # the residuals it moves
    shown_on: str = ""  # the residual whose held-out RMSE the record reports
    # mean held-out score on every residual it was scored on, in units of its noise level
    per_residual: dict[str, float] = field(default_factory=dict, repr=False)


@dataclass(frozen=True)
class Finding(_Scored):
    """One significant model deficiency, its extension and the held-out gain."""

    rank: int
    params: dict[str, Any]
    significant: bool
    step: int
    alternatives: list[dict[str, Any]] = field(default_factory=list)
    view: str = "samples"  # "samples", "segment means" or "crank-resolved"
    model_channel: str = ""  # the residual that shows it (a sensor error of an input: the
    # channel the model predicts from that input); empty: ``channel`` itself
    residuals: tuple[str, ...] = ()  # every residual it moves (scored on all of them at once)
    shown_on: str = ""  # the residual whose held-out RMSE before/after is reported
    input_sensor: bool = False  # an error of a sensor the model reads (not of a residual's
    # own measurement)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = _jsonable(asdict(self))
        return out


@dataclass
class DiscrepancyResult:
    """Outcome of :func:`analyse` (like scipy's OptimizeResult: check ``success``)."""

    findings: list[Finding]
    candidates: list[Candidate]
    verdict: str
    message: str
    success: bool
    channels: dict[str, dict[str, Any]]
    chains: dict[str, list[tuple[Effect, dict[str, Any]]]]
    n_blocks: int
    nit: int
    seconds: float
    config: DiscrepancyConfig
    oof: dict[str, dict[str, np.ndarray]] = field(default_factory=dict, repr=False)
    # the first step's leading explanations scored on every residual at once (their
    # mse_blocks: the joint held-out score), when other residuals checked them
    joint: list[Candidate] = field(default_factory=list, repr=False)
    # with no significant finding: the best explanation over every residual (significant
    # False, parameters fitted on every valid sample, its ties), when one gained
    # SUSPECT_GAIN_PCT held-out
    suspect: Finding | None = None

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = _jsonable({
            "verdict": self.verdict,
            "message": self.message,
            "success": self.success,
            "findings": [f.to_dict() for f in self.findings],
            "suspect": None if self.suspect is None else self.suspect.to_dict(),
            "candidates": [{k: v for k, v in asdict(c).items() if k != "mse_blocks"}
                           for c in self.candidates[:25]],
            "channels": self.channels,
            "held_out": {
                "scheme": "leave-one-block-out over contiguous time blocks with guard bands",
                "n_blocks": {ch: c.get("n_blocks") for ch, c in self.channels.items()},
                "test": "one-sided Wilcoxon signed-rank test over the blockwise held-out MSE "
                        "differences (blocks as "
                        "the independent units, samples within a block are correlated), "
                        "Bonferroni over the channels' own candidates and the channels "
                        "(input-sensor errors compete for the attribution); p_dm: "
                        "Diebold-Mariano test on the per-sample loss differential with a "
                        "Newey-West variance, for reference",
                "alpha": self.config.alpha,
                "min_gain_pct": self.config.min_gain_pct,
            },
            "seconds": self.seconds,
        })
        return out


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        v = float(x)
        if np.isnan(v):
            return None
        if np.isinf(v):
            return "inf" if v > 0 else "-inf"
        return v
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def make_blocks(t: np.ndarray, ok: np.ndarray, n_blocks: int,
                span: tuple[float, float] | None = None) -> np.ndarray:
    """Block id per sample (-1 where not ok): equal-duration contiguous blocks over ``span``
    (default: the valid samples' time range)."""
    tv = t[ok]
    lo, hi = (tv[0], tv[-1]) if span is None else span
    edges = np.linspace(lo, hi, n_blocks + 1)
    blk = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, n_blocks - 1)
    return np.where(ok, blk, -1)


def apply_chain(ctx: ChannelContext, chain: list[tuple[Effect, dict[str, Any]]]) -> np.ndarray:
    pred = ctx.yhat
    for eff, p in chain:
        pred = eff.apply(ctx, pred, p)
    return pred


def _block_mse(err2: np.ndarray, blk: np.ndarray, n_blocks: int) -> np.ndarray:
    ok = blk >= 0
    s = np.bincount(blk[ok], weights=err2[ok], minlength=n_blocks)
    c = np.bincount(blk[ok], minlength=n_blocks)
    return np.where(c > 0, s / np.maximum(c, 1), np.nan)


def paired_p(before: np.ndarray, after: np.ndarray) -> float:
    """One-sided p-value that the held-out MSE is lower after: Wilcoxon signed-rank over blocks.

    Ranks, not magnitudes: a few blocks with large transients must not decide the test, and an
    effect present in part of the record only (a fault after its onset) leaves the other blocks
    exactly unchanged; those zero differences carry no information and are dropped.
    """
    d = (before - after)[np.isfinite(before) & np.isfinite(after)]
    scale = max(float(np.nanmax(np.abs(before))), 1e-300) if before.size else 1.0
    d = d[np.abs(d) > 1e-12 * scale]
    if d.size < 3:
        return 1.0
    return float(stats.wilcoxon(d, alternative="greater", zero_method="wilcox").pvalue)


def hac_bandwidth(d: np.ndarray) -> int:
    """Bartlett bandwidth [samples] for a serially correlated series.

    Three times the lag at which the sample autocorrelation first falls below 0.05 (20 Hz
    residuals stay correlated over seconds), at least ``N^(1/3)``, at most ``N / 8``.
    """
    n = d.size
    x = d - d.mean()
    var = float(np.dot(x, x))
    if var == 0.0:
        return 1
    nfft = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(x, nfft)
    acf = np.fft.irfft(f * np.conj(f), nfft)[: n // 8 + 1] / var
    below = np.flatnonzero(acf < 0.05)
    lag = int(below[0]) if below.size else n // 8
    return int(np.clip(3 * lag, np.ceil(n ** (1 / 3)), max(n // 8, 1)))


def loss_differential_p(e_before: np.ndarray, e_after: np.ndarray) -> tuple[float, int]:
    """One-sided Diebold-Mariano test that the squared held-out error is lower after.

    ``d_i = e_before_i^2 - e_after_i^2`` over the held-out samples in time order; its mean is
    tested with a Newey-West (Bartlett) long-run variance, so the strong serial correlation of
    the residuals is accounted for, against a t distribution with ``N / L - 1`` degrees of
    freedom (L the bandwidth: about one independent value per bandwidth). The bandwidth comes
    from the autocorrelation of the remaining residual (the noise process), not of ``d``
    itself, whose mean legitimately changes where an effect switches on. Returns (p, L).
    """
    ok = np.isfinite(e_before) & np.isfinite(e_after)
    d = e_before[ok] ** 2 - e_after[ok] ** 2
    n = d.size
    if n < 10:
        return 1.0, 0
    L = hac_bandwidth(e_after[ok])
    x = d - d.mean()
    nfft = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(x, nfft)
    acov = np.fft.irfft(f * np.conj(f), nfft)[: L + 1] / n
    k = np.arange(1, L + 1)
    lrv = float(acov[0] + 2.0 * np.sum((1.0 - k / (L + 1)) * acov[1:]))
    if lrv <= 0.0:
        return (0.0 if d.mean() > 0 else 1.0), L
    tstat = d.mean() / np.sqrt(lrv / n)
    dof = max(n / L - 1.0, 2.0)
    return float(stats.t.sf(tstat, dof)), L


def _lead(h: Hypothesis) -> Effect:
    """The effect a hypothesis is fitted through (its first member)."""
    return h.members[0][1]


def _nests(big: Hypothesis, small: Hypothesis) -> bool:
    """True when ``small`` is a special case of ``big`` (the same effect of the same carrier
    with fewer change times: always on < after an onset < piecewise constant in time)."""
    a, b = _lead(big), _lead(small)
    if big.effect != small.effect or big.carrier != small.carrier or getattr(
            a, "sensor", "") != getattr(b, "sensor", ""):
        return False
    if big.effect == "input_dependence" and not getattr(a, "sensor", ""):
        # linear in a column < linear with a square of the same column
        return (getattr(a, "column", None) == getattr(b, "column", "")
                and getattr(b, "degree", 2) < getattr(a, "degree", 2))
    if getattr(a, "piecewise", False):
        return not getattr(b, "piecewise", True)
    return getattr(a, "onset", False) and not getattr(b, "onset", True) and not getattr(
        b, "piecewise", True)


def _linear_case(h: Hypothesis) -> bool:
    """A linear dependence on a measured signal, tested beside (and nested in) the same
    dependence with a square: the shape is counted once in the multiplicity correction."""
    lead = _lead(h)
    return (isinstance(lead, InputDependence) and lead.degree == 1
            and not lead.column.startswith("d/dt "))


def _finite_diff(blocks: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Block-by-block ``blocks - ref`` where both are known."""
    d = blocks - ref
    return np.asarray(d[np.isfinite(d)], float)


def _within_one_se(d: np.ndarray, tol: float = 0.0) -> bool:
    """Whether the mean of block differences ``d`` (:func:`_finite_diff`; at least 3) is
    at most one standard error (plus ``tol``): the held-out data cannot tell the two apart."""
    return bool(d.size >= 3 and d.mean() <= np.std(d, ddof=1) / np.sqrt(d.size) + tol)


def penalised(c: Candidate, n_eff: float) -> float:
    """Bayesian information criterion of a candidate on its held-out blocks.

    ``n_eff ln(S) + k ln(n_eff)``: ``S`` the mean held-out score over the blocks (the
    residuals' mean squared errors, each residual in units of its own noise level), ``k`` the
    number of parameters, ``n_eff`` the number of effectively independent held-out values
    (samples over the residual's correlation length). The held-out error already penalises
    a fit to noise; the price on parameters makes an explanation with more parameters
    (an onset, change times) earn its keep: with 50 independent values a second parameter
    must lower the held-out error by about 8 %.
    """
    s = float(np.nanmean(c.mse_blocks))
    return n_eff * math.log(max(s, 1e-300)) + c.n_params * math.log(max(n_eff, 2.0))


def _one_se_choice(scored: list[tuple[Hypothesis, Candidate]], alpha: float,
                   n_eff: float = 0.0) -> tuple[Hypothesis, Candidate]:
    """The explanation with the lowest penalised held-out score (:func:`penalised`), or a
    special case of it within one standard error.

    Nested alternatives compete on parsimony (an always-on gain error vs the same gain
    switching on at some time), and a time-varying best (drift, piecewise in time) yields to a
    dependence on a measured column within one standard error; an input sensor's error yields
    to the same kind of error of a measured channel within one standard error, and a
    dependence on an input's slope to that input's lag or dead time unless it is
    significantly worse; other effects with different physics compete on held-out error.
    ``n_eff`` = 0: no price on parameters (the lowest held-out score).
    """
    if n_eff > 0:
        best = min(scored, key=lambda hc: penalised(hc[1], n_eff))
    else:
        best = min(scored, key=lambda hc: np.nanmean(hc[1].mse_blocks))
    tol = 1e-3 * float(np.nanmean(best[1].mse_blocks))

    def within_one_se(c: Candidate) -> bool:
        return _within_one_se(_finite_diff(c.mse_blocks, best[1].mse_blocks), tol)

    if getattr(_lead(best[0]), "sensor", ""):
        # the same kind of error of a measured channel, within one standard error of an input
        # sensor's: the channel's own error is named (it needs no second faulty sensor), the
        # input sensor's stays among the reported ties
        own = [(h, c) for h, c in scored if not getattr(_lead(h), "sensor", "")
               and h.effect == best[0].effect and c.p_adjusted < alpha and within_one_se(c)]
        if own:
            best = min(own, key=lambda hc: np.nanmean(hc[1].mse_blocks))
    column = str(getattr(_lead(best[0]), "column", ""))
    if best[0].effect == "input_dependence" and column.startswith("d/dt "):
        # the residual following the slope of one of the model's inputs is what a lag or
        # dead time of that sensor produces (to first order the same explanation): unless it
        # is significantly worse, the sensor's timing error is named (as many parameters, and
        # it predicts through the model)
        timing = [(h, c) for h, c in scored
                  if h.carrier == column[5:] and h.effect in ("sensor_lag", "dead_time")
                  and c.p_adjusted < alpha
                  and paired_p(c.mse_blocks, best[1].mse_blocks) >= alpha]
        if timing:
            best = min(timing, key=lambda hc: np.nanmean(hc[1].mse_blocks))
        else:
            # the slope of a slowly settling quantity is the quantity itself (an exponential
            # warm-up: d/dt T = (T_end - T) / tau): unless it is significantly worse, the
            # measured signal is named, its slope stays among the ties
            itself = [(h, c) for h, c in scored if h.effect == "input_dependence"
                      and getattr(_lead(h), "column", "") == column[5:]
                      and h.carrier == best[0].carrier and c.p_adjusted < alpha
                      and paired_p(c.mse_blocks, best[1].mse_blocks) >= alpha]
            if itself:
                best = min(itself, key=lambda hc: np.nanmean(hc[1].mse_blocks))
    if _time_varying(_lead(best[0])):
        # a change over time is accepted only if no measured column explains the same
        # residual: a dependence on a measured signal (few parameters, predicts new data)
        # beats a drift or a piecewise-in-time fit within one standard error of it, and so
        # does an offset in a region of the measured operating point (a piecewise fit that
        # follows the visits to that region needs a change time for each)
        measured = [(h, c) for h, c in scored if (
                        (h.effect == "input_dependence" and h.n_params <= best[0].n_params)
                        or h.effect == "local_region")
                    and c.p_adjusted < alpha and within_one_se(c)]
        if measured:
            return min(measured, key=lambda hc: np.nanmean(hc[1].mse_blocks))
    eligible = [best]
    for h, c in scored:
        if not _nests(best[0], h) or c.p_adjusted >= alpha:
            continue
        if within_one_se(c):
            eligible.append((h, c))
    return min(eligible, key=lambda hc: (hc[0].n_params, np.nanmean(hc[1].mse_blocks)))


def _time_varying(eff: Effect) -> bool:
    """Drift, or an effect piecewise constant in time."""
    return eff.id == "drift" or bool(getattr(eff, "piecewise", False))


def _verdict(findings: list[Finding], table: list[Candidate], alpha: float = 0.05,
             suspect: Finding | None = None) -> tuple[str, str]:
    """Verdict and one-line message from the findings and the candidate table (``alpha``: the
    significance level, to tell a candidate dropped as too small from an inconsistent one;
    ``suspect``: the best explanation over every residual when nothing is significant)."""
    if findings:
        top = findings[0]
        return "discrepant", (f"{len(findings)} significant finding(s); top: {top.label} on "
                              f"{top.channel} (held-out RMSE -{top.gain_pct:.1f}%)")
    msg = ("no extension improves the held-out error significantly: the model is consistent "
           "with the data")
    if table and table[0].gain_pct >= 10.0:
        c = table[0]
        why = ("moves the reading less than the relevance floor: real, but too small to matter"
               if c.p_adjusted < alpha else "not consistently over the held-out blocks: an "
               "effect outside the catalogue, e.g. intermittent, is possible")
        msg += (f" (the best candidate, {c.label} on {c.channel}, gains {c.gain_pct:.0f} % "
                f"held-out, p_adj {c.p_adjusted:.2g}, but {why})")
        if suspect is not None and c.p_adjusted >= alpha:
            ties = ", ".join(f"{a['label']} on {a['channel']}"
                             for a in suspect.alternatives[:3])
            msg += (f"; the suspect (the best explanation, over every residual that checks "
                    f"it, fitted on every sample) is {suspect.label} on {suspect.channel} "
                    f"({format_params(suspect.params)}), not significant"
                    + (f"; tied: {ties}" if ties else ""))
    return "consistent", msg


def format_params(p: dict[str, Any]) -> str:
    """A fitted explanation's parameters for a message or report (``gain=0.925;
    onset_s=125.1``), without the internal scalings of its regressors."""
    out = []
    for k, v in p.items():
        if k in ("a", "b", "center", "scale", "sq_mean", "z_range", "t_ref_s", "cd",
                 "cda_mm2") or v is None:
            continue
        if isinstance(v, float):
            out.append(f"{k}={v:.4g}")
        elif isinstance(v, dict):
            out.append(f"{k}=" + ", ".join(f"{a} in [{lo:.4g}, {hi:.4g}]"
                                            for a, (lo, hi) in v.items()))
        elif isinstance(v, list):
            out.append(f"{k}=[" + ", ".join(f"{x:.3g}" for x in v) + "]")
        else:
            out.append(f"{k}={v}")
    return "; ".join(out)


def _n_blocks(ctx: ChannelContext, cfg: DiscrepancyConfig, info: dict[str, Any]) -> int | None:
    """Number of time blocks of a channel, or None (and ``info["status"]``) if too few
    valid samples."""
    n_ok = info["n_valid"]
    tv = ctx.t[ctx.ok]
    if tv.size < 2:
        info["status"] = (f"too few valid samples ({n_ok}): measured or predicted values "
                          "missing (outside the identified region?)")
        return None
    nb = cfg.n_blocks or int(np.clip(round((tv[-1] - tv[0]) / cfg.block_s), 24, 60))
    info["n_blocks"] = nb
    if n_ok < 20 * nb:
        info["status"] = f"too few valid samples ({n_ok}) for {nb} blocks"
        return None
    return nb


def _folds(ctx: ChannelContext, cfg: DiscrepancyConfig, blk: np.ndarray, nb: int,
           ok: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Training and test masks of the interleaved block folds (a guard interval around each
    held-out block is left out of training); the folds are also left on ``ctx`` for effects
    that evaluate a parameter grid for all folds at once."""
    tv = ctx.t[ok]
    blen = (tv[-1] - tv[0]) / nb
    guard = 0.25 * blen if cfg.guard_s is None else cfg.guard_s
    bounds = [(ctx.t[blk == b].min(), ctx.t[blk == b].max()) if np.any(blk == b)
              else (np.nan, np.nan) for b in range(nb)]
    nf = min(cfg.n_folds or nb, nb)
    trains, tests, cuts = [], [], []
    for k in range(nf):
        held = list(range(k, nb, nf))  # interleaved blocks: every fold spans the record
        for b in held:
            lo, hi = bounds[b]
            i0 = int(np.searchsorted(ctx.t, lo - guard, side="left"))
            i1 = int(np.searchsorted(ctx.t, hi + guard, side="right"))
            cuts.append((i0, i1, k))
        mask = np.zeros(ctx.n, dtype=bool)
        for i0, i1, kk in cuts:
            if kk == k:
                mask[i0:i1] = True
        trains.append(ok & ~mask)
        tests.append(np.isin(blk, held))
    # merge overlapping left-out intervals per fold (guards of neighbouring blocks)
    merged: list[tuple[int, int, int]] = []
    for k in range(nf):
        iv = sorted((a, b) for a, b, kk in cuts if kk == k)
        for a, b in iv:
            if merged and merged[-1][2] == k and a <= merged[-1][1]:
                merged[-1] = (merged[-1][0], max(b, merged[-1][1]), k)
            else:
                merged.append((a, b, k))
    ctx.folds = (np.array([c[0] for c in merged]), np.array([c[1] for c in merged]),
                 np.array([c[2] for c in merged]))
    ctx.fold_ids = {id(tr): k for k, tr in enumerate(trains)}
    return trains, tests


@dataclass
class _Channel:
    """One residual under analysis (a view): its context, folds and blocks.

    ``secondary``: a residual that checks the leading explanations only (none is proposed
    there, none is tested for significance there): e.g. the crank-resolved pulsation of a
    channel whose mean-value effects are found on segment means.
    """

    name: str
    ctx: ChannelContext
    blk: np.ndarray
    nb: int
    trains: list[np.ndarray]
    tests: list[np.ndarray]
    ok: np.ndarray  # valid samples (one array for the whole analysis of the channel)
    secondary: bool = False

    def err(self, pred: np.ndarray) -> np.ndarray:
        return self.ctx.pulsation(self.ctx.y - pred)

    def rmse(self, pred: np.ndarray) -> float:
        return float(np.sqrt(np.nanmean(self.err(pred)[self.ok] ** 2)))

    def block_mse(self, pred: np.ndarray) -> np.ndarray:
        return _block_mse(self.err(pred) ** 2, self.blk, self.nb)


@dataclass
class _Step:
    """The current model of every residual, per fold and held out (one greedy step)."""

    bases: dict[str, list[np.ndarray]]
    before: dict[str, np.ndarray]
    mse_b: dict[str, np.ndarray]
    rmse_b: dict[str, float]


def _contexts(views: dict[str, _Channel]) -> dict[str, ChannelContext]:
    return {v: c.ctx for v, c in views.items()}


def _fit_in(views: dict[str, _Channel], h: Hypothesis, preds: dict[str, np.ndarray],
            trains: dict[str, np.ndarray], *, refine: bool = False
            ) -> list[dict[str, Any]]:
    """``h``'s member parameters (:func:`~fdi_ros.core.discrepancy.joint.fit_hypothesis`)."""
    return fit_hypothesis(h, _contexts(views), preds, trains, refine=refine)


def _held_out_chain(views: dict[str, _Channel], chain: list[Hypothesis]) -> _Step:
    """Per fold the chain's prediction of every residual, and its held-out prediction."""
    any_view = next(iter(views.values()))
    bases: dict[str, list[np.ndarray]] = {v: [] for v in views}
    before = {v: np.full(c.ctx.n, np.nan) for v, c in views.items()}
    for k in range(len(any_view.trains)):
        preds = _fit_all(views, chain, {v: c.trains[k] for v, c in views.items()})
        for v, c in views.items():
            bases[v].append(preds[v])
            te = c.tests[k]
            before[v][te] = preds[v][te]
    return _Step(bases=bases, before=before,
                 mse_b={v: c.block_mse(before[v]) for v, c in views.items()},
                 rmse_b={v: c.rmse(before[v]) for v, c in views.items()})


def _held_out(views: dict[str, _Channel], h: Hypothesis, st: _Step, scope: set[str]
              ) -> dict[str, np.ndarray] | None:
    """Held-out prediction of every residual in ``scope`` that ``h`` moves (None: it cannot
    be fitted)."""
    touched = [v for v in h.views if v in scope]
    if not touched:
        return {}
    after = {v: np.full(views[v].ctx.n, np.nan) for v in touched}
    first = next(iter(views.values()))
    try:
        for k in range(len(first.trains)):
            preds = {v: st.bases[v][k] for v in views}
            trains = {v: c.trains[k] for v, c in views.items()}
            for (v, eff), p in zip(h.members, _fit_in(views, h, preds, trains)):
                if v in after:
                    te = views[v].tests[k]
                    after[v][te] = eff.apply(views[v].ctx, preds[v], p)[te]
    except (np.linalg.LinAlgError, ValueError, FloatingPointError, KeyError):
        return None
    # a candidate that cannot predict a sample leaves the model's value there
    return {v: np.where(np.isfinite(a), a, st.before[v]) for v, a in after.items()}


@dataclass
class _Scoring:
    """Held-out predictions of the candidates of one step, per residual."""

    after: dict[int, dict[str, np.ndarray]] = field(default_factory=dict)  # id(h) -> view
    mse_a: dict[int, dict[str, np.ndarray]] = field(default_factory=dict)


def _noise_levels(views: dict[str, _Channel], st: _Step, sc: _Scoring, hs: list[Hypothesis]
                  ) -> dict[str, float]:
    """Per residual the scale its block errors are measured in: the lowest mean held-out
    error any candidate reaches there (the residual's noise level under the best
    explanation), the current model's where no candidate moves it."""
    level = {}
    for v in views:
        b = float(np.nanmean(st.mse_b[v]))
        best = [float(np.nanmean(sc.mse_a[id(h)][v])) for h in hs
                if id(h) in sc.mse_a and v in sc.mse_a[id(h)]]
        lo = min(best + [b])
        level[v] = max(lo, 1e-9 * b, 1e-300)
    return level


def _joint_blocks(views: dict[str, _Channel], per_view: dict[str, np.ndarray],
                  level: dict[str, float]) -> np.ndarray:
    """Blockwise score: the residuals' held-out mean squared errors, each in units of its
    noise level, summed (a residual without samples in a block adds nothing)."""
    stack = np.vstack([per_view[v] / level[v] for v in views])
    out: np.ndarray = np.where(np.isfinite(stack).any(axis=0), np.nansum(stack, axis=0),
                               np.nan)
    return out


def _candidate(views: dict[str, _Channel], h: Hypothesis, st: _Step, sc: _Scoring,
               level: dict[str, float], score_b: np.ndarray) -> Candidate:
    """The candidate record of ``h``: its blockwise joint score and, for the report, the
    held-out RMSE of the residual it improves most."""
    mse_a = sc.mse_a[id(h)]
    per_view = {v: mse_a.get(v, st.mse_b[v]) for v in views}
    score_a = _joint_blocks(views, per_view, level)

    def rel(v: str) -> float:
        return float(np.nanmean(mse_a[v]) / max(float(np.nanmean(st.mse_b[v])), 1e-300))

    shown = [v for v in mse_a if v in views and not views[v].secondary]
    show = min(shown, key=rel) if shown else h.primary
    after = sc.after[id(h)].get(show, st.before[show])
    c = views[show]
    rmse_a = c.rmse(after)
    p_dm, _ = loss_differential_p(c.err(st.before[show]), c.err(after))
    return Candidate(effect=h.effect, label=h.label, channel=h.carrier, n_params=h.n_params,
                     rmse_before=st.rmse_b[show], rmse_after=rmse_a,
                     gain_pct=100.0 * (1.0 - rmse_a / st.rmse_b[show]),
                     p_value=paired_p(score_b, score_a), p_adjusted=1.0, p_dm=p_dm,
                     mse_blocks=score_a, residuals=tuple(sorted(mse_a)), shown_on=show,
                     per_residual={v: float(np.nanmean(per_view[v]) / level[v])
                                   for v in views})


def _score_all(views: dict[str, _Channel], hs: list[Hypothesis], st: _Step,
               scope: set[str], sc: _Scoring) -> None:
    for h in hs:
        need = (scope & set(h.views)) - set(sc.after.get(id(h), {}))
        if not need and id(h) in sc.after:
            continue
        got = _held_out(views, h, st, need)
        if got is None:
            continue
        sc.after.setdefault(id(h), {}).update(got)
        sc.mse_a.setdefault(id(h), {}).update(
            {v: views[v].block_mse(a) for v, a in got.items()})


def _effective_n(views: dict[str, _Channel], st: _Step) -> float:
    """Effectively independent held-out values of the primary residuals: samples over the
    correlation length of the current residual (where its autocorrelation falls below 0.05)."""
    n = 0.0
    for v, c in views.items():
        if c.secondary:
            continue
        e = c.err(st.before[v])[c.ok]
        e = e[np.isfinite(e)]
        if e.size < 10:
            continue
        n += e.size / max(1.0, hac_bandwidth(e) / 3.0)
    return n


# A significant explanation that achieves all but this share of the named one's held-out
# RMSE gain is reported as a tie: what remains after either is the model's own error, and a
# difference of a few percent of the gain is no evidence for one cause over the other.
PRACTICAL_TIE = 0.05


def _alternatives(views: dict[str, _Channel], chain: list[Hypothesis],
                  scored: list[tuple[Hypothesis, Candidate]], choice: Candidate,
                  residual: str, before: float, alpha: float = 0.05, max_ties: int = 8
                  ) -> list[dict[str, Any]]:
    """Other explanations the held-out data cannot tell apart from the choice, with their own
    parameters fitted on every valid sample: within one standard error of it, or significant
    themselves and not significantly worse than it (one-sided Wilcoxon over the blocks, level
    ``alpha``), one per effect and carrier (its best variant), best first; then those that
    are significant and achieve at least 1 - :data:`PRACTICAL_TIE` of the choice's held-out
    gain (its simplest such variant): a difference that small, however significant with
    little noise, does not say which explanation is true."""
    alternatives: list[dict[str, Any]] = []
    full: dict[str, np.ndarray] | None = None
    oks = {v: c.ok for v, c in views.items()}

    def kind(h: Hypothesis | None, cand: Candidate) -> tuple[str, str, str]:
        # variants of one explanation share this (always on, after an onset, piecewise);
        # a dependence on another column is another explanation
        return (cand.effect, cand.channel, str(getattr(_lead(h), "column", "")) if h else "")

    chosen = next((h for h, c in scored if c is choice), None)
    seen = {kind(chosen, choice)}
    ranked = sorted(scored, key=lambda hc: float(np.nanmean(hc[1].mse_blocks)))

    def add(h: Hypothesis, cand: Candidate, basis: str) -> None:
        nonlocal full
        if full is None:
            full = _fit_all(views, chain, oks)
        params = _fit_in(views, h, full, oks, refine=True)[0]
        alt_d = {"effect": cand.effect, "label": cand.label, "channel": cand.channel,
                 "gain_pct": cand.gain_pct, "p_adjusted": cand.p_adjusted,
                 "params": params, "residuals": list(cand.residuals)}
        alt_d.update(tie_reason(choice, cand, residual, basis))
        alternatives.append(alt_d)
        seen.add(kind(h, cand))

    for h, cand in ranked:
        if kind(h, cand) in seen:
            continue  # one alternative per effect, channel and column: its best variant
        if not (cand.gain_pct > 0 and float(np.nanmean(cand.mse_blocks)) < before):
            # worse than the model as it is: no explanation at all (one block it cannot
            # predict puts the mean within one standard error of anything)
            continue
        d = _finite_diff(cand.mse_blocks, choice.mse_blocks)
        if d.size < 3 or len(alternatives) >= max_ties:
            continue
        if _within_one_se(d):
            add(h, cand, "held-out error within one standard error")
        elif cand.p_adjusted < alpha and paired_p(cand.mse_blocks,
                                                  choice.mse_blocks) >= alpha:
            add(h, cand, "significant itself, and not significantly worse over the held-out "
                         "blocks")
    # what each explains: the held-out RMS gain in the units of the score (every residual it
    # was scored on, each in units of its noise level)
    def gain(cand: Candidate) -> float:
        return 1.0 - float(np.sqrt(max(float(np.nanmean(cand.mse_blocks)), 0.0) / before))

    def told_apart(cand: Candidate) -> bool:
        # a check (a residual that only judges the leading explanations, an independent
        # witness) where what either leaves differs by more than its noise level: the data
        # there say which one it is, however close the joint gains are
        return any(abs(cand.per_residual.get(v, np.nan) - choice.per_residual.get(v, np.nan))
                   > 1.0 for v in choice.per_residual if v in views and views[v].secondary)

    best = gain(choice) if before > 0 else 0.0
    close = [(h, cand) for h, cand in ranked if cand.p_adjusted < alpha and best > 0
             and gain(cand) >= (1.0 - PRACTICAL_TIE) * best and not told_apart(cand)]
    for h, cand in sorted(close, key=lambda hc: (hc[1].n_params,
                                                 float(np.nanmean(hc[1].mse_blocks)))):
        if kind(h, cand) not in seen and len(alternatives) < max_ties:
            add(h, cand, f"held-out RMS gain {100 * gain(cand):.1f} % against "
                         f"{100 * best:.1f} %: within {PRACTICAL_TIE:.0%} of it")
    return alternatives


def _fit_all(views: dict[str, _Channel], chain: list[Hypothesis],
             trains: dict[str, np.ndarray], *, refine: bool = False,
             params_out: list[list[dict[str, Any]]] | None = None) -> dict[str, np.ndarray]:
    """Every residual's prediction with the chain fitted on ``trains``."""
    preds = {v: c.ctx.yhat for v, c in views.items()}
    for h in chain:
        ps = _fit_in(views, h, preds, trains, refine=refine)
        if params_out is not None:
            params_out.append(ps)
        for (v, eff), p in zip(h.members, ps):
            if v in views:
                preds[v] = eff.apply(views[v].ctx, preds[v], p)
    return preds


def _contenders(scored: list[tuple[Hypothesis, Candidate]], choice: Candidate,
                before: float, alpha: float, limit: int = 12
                ) -> list[tuple[Hypothesis, Candidate]]:
    """The choice and the explanations the primary residuals cannot tell from it: within
    one standard error of it, not significantly worse (significant or not on their own), or
    explaining at least 90 % of what it explains (``before``: the current model's mean
    held-out score): a consistent but small advantage on the primary residuals is no reason
    to keep an explanation from the residuals that could tell the two apart."""
    out = []
    best = before - float(np.nanmean(choice.mse_blocks))
    for h, c in sorted(scored, key=lambda hc: float(np.nanmean(hc[1].mse_blocks))):
        d = _finite_diff(c.mse_blocks, choice.mse_blocks)
        if c is choice or (d.size >= 3 and (
                _within_one_se(d)
                or before - float(np.nanmean(c.mse_blocks)) >= 0.9 * best
                or paired_p(c.mse_blocks, choice.mse_blocks) >= alpha)):
            out.append((h, c))
        if len(out) >= limit:
            break
    # the special cases of a contender (the same effect with fewer change times) are
    # contenders too: parsimony then chooses among them
    have = {id(h) for h, _ in out}
    out += [(h, c) for h, c in scored if id(h) not in have
            and any(_nests(big, h) for big, _ in out)]
    return out


def _finding(h: Hypothesis, choice: Candidate, step: int, alternatives: list[dict[str, Any]],
             *, significant: bool = True, params: dict[str, Any] | None = None) -> Finding:
    """The record of an explanation chosen at greedy ``step`` (0-based)."""
    return Finding(rank=0, effect=choice.effect, label=choice.label, channel=choice.channel,
                   model_channel=h.primary, params=params or {},
                   rmse_before=choice.rmse_before, rmse_after=choice.rmse_after,
                   gain_pct=choice.gain_pct, p_value=choice.p_value,
                   p_adjusted=choice.p_adjusted, p_dm=choice.p_dm, significant=significant,
                   n_params=choice.n_params, step=step + 1, alternatives=alternatives,
                   residuals=choice.residuals, shown_on=choice.shown_on,
                   input_sensor=isinstance(_lead(h), SensorError))


def _judged_jointly(views: dict[str, _Channel], scored: list[tuple[Hypothesis, Candidate]],
                    choice: Candidate, before: float, st: _Step, sc: _Scoring,
                    cfg: DiscrepancyConfig, n_eff: float
                    ) -> tuple[Hypothesis, Candidate, list[tuple[Hypothesis, Candidate]], float]:
    """The primary residuals' choice and its contenders scored over every residual at once
    (checks included): the explanation chosen there, the contenders' joint records and the
    current model's joint score. Two stages: the primary residuals say that something is
    wrong (the detection's p-value, carried by every contender), all residuals together say
    what (``before``: the current model's mean score on the primary residuals)."""
    cont = _contenders(scored, choice, before, cfg.alpha)
    _score_all(views, [hh for hh, _ in cont], st, set(views), sc)
    level = _noise_levels(views, st, sc, [hh for hh, _ in cont])
    every = _joint_blocks(views, {v: st.mse_b[v] for v in views}, level)
    detect = choice.p_adjusted
    ties_from = [(hh, replace(_candidate(views, hh, st, sc, level, every),
                              p_adjusted=detect)) for hh, _ in cont]
    h, joint_choice = _one_se_choice(ties_from, cfg.alpha, n_eff)
    return h, joint_choice, ties_from, float(np.nanmean(every))


def _grow_chain(views: dict[str, _Channel], cfg: DiscrepancyConfig,
                progress: Callable[[str], None] | None, findings: list[Finding],
                table: list[Candidate], oof: dict[str, dict[str, np.ndarray]],
                joint: list[Candidate], suspect: list[Finding]
                ) -> tuple[list[Hypothesis], int]:
    """Add the significant explanations, best first, to the model of every residual they
    move; returns the chain and the number of steps taken."""
    primary = {v: c.ctx for v, c in views.items() if not c.secondary}
    second = {v: c.ctx for v, c in views.items() if c.secondary}
    hs = hypotheses(primary, effects=cfg.effects, onset=cfg.onset,
                    sensor_effects=cfg.sensor_effects, secondary=second)
    measured = {c.ctx.signal for c in views.values()}
    chain: list[Hypothesis] = []
    nit = 0
    for step in range(cfg.max_findings):
        nit += 1
        for c in views.values():
            c.ctx.cache.clear()
        st = _held_out_chain(views, chain)
        if step == 0:
            for v in primary:
                oof.setdefault(v, {})["before"] = st.before[v]
        todo = [h for h in hs if h not in chain]
        sc = _Scoring()
        _score_all(views, todo, st, set(primary), sc)
        todo = [h for h in todo if id(h) in sc.mse_a and sc.mse_a[id(h)]]
        if not todo:
            break
        level = _noise_levels(views, st, sc, todo)
        prim = {v: views[v] for v in primary}
        score_b = _joint_blocks(prim, {v: st.mse_b[v] for v in prim}, level)
        base = float(np.nanmean(score_b))
        scored = [(h, _candidate(prim, h, st, sc, level, score_b)) for h in todo]
        # Bonferroni over the effect shapes tested on the measured channels: an input
        # sensor's error is one more carrier of a shape the channel's own candidates already
        # test (its residual following the model's sensitivity to that sensor), a question
        # of attribution among explanations rather than one more chance of a false discovery
        m = max(1, sum((not h.signal or h.carrier in measured) and not _linear_case(h)
                       for h, _ in scored))
        scored = [(h, replace(c, p_adjusted=min(1.0, c.p_value * m))) for h, c in scored]
        if step == 0:
            table.extend(c for _, c in scored)
        # the choice is made among the significant explanations when there are any (a
        # better but unproven one is reported beside it as a tie)
        pool = [(h, c) for h, c in scored
                if c.p_adjusted < cfg.alpha and c.gain_pct >= cfg.min_gain_pct]
        n_eff = _effective_n(views, st) if cfg.penalty else 0.0
        h, choice = _one_se_choice(pool or scored, cfg.alpha, n_eff)
        sig = choice.p_adjusted < cfg.alpha and choice.gain_pct >= cfg.min_gain_pct
        ties_from = scored
        suspected = not sig and step == 0 and choice.gain_pct >= SUSPECT_GAIN_PCT
        if second and (sig and _relevant(views, chain, h) or suspected):
            # the leading explanations are checked on the secondary residuals too: scored
            # jointly over every residual, the one that explains all of them is named (and,
            # when nothing is significant, reported as the suspect)
            h, choice, ties_from, base = _judged_jointly(views, scored, choice, base, st, sc,
                                                         cfg, n_eff)
            if step == 0:
                joint.extend(c for _, c in ties_from)
        if progress and sig and second:
            def per_residual(c: Candidate) -> str:
                return "/".join(f"{c.per_residual.get(v, np.nan):.3g}" for v in views)
            progress(f"step {step + 1}: leading explanations, held-out score (every residual in "
                     f"units of its noise level; {'/'.join(views)}): " + ", ".join(
                         f"{c.label} on {c.channel} {np.nanmean(c.mse_blocks):.4g} "
                         f"({per_residual(c)})"
                         for _, c in sorted(ties_from, key=lambda hc: np.nanmean(
                             hc[1].mse_blocks))[:6]))
        if progress:
            progress(f"step {step + 1}: best {choice.label} on {choice.channel} gain "
                     f"{choice.gain_pct:.1f}% p_adj {choice.p_adjusted:.2g}"
                     f"{' (significant)' if sig else ''}")
        alternatives = _alternatives(views, chain, ties_from, choice, h.primary, base,
                                     cfg.alpha) if sig or suspected else []
        if not sig:
            if suspected:
                # nothing significant: the best explanation (over every residual where others
                # check it), fitted on every valid sample, is reported as the suspect (not a
                # finding)
                oks = {v: c.ok for v, c in views.items()}
                params = _fit_in(views, h, _fit_all(views, chain, oks), oks, refine=True)[0]
                suspect.append(_finding(h, choice, step, alternatives, significant=False,
                                        params=params))
            break
        chain.append(h)
        for v, a in sc.after[id(h)].items():
            if v in primary:
                oof.setdefault(v, {})[f"after_{step + 1}"] = a
        findings.append(_finding(h, choice, step, alternatives))
    return chain, nit


# Held-out gain [%] from which the best explanation of a record with no significant finding
# is reported as the suspect (judged on every residual, with its parameters and ties): a user
# reads "consistent" together with what, if anything, came closest
SUSPECT_GAIN_PCT = 10.0
MIN_GAIN_EFFECT = 0.01  # relevance floor of a gain error: |gain - 1| [1]
MIN_EFFECT_REL = 0.01  # relevance floor of any effect: its error / RMS of the reading
# ... and of an input sensor's error, also what it moves the channel's prediction by / RMS of
# the channel: a quarter of the channel's accuracy class (measured: a T2 lag fitted to the
# model's own transient error on fault-free data moves the flow prediction by 0.08 %; the
# smallest p2 dead time stated detectable, 0.3 s, by 0.9 %)
MIN_PROPAGATED_REL = 0.0025


def _gain_magnitude(params: dict[str, Any]) -> float:
    """Largest |gain - 1| of a fitted gain error (constant, from an onset, or piecewise)."""
    vals = [abs(float(v)) for v in params.get("values", ())]
    if "gain" in params:
        vals.append(abs(float(params["gain"]) - 1.0))
    return max(vals, default=0.0)


def _relative_size(c: _Channel, eff: Effect, p: dict[str, Any], pred: np.ndarray,
                   nxt: np.ndarray) -> float:
    """The size of an effect against the reading it errs on (see :func:`_refit`)."""
    ctx = c.ctx
    if isinstance(eff, SensorError):
        e, x = eff.error(ctx, p), ctx.sensor_reading(eff.sensor)
        ok = c.ok & np.isfinite(e) & np.isfinite(x)
        # a lag or dead time errs only while the reading moves: judged against how much it
        # moves (its standard deviation), the other errors against the reading
        timing = eff.kind in ("sensor_lag", "dead_time")
        ref = (float(np.std(x[ok]) if timing else np.sqrt(np.mean(x[ok] ** 2)))
               if ok.any() else 0.0)
        e = e[ok]
    else:
        e, ref = (nxt - pred)[c.ok], float(np.sqrt(np.mean(ctx.y[c.ok] ** 2)))
        e = e[np.isfinite(e)]
    mag = 0.0
    if e.size:
        mag = float(np.max(np.abs(e)) if eff.id == "drift" else np.sqrt(np.mean(e ** 2)))
    return mag / ref if ref > 0 else 0.0


def _negligible(c: _Channel, eff: Effect, p: dict[str, Any], pred: np.ndarray,
                nxt: np.ndarray) -> bool:
    """Whether an effect stays below the relevance floor (see :func:`_refit`): its size
    against the reading it errs on, and for an input sensor's error also what it moves the
    channel's prediction by."""
    if _relative_size(c, eff, p, pred, nxt) < MIN_EFFECT_REL:
        return True
    if not isinstance(eff, SensorError):
        return False
    shift = (nxt - pred)[c.ok]
    shift = shift[np.isfinite(shift)]
    level = float(np.sqrt(np.mean(c.ctx.y[c.ok] ** 2)))
    moved = float(np.sqrt(np.mean(shift ** 2))) / level if shift.size and level > 0 else 0.0
    return moved < MIN_PROPAGATED_REL


def _relevant(views: dict[str, _Channel], chain: list[Hypothesis], h: Hypothesis) -> bool:
    """Whether ``h``, fitted on every valid sample on top of the chain, reaches the relevance
    floor of :func:`_refit` (a detection whose best explanation is a negligible wander is not
    handed on to the attribution among the other residuals: it stays the model's wander)."""
    oks = {v: c.ok for v, c in views.items()}
    preds = _fit_all(views, chain, oks)
    ps = _fit_in(views, h, preds, oks)
    v0, e0 = h.members[0]
    if e0.id == "gain_error" and _gain_magnitude(ps[0]) < MIN_GAIN_EFFECT:
        return False
    nxt = e0.apply(views[v0].ctx, preds[v0], ps[0])
    return not _negligible(views[v0], e0, ps[0], preds[v0], nxt)


def _refit(views: dict[str, _Channel], chain: list[Hypothesis], findings: list[Finding],
           summary: dict[str, dict[str, Any]]
           ) -> dict[str, list[tuple[Effect, dict[str, Any]]]]:
    """The extension as saved: the chain refitted on every valid sample, per residual; the
    findings get the parameters of their first member.

    A gain error below the relevance floor (every piece within MIN_GAIN_EFFECT of 1, the
    order of a sensor's own accuracy class) is a real but negligible wander of the model,
    not a deficiency worth naming: it stays in the candidate table, not among the findings.
    Any other effect is held to the same floor by its size: the error it puts on a reading
    (the channel's, or an input sensor's) must reach MIN_EFFECT_REL of that reading's RMS (a
    sensor's accuracy class, 1 % of reading) in RMS over the record, a drift by what it
    accumulates, an input sensor's lag or dead time against how much the reading moves,
    and an input sensor's error also by how much it moves the channel's prediction
    (MIN_PROPAGATED_REL: a T2 lag of 0.3 s while T2 wanders by 2 K changes the predicted flow
    by less than 0.1 %); smaller effects are real but negligible wanders of the model.
    """
    for c in views.values():
        c.ctx.cache.clear()
    oks = {v: c.ok for v, c in views.items()}
    fitted: list[list[dict[str, Any]]] = []
    _fit_all(views, chain, oks, refine=True, params_out=fitted)
    for c in views.values():
        c.ctx.cache.clear()
        c.ctx.folds, c.ctx.fold_ids = None, {}
    chains: dict[str, list[tuple[Effect, dict[str, Any]]]] = {v: [] for v in views}
    preds = {v: c.ctx.yhat for v, c in views.items()}
    small = []
    for h, ps in zip(chain, fitted):
        first = True
        for (v, eff), p in zip(h.members, ps):
            if v not in views:
                continue
            nxt = eff.apply(views[v].ctx, preds[v], p)
            if first:
                small.append(_negligible(views[v], eff, p, preds[v], nxt))
                first = False
            chains[v].append((eff, p))
            preds[v] = nxt
    for f_i, f in enumerate(findings):
        if not f.params and f.step <= len(fitted):
            findings[f_i] = replace(f, params=fitted[f.step - 1][0])
    findings[:] = [f for f in findings
                   if not ((f.effect == "gain_error"
                            and _gain_magnitude(f.params) < MIN_GAIN_EFFECT)
                           or small[f.step - 1])]
    for v, c in views.items():
        if v in summary and not c.secondary:
            summary[v]["rmse_extended_in_sample"] = float(np.sqrt(np.mean(
                c.err(preds[v])[c.ok] ** 2)))
    return chains


def _conclude(findings: list[Finding], table: list[Candidate],
              summary: dict[str, dict[str, Any]], alpha: float = 0.05,
              suspect: Finding | None = None) -> tuple[list[Finding], str, str, bool]:
    """Findings ranked, the verdict and its message, and whether any channel was analysed.

    The findings keep the order they were chosen in: each step's explanation was the best
    over every residual at once, and a later one explains what the earlier ones left (its
    held-out gain is of that remainder, not comparable with the first's)."""
    findings = [replace(f, rank=i + 1) for i, f in enumerate(findings)]
    table.sort(key=lambda c: -c.gain_pct)
    verdict, msg = _verdict(findings, table, alpha, suspect)
    skipped = {ch: c["status"] for ch, c in summary.items() if "status" in c}
    success = len(skipped) < len(summary)
    if not success:
        # nothing was analysed (e.g. every sample outside the identified region): say so
        verdict = "invalid"
        msg = "no channel could be analysed: " + "; ".join(f"{k}: {v}" for k, v in
                                                          skipped.items())
    elif skipped:
        msg += " (not analysed: " + "; ".join(f"{k}: {v}" for k, v in skipped.items()) + ")"
    return findings, verdict, msg, success


def _views(contexts: dict[str, ChannelContext], secondary: dict[str, ChannelContext],
           cfg: DiscrepancyConfig, summary: dict[str, dict[str, Any]]) -> dict[str, _Channel]:
    """Blocks and folds of every residual: the same time blocks for all of them (a fold
    holds out the same stretch of time in every residual)."""
    spans = []
    for ch, ctx in contexts.items():
        ok = ctx.ok
        n_ok = int(ok.sum())
        summary[ch] = {"unit": ctx.unit, "n_samples": ctx.n, "n_valid": n_ok,
                       "n_masked": ctx.n - n_ok}
        if ctx.measured:
            summary[ch]["measures"] = ctx.measured
        if _n_blocks(ctx, cfg, dict(summary[ch])) is not None:
            spans.append((float(ctx.t[ok][0]), float(ctx.t[ok][-1])))
    views: dict[str, _Channel] = {}
    if not spans:
        for ch, ctx in contexts.items():
            _n_blocks(ctx, cfg, summary[ch])
        return views
    t0, t1 = min(a for a, _ in spans), max(b for _, b in spans)
    nb = cfg.n_blocks or int(np.clip(round((t1 - t0) / cfg.block_s), 24, 60))
    every = [(ch, ctx, False) for ch, ctx in contexts.items()]
    every += [(ch, ctx, True) for ch, ctx in secondary.items()]
    for ch, ctx, sec in every:
        info = summary.setdefault(ch, {"unit": ctx.unit, "n_samples": ctx.n,
                                       "n_valid": int(ctx.ok.sum()),
                                       "n_masked": ctx.n - int(ctx.ok.sum())})
        ok = ctx.ok
        info["n_blocks"] = nb
        if int(ok.sum()) < 20 * nb:
            info["status"] = f"too few valid samples ({int(ok.sum())}) for {nb} blocks"
            continue
        blk = make_blocks(ctx.t, ok, nb, span=(t0, t1))
        trains, tests = _folds(ctx, cfg, blk, nb, ok)
        views[ch] = _Channel(ch, ctx, blk, nb, trains, tests, ok, secondary=sec)
        resid0 = ctx.pulsation(ctx.y - ctx.yhat)
        info["rmse_baseline"] = float(np.sqrt(np.mean(resid0[ok] ** 2)))
        info["bias_baseline"] = float(np.mean(resid0[ok]))
        if sec:
            info["checks_only"] = True
    return views


def analyse(contexts: dict[str, ChannelContext], *, config: DiscrepancyConfig | None = None,
            progress: Callable[[str], None] | None = None,
            secondary: dict[str, ChannelContext] | None = None) -> DiscrepancyResult:
    """Find, name, extend and score the model's discrepancies in measured data.

    Parameters
    ----------
    contexts : per residual, measured values, baseline prediction and explanations
        (:func:`fdi_ros.core.discrepancy.context.build_contexts`); all are analysed
        together: an error of a signal is one hypothesis over every residual that reads the
        signal (:mod:`.joint`).
    config : settings; see :class:`DiscrepancyConfig`.
    progress : optional callable(str) for status lines.
    secondary : residuals that check the leading explanations without proposing any (e.g.
        the pulsation of a channel whose mean-value effects are found on segment means).

    Returns
    -------
    DiscrepancyResult with the ranked findings (by held-out gain), the step-1 candidate table,
    the verdict ("consistent" when no finding is significant, else "discrepant"), per residual
    the baseline RMSE, and the fitted extension chains (refitted on all valid samples).
    """
    cfg = config or DiscrepancyConfig()
    t0 = time.perf_counter()
    findings: list[Finding] = []
    table: list[Candidate] = []
    summary: dict[str, dict[str, Any]] = {}
    oof: dict[str, dict[str, np.ndarray]] = {}
    views = _views(contexts, secondary or {}, cfg, summary)
    chains: dict[str, list[tuple[Effect, dict[str, Any]]]] = {ch: [] for ch in contexts}
    nit = 0
    joint: list[Candidate] = []
    suspect: list[Finding] = []
    if any(not c.secondary for c in views.values()):
        chain, nit = _grow_chain(views, cfg, progress, findings, table, oof, joint, suspect)
        chains.update({v: ch for v, ch in _refit(views, chain, findings, summary).items()
                       if v in contexts})
    findings, verdict, msg, success = _conclude(findings, table,
                                                {k: v for k, v in summary.items()
                                                 if k in contexts}, cfg.alpha,
                                                suspect[0] if suspect else None)
    return DiscrepancyResult(findings=findings, candidates=table, verdict=verdict, message=msg,
                             success=success, channels=summary, chains=chains,
                             n_blocks=max([c.get("n_blocks", 0) for c in summary.values()]
                                          or [0]), nit=nit,
                             seconds=time.perf_counter() - t0, config=cfg, oof=oof,
                             joint=joint, suspect=suspect[0] if suspect else None)


def merge_results(a: DiscrepancyResult, b: DiscrepancyResult, *, b_suffix: str,
                  b_channels: bool = True) -> DiscrepancyResult:
    """One result from two analyses (e.g. mean-value and crank-resolved views of a channel).

    Findings are merged by held-out gain, each analysis' own in the order they were chosen
    (:func:`_conclude`); chains are concatenated per channel (``b``'s extensions act on top of
    ``a``'s); ``b``'s channel summaries get ``b_suffix``.
    """
    qa, qb, findings = list(a.findings), list(b.findings), []
    while qa or qb:
        take_a = bool(qa) and (not qb or qa[0].gain_pct >= qb[0].gain_pct)
        findings.append((qa if take_a else qb).pop(0))
    findings = [Finding(**{**f.__dict__, "rank": i + 1}) for i, f in enumerate(findings)]
    chains = {ch: list(a.chains.get(ch, [])) + list(b.chains.get(ch, []))
              for ch in set(a.chains) | set(b.chains)}
    channels = dict(a.channels if b_channels else b.channels)
    if b_channels:
        channels.update({f"{ch}{b_suffix}": v for ch, v in b.channels.items()})
    else:
        channels.update({f"{ch} (crank-resolved)": v for ch, v in a.channels.items()})
    cands = sorted(a.candidates + b.candidates, key=lambda c: -c.gain_pct)
    suspect = a.suspect or b.suspect
    verdict, msg = _verdict(findings, cands, a.config.alpha, suspect)
    if not (a.success and b.success):
        verdict = "invalid"
        msg = "; ".join(r.message for r in (a, b) if not r.success)
    return DiscrepancyResult(findings=findings, candidates=cands, verdict=verdict, message=msg,
                             success=a.success and b.success, channels=channels,
                             chains=chains, n_blocks=max(a.n_blocks, b.n_blocks),
                             nit=a.nit + b.nit, seconds=a.seconds + b.seconds,
                             config=a.config, oof=a.oof, joint=a.joint + b.joint,
                             suspect=None if findings else suspect)
