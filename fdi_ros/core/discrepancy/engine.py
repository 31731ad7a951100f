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

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from fdi_ros.core.discrepancy.context import ChannelContext
from fdi_ros.core.discrepancy.effects import CATALOGUE, Effect, SensorError, candidates
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

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = _jsonable({
            "verdict": self.verdict,
            "message": self.message,
            "success": self.success,
            "findings": [f.to_dict() for f in self.findings],
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


def make_blocks(t: np.ndarray, ok: np.ndarray, n_blocks: int) -> np.ndarray:
    """Block id per sample (-1 where not ok): equal-duration contiguous blocks."""
    tv = t[ok]
    edges = np.linspace(tv[0], tv[-1], n_blocks + 1)
    blk = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, n_blocks - 1)
    return np.where(ok, blk, -1)


def fit_chain(ctx: ChannelContext, chain: list[Effect], train: np.ndarray, *,
              refine: bool = False) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """Fit the effects one after the other on ``train``; the full-length prediction."""
    pred = ctx.yhat
    params = []
    for eff in chain:
        p = eff.fit(ctx, pred, train, refine=refine)
        pred = eff.apply(ctx, pred, p)
        params.append(p)
    return pred, params


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


def _nests(big: Effect, small: Effect) -> bool:
    """True when ``small`` is a special case of ``big`` (the same effect with fewer change
    times: always on < after an onset < piecewise constant in time)."""
    if big.id != small.id or getattr(big, "sensor", "") != getattr(small, "sensor", ""):
        return False
    if getattr(big, "piecewise", False):
        return not getattr(small, "piecewise", True)
    return getattr(big, "onset", False) and not getattr(small, "onset", True) and not getattr(
        small, "piecewise", True)


def _one_se_choice(scored: list[tuple[Effect, Candidate]], alpha: float
                   ) -> tuple[Effect, Candidate]:
    """Lowest held-out MSE, or a special case of it within one standard error of it.

    Nested alternatives compete on parsimony (an always-on gain error vs the same gain
    switching on at some time), and a time-varying best (drift, piecewise in time) yields to a
    dependence on a measured column within one standard error; an input sensor's error yields
    to the same kind of error of the channel within one standard error, and a dependence on an
    input's slope to that input's lag or dead time unless it is significantly worse; other
    effects with different physics compete on held-out error.
    """
    best = min(scored, key=lambda ec: np.nanmean(ec[1].mse_blocks))
    tol = 1e-3 * float(np.nanmean(best[1].mse_blocks))

    def within_one_se(c: Candidate) -> bool:
        d = c.mse_blocks - best[1].mse_blocks
        d = d[np.isfinite(d)]
        return bool(d.size >= 3 and d.mean() <= np.std(d, ddof=1) / np.sqrt(d.size) + tol)

    if getattr(best[0], "sensor", ""):
        # the same kind of error on the analysed channel itself, within one standard error of
        # an input sensor's: the channel's own error is named (it needs no second faulty
        # sensor), the input sensor's stays among the reported ties
        own = [(eff, c) for eff, c in scored if not getattr(eff, "sensor", "")
               and eff.id == best[0].id and c.p_adjusted < alpha and within_one_se(c)]
        if own:
            best = min(own, key=lambda ec: np.nanmean(ec[1].mse_blocks))
    column = str(getattr(best[0], "column", ""))
    if best[0].id == "input_dependence" and column.startswith("d/dt "):
        # the residual following the slope of one of the model's inputs is what a lag or
        # dead time of that sensor produces (to first order the same explanation): unless it
        # is significantly worse, the sensor's timing error is named (as many parameters, and
        # it predicts through the model)
        timing = [(eff, c) for eff, c in scored
                  if getattr(eff, "sensor", "") == column[5:]
                  and eff.id in ("sensor_lag", "dead_time") and c.p_adjusted < alpha
                  and paired_p(c.mse_blocks, best[1].mse_blocks) >= alpha]
        if timing:
            best = min(timing, key=lambda ec: np.nanmean(ec[1].mse_blocks))
    if _time_varying(best[0]):
        # a change over time is accepted only if no measured column explains the same
        # residual: a dependence on a measured signal (few parameters, predicts new data)
        # beats a drift or a piecewise-in-time fit within one standard error of it
        measured = [(eff, c) for eff, c in scored if eff.id == "input_dependence"
                    and eff.n_params <= best[0].n_params and c.p_adjusted < alpha
                    and within_one_se(c)]
        if measured:
            return min(measured, key=lambda ec: np.nanmean(ec[1].mse_blocks))
    eligible = [best]
    for eff, c in scored:
        if not _nests(best[0], eff) or c.p_adjusted >= alpha:
            continue
        if within_one_se(c):
            eligible.append((eff, c))
    return min(eligible, key=lambda ec: (ec[0].n_params, np.nanmean(ec[1].mse_blocks)))


def _time_varying(eff: Effect) -> bool:
    """Drift, or an effect piecewise constant in time."""
    return eff.id == "drift" or bool(getattr(eff, "piecewise", False))


def _verdict(findings: list[Finding], table: list[Candidate], alpha: float = 0.05
             ) -> tuple[str, str]:
    """Verdict and one-line message from the findings and the candidate table (``alpha``: the
    significance level, to tell a candidate dropped as too small from an inconsistent one)."""
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
    return "consistent", msg


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
    """One channel under analysis: its context, folds and blocks."""

    name: str
    ctx: ChannelContext
    blk: np.ndarray
    nb: int
    trains: list[np.ndarray]
    tests: list[np.ndarray]
    ok: np.ndarray  # valid samples (one array for the whole analysis of the channel)

    def rmse(self, pred: np.ndarray) -> float:
        return float(np.sqrt(np.nanmean((self.ctx.y - pred)[self.ok] ** 2)))

    def block_mse(self, pred: np.ndarray) -> np.ndarray:
        return _block_mse((self.ctx.y - pred) ** 2, self.blk, self.nb)


def _held_out_chain(c: _Channel, chain: list[Effect]) -> tuple[list[np.ndarray], np.ndarray]:
    """Per fold the chain's prediction, and the held-out prediction of every sample."""
    bases = []
    before = np.full(c.ctx.n, np.nan)
    for tr, te in zip(c.trains, c.tests):
        pred, _ = fit_chain(c.ctx, chain, tr)
        bases.append(pred)
        before[te] = pred[te]
    return bases, before


def _score(c: _Channel, eff: Effect, bases: list[np.ndarray], before: np.ndarray,
           rmse_b: float, mse_b: np.ndarray) -> tuple[Candidate, np.ndarray] | None:
    """Held-out score of one candidate effect on top of the chain (None: it cannot fit)."""
    ctx = c.ctx
    after = np.full(ctx.n, np.nan)
    try:
        for base, tr, te in zip(bases, c.trains, c.tests):
            params = eff.fit(ctx, base, tr)
            after[te] = eff.apply(ctx, base, params)[te]
    except (np.linalg.LinAlgError, ValueError, FloatingPointError):
        return None
    # a candidate that cannot predict a sample leaves the model's value there
    after = np.where(np.isfinite(after), after, before)
    mse_a = c.block_mse(after)
    rmse_a = c.rmse(after)
    p = paired_p(mse_b, mse_a)
    p_dm, _ = loss_differential_p(ctx.y - before, ctx.y - after)
    return Candidate(effect=eff.id, label=eff.label, channel=carrier(eff, c.name),
                     n_params=eff.n_params,
                     rmse_before=rmse_b, rmse_after=rmse_a,
                     gain_pct=100.0 * (1.0 - rmse_a / rmse_b), p_value=p, p_adjusted=p,
                     p_dm=p_dm, mse_blocks=mse_a), after


def carrier(eff: Effect, channel: str) -> str:
    """The signal an effect is an error of: the input sensor of a sensor error, else the
    channel whose residual is analysed."""
    return str(getattr(eff, "sensor", "") or channel)


# A significant explanation that achieves all but this share of the named one's held-out
# RMSE gain is reported as a tie: what remains after either is the model's own error, and a
# difference of a few percent of the gain is no evidence for one cause over the other.
PRACTICAL_TIE = 0.05


def _alternatives(c: _Channel, chain: list[Effect], scored: list[tuple[Candidate, np.ndarray]],
                  choice: Candidate, by_label: dict[str, Effect], alpha: float = 0.05,
                  max_ties: int = 8) -> list[dict[str, Any]]:
    """Other explanations the held-out data cannot tell apart from the choice, with their own
    parameters fitted on every valid sample: within one standard error of it, or significant
    themselves and not significantly worse than it (one-sided Wilcoxon over the blocks, level
    ``alpha``), one per effect and carrier (its best variant), best first; then those that
    are significant and achieve at least 1 - :data:`PRACTICAL_TIE` of the choice's held-out
    gain (its simplest such variant): a difference that small, however significant with
    little noise, does not say which explanation is true."""
    alternatives: list[dict[str, Any]] = []
    full_pred = None
    seen = {(choice.effect, choice.channel)}
    ranked = [cand for cand, _ in sorted(scored,
                                         key=lambda ca: float(np.nanmean(ca[0].mse_blocks)))]

    def add(cand: Candidate, basis: str) -> None:
        nonlocal full_pred
        if full_pred is None:
            full_pred, _ = fit_chain(c.ctx, chain, c.ok)
        alt = by_label[cand.label]
        alt_d = {"effect": cand.effect, "label": cand.label, "channel": cand.channel,
                 "gain_pct": cand.gain_pct, "p_adjusted": cand.p_adjusted,
                 "params": alt.fit(c.ctx, full_pred, c.ok, refine=True)}
        alt_d.update(tie_reason(choice, cand, c.name, basis))
        alternatives.append(alt_d)
        seen.add((cand.effect, cand.channel))

    for cand in ranked:
        if (cand.effect, cand.channel) in seen:
            continue  # one alternative per effect and channel: its best variant
        d = cand.mse_blocks - choice.mse_blocks
        d = d[np.isfinite(d)]
        if d.size < 3 or len(alternatives) >= max_ties:
            continue
        if d.mean() <= np.std(d, ddof=1) / np.sqrt(d.size):
            add(cand, "held-out error within one standard error")
        elif cand.p_adjusted < alpha and paired_p(cand.mse_blocks,
                                                  choice.mse_blocks) >= alpha:
            add(cand, "significant itself, and not significantly worse over the held-out "
                      "blocks")
    close = [cand for cand in ranked if cand.p_adjusted < alpha
             and cand.gain_pct >= (1.0 - PRACTICAL_TIE) * choice.gain_pct]
    for cand in sorted(close, key=lambda k: (k.n_params, float(np.nanmean(k.mse_blocks)))):
        if (cand.effect, cand.channel) not in seen and len(alternatives) < max_ties:
            add(cand, f"held-out RMSE gain {cand.gain_pct:.1f} % against "
                      f"{choice.gain_pct:.1f} %: within {PRACTICAL_TIE:.0%} of it")
    return alternatives


def _grow_chain(c: _Channel, cfg: DiscrepancyConfig, n_channels: int,
                progress: Callable[[str], None] | None,
                findings: list[Finding], table: list[Candidate],
                oof: dict[str, np.ndarray]) -> tuple[list[Effect], int]:
    """Add the significant effects of one channel, best first; returns the chain and the
    number of steps taken."""
    ctx = c.ctx
    cands = candidates(ctx, effects=cfg.effects, onset=cfg.onset,
                       sensor_effects=cfg.sensor_effects)
    by_label = {e.label: e for e in cands}
    chain: list[Effect] = []
    nit = 0
    for step in range(cfg.max_findings):
        nit += 1
        ctx.cache.clear()
        bases, before = _held_out_chain(c, chain)
        mse_b = c.block_mse(before)
        rmse_b = c.rmse(before)
        if step == 0:
            oof["before"] = before
        scored = [sc for eff in cands if not any(e.label == eff.label for e in chain)
                  if (sc := _score(c, eff, bases, before, rmse_b, mse_b)) is not None]
        if not scored:
            break
        # Bonferroni over the effect shapes tested on the channel: an input sensor's error is
        # one more carrier of a shape the channel's own candidates already test (its
        # residual following the model's sensitivity to that sensor), a question of
        # attribution among explanations rather than one more chance of a false discovery
        m = max(1, sum(cand.channel == c.name for cand, _ in scored)) * n_channels
        scored = [(Candidate(**{**cand.__dict__, "p_adjusted": min(1.0, cand.p_value * m)}), a)
                  for cand, a in scored]
        if step == 0:
            table.extend(cand for cand, _ in scored)
        # the choice is made among the significant explanations when there are any (a
        # better but unproven one is reported beside it as a tie)
        pool = [(by_label[cand.label], cand) for cand, _ in scored
                if cand.p_adjusted < cfg.alpha and cand.gain_pct >= cfg.min_gain_pct]
        eff, choice = _one_se_choice(pool or [(by_label[cand.label], cand)
                                              for cand, _ in scored], cfg.alpha)
        sig = choice.p_adjusted < cfg.alpha and choice.gain_pct >= cfg.min_gain_pct
        if progress:
            progress(f"{c.name} step {step + 1}: best {choice.label} gain "
                     f"{choice.gain_pct:.1f}% p_adj {choice.p_adjusted:.2g}"
                     f"{' (significant)' if sig else ''}")
        if not sig:
            break
        alternatives = _alternatives(c, chain, scored, choice, by_label, cfg.alpha)
        chain.append(eff)
        oof[f"after_{step + 1}"] = next(a for cand, a in scored if cand is choice)
        findings.append(Finding(rank=0, effect=choice.effect, label=choice.label,
                                channel=choice.channel, model_channel=c.name, params={},
                                rmse_before=choice.rmse_before,
                                rmse_after=choice.rmse_after, gain_pct=choice.gain_pct,
                                p_value=choice.p_value, p_adjusted=choice.p_adjusted,
                                p_dm=choice.p_dm, significant=True,
                                n_params=choice.n_params, step=step + 1,
                                alternatives=alternatives))
    return chain, nit


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


def _effect_size(eff: Effect, err: np.ndarray, ref: float) -> float:
    """The error an effect puts on a signal relative to ``ref``: a drift by what it
    accumulates (its largest value), any other effect by its RMS."""
    if not err.size or ref <= 0:
        return 0.0
    mag = float(np.max(np.abs(err)) if eff.id == "drift" else np.sqrt(np.mean(err ** 2)))
    return mag / ref


def _refit(c: _Channel, chain: list[Effect], findings: list[Finding], info: dict[str, Any]
           ) -> list[tuple[Effect, dict[str, Any]]]:
    """The extension as saved: the chain refitted on every valid sample; the channel's
    findings get these parameters."""
    ctx = c.ctx
    ctx.cache.clear()
    _, params = fit_chain(ctx, chain, c.ok, refine=True)
    ctx.cache.clear()
    ctx.folds, ctx.fold_ids = None, {}
    fitted = list(zip(chain, params))
    for f_i, f in enumerate(findings):
        if f.model_channel == c.name and not f.params:
            findings[f_i] = Finding(**{**f.__dict__, "params": params[f.step - 1]})
    # A gain error below the relevance floor (every piece within MIN_GAIN_EFFECT of 1, the
    # order of a sensor's own accuracy class) is a real but negligible wander of the model,
    # not a deficiency worth naming: it stays in the candidate table, not among the findings.
    # Any other effect is held to the same floor by its size: the error it puts on a reading
    # (the channel's, or an input sensor's) must reach MIN_EFFECT_REL of that reading's RMS
    # (a sensor's accuracy class, 1 % of reading) in RMS over the record, a drift by what it
    # accumulates, an input sensor's lag or dead time against how much the reading moves,
    # and an input sensor's error also by how much it moves the channel's prediction;
    # smaller effects are real but negligible wanders of the model.
    level = float(np.sqrt(np.mean(ctx.y[c.ok] ** 2)))
    pred, small = ctx.yhat, []
    for eff, p in fitted:
        nxt = eff.apply(ctx, pred, p)
        shift = (nxt - pred)[c.ok]
        moved = _effect_size(eff, shift[np.isfinite(shift)], level)
        if not isinstance(eff, SensorError):
            small.append(moved < MIN_EFFECT_REL)
        else:
            e, x = eff.error(ctx, p), ctx.sensor_reading(eff.sensor)
            ok = c.ok & np.isfinite(e) & np.isfinite(x)
            # a lag or dead time errs only while the reading moves: judged against how much
            # it moves (its standard deviation), the other errors against the reading; and
            # an input sensor's error must also move the channel's prediction by
            # MIN_PROPAGATED_REL (a T2 lag of 0.3 s while T2 wanders by 2 K changes the
            # predicted flow by less than 0.1 %: real or not, no deficiency worth naming)
            timing = eff.kind in ("sensor_lag", "dead_time")
            ref = (float(np.std(x[ok]) if timing else np.sqrt(np.mean(x[ok] ** 2)))
                   if ok.any() else 0.0)
            small.append(_effect_size(eff, e[ok], ref) < MIN_EFFECT_REL
                         or moved < MIN_PROPAGATED_REL)
        pred = nxt
    findings[:] = [f for f in findings
                   if not (f.model_channel == c.name
                           and ((f.effect == "gain_error"
                                 and _gain_magnitude(f.params) < MIN_GAIN_EFFECT)
                                or small[f.step - 1]))]
    final = apply_chain(ctx, fitted)
    info["rmse_extended_in_sample"] = float(np.sqrt(np.mean((ctx.y - final)[c.ok] ** 2)))
    return fitted


def _conclude(findings: list[Finding], table: list[Candidate],
              summary: dict[str, dict[str, Any]], alpha: float = 0.05
              ) -> tuple[list[Finding], str, str, bool]:
    """Findings ranked, the verdict and its message, and whether any channel was analysed."""
    findings.sort(key=lambda f: -f.gain_pct)
    findings = [Finding(**{**f.__dict__, "rank": i + 1}) for i, f in enumerate(findings)]
    table.sort(key=lambda c: -c.gain_pct)
    verdict, msg = _verdict(findings, table, alpha)
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


def analyse(contexts: dict[str, ChannelContext], *, config: DiscrepancyConfig | None = None,
            progress: Callable[[str], None] | None = None) -> DiscrepancyResult:
    """Find, name, extend and score the model's discrepancies in measured data.

    Parameters
    ----------
    contexts : per channel, measured values, baseline prediction and explanations
        (:func:`fdi_ros.core.discrepancy.context.build_contexts`).
    config : settings; see :class:`DiscrepancyConfig`.
    progress : optional callable(str) for status lines.

    Returns
    -------
    DiscrepancyResult with the ranked findings (by held-out gain), the step-1 candidate table,
    the verdict ("consistent" when no finding is significant, else "discrepant"), per channel
    the baseline RMSE, and the fitted extension chains (refitted on all valid samples).
    """
    cfg = config or DiscrepancyConfig()
    t0 = time.perf_counter()
    findings: list[Finding] = []
    table: list[Candidate] = []
    chains: dict[str, list[tuple[Effect, dict[str, Any]]]] = {}
    summary: dict[str, dict[str, Any]] = {}
    oof: dict[str, dict[str, np.ndarray]] = {}
    nit = 0
    for ch, ctx in contexts.items():
        ok = ctx.ok
        n_ok = int(ok.sum())
        info = summary[ch] = {"unit": ctx.unit, "n_samples": ctx.n, "n_valid": n_ok,
                              "n_masked": ctx.n - n_ok}
        chains[ch] = []
        nb = _n_blocks(ctx, cfg, info)
        if nb is None:
            continue
        blk = make_blocks(ctx.t, ok, nb)
        trains, tests = _folds(ctx, cfg, blk, nb, ok)
        c = _Channel(ch, ctx, blk, nb, trains, tests, ok)
        resid0 = ctx.y - ctx.yhat
        info["rmse_baseline"] = float(np.sqrt(np.mean(resid0[ok] ** 2)))
        info["bias_baseline"] = float(np.mean(resid0[ok]))
        oof[ch] = {}
        chain, steps = _grow_chain(c, cfg, len(contexts), progress, findings, table, oof[ch])
        if not oof[ch]:
            del oof[ch]  # no step taken (max_findings = 0)
        nit += steps
        chains[ch] = _refit(c, chain, findings, info)
    findings, verdict, msg, success = _conclude(findings, table, summary, cfg.alpha)
    return DiscrepancyResult(findings=findings, candidates=table, verdict=verdict, message=msg,
                             success=success, channels=summary, chains=chains,
                             n_blocks=max([c.get("n_blocks", 0) for c in summary.values()]
                                          or [0]), nit=nit,
                             seconds=time.perf_counter() - t0, config=cfg, oof=oof)


def merge_results(a: DiscrepancyResult, b: DiscrepancyResult, *, b_suffix: str,
                  b_channels: bool = True) -> DiscrepancyResult:
    """One result from two analyses (e.g. mean-value and crank-resolved views of a channel).

    Findings are re-ranked by held-out gain; chains are concatenated per channel (``b``'s
    extensions act on top of ``a``'s); ``b``'s channel summaries get ``b_suffix``.
    """
    findings = sorted(a.findings + b.findings, key=lambda f: -f.gain_pct)
    findings = [Finding(**{**f.__dict__, "rank": i + 1}) for i, f in enumerate(findings)]
    chains = {ch: list(a.chains.get(ch, [])) + list(b.chains.get(ch, []))
              for ch in set(a.chains) | set(b.chains)}
    channels = dict(a.channels if b_channels else b.channels)
    if b_channels:
        channels.update({f"{ch}{b_suffix}": v for ch, v in b.channels.items()})
    else:
        channels.update({f"{ch} (crank-resolved)": v for ch, v in a.channels.items()})
    cands = sorted(a.candidates + b.candidates, key=lambda c: -c.gain_pct)
    verdict, msg = _verdict(findings, cands, a.config.alpha)
    if not (a.success and b.success):
        verdict = "invalid"
        msg = "; ".join(r.message for r in (a, b) if not r.success)
    return DiscrepancyResult(findings=findings, candidates=cands, verdict=verdict, message=msg,
                             success=a.success and b.success, channels=channels,
                             chains=chains, n_blocks=max(a.n_blocks, b.n_blocks),
                             nit=a.nit + b.nit, seconds=a.seconds + b.seconds,
                             config=a.config, oof=a.oof)
