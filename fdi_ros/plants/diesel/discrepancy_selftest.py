"""Randomised self-test of the discrepancy analysis on the diesel plant.

Every case draws at random: the effect (the whole catalogue, or none: a null case), the
channel (a sensor effect: the model's channel or any of its input sensors p2, T2, n; a model
effect: the model's channel), the size (log-uniform over the range stated detectable for that
channel in :data:`DETECTABLE` / :data:`SENSOR_DETECTABLE`, random sign), the plant run
(operating profile, noise seed, window start) and the extra measured columns (random smooth
shapes, random number of them; an input dependence acts through one of them). The effect is
hidden in the record with the independent implementations of :mod:`.scenarios` (a leak is
injected into the plant), the full analysis runs, and the top finding is compared with the
truth.

Summary: the confusion matrix (true effect x top-1 effect, ``none`` when no finding is
significant), the channel accuracy, the parameter error of the headline parameter, the false
discoveries on null cases and the ties (the truth among the top finding's statistically
indistinguishable alternatives).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from fdi_ros.plants.diesel import discrepancy_scenarios as sc

# Sizes the README states detectable on 60 s of 20 deg CA diesel data (maf in kg/h): the
# draw is log-uniform over each range, with a random sign where the effect has one.
DETECTABLE: dict[str, tuple[str, float, float]] = {
    "offset": ("offset", 3.0, 8.0),
    "gain_error": ("gain", 1.04, 1.12),
    "drift": ("rate_per_s", 0.08, 0.2),
    "sensor_lag": ("tau_s", 0.05, 0.4),
    "dead_time": ("delay_s", 0.03, 0.3),
    "input_dependence": ("coef", 4.0, 8.0),
    "missing_harmonic": ("amplitude", 3.0, 6.0),
    "local_region": ("offset", 6.0, 12.0),
    "leak": ("diameter_mm", 5.0, 9.0),
}
EFFECTS = tuple(DETECTABLE)
# share of the window's time a hidden local offset's speed band covers (drawn uniformly)
LOCAL_SHARE = (0.4, 0.7)
# Effects of the model itself (not of one sensor): shown on the channel it predicts.
MODEL_EFFECTS = ("missing_harmonic", "local_region", "leak")
# The same for the model's input sensors (units: p2 Pa, T2 K, n rpm), each seen only through
# the air-flow prediction the model makes from it; a sensor lag and a dead time of an input
# are told apart by nothing the mean-value model predicts (an honest tie).
SENSOR_DETECTABLE: dict[str, dict[str, tuple[str, float, float]]] = {
    "p2": {"offset": ("offset", 3000.0, 8000.0), "gain_error": ("gain", 1.04, 1.12),
           "drift": ("rate_per_s", 100.0, 300.0), "sensor_lag": ("tau_s", 0.3, 1.0),
           "dead_time": ("delay_s", 0.3, 1.0), "input_dependence": ("coef", 3000.0, 8000.0)},
    # T2 varies slowly: a lag or dead time of a few seconds moves the air-flow prediction
    # less than the relevance floor (1 % of reading); none is stated detectable
    "T2": {"offset": ("offset", 6.0, 15.0), "gain_error": ("gain", 1.04, 1.12),
           "drift": ("rate_per_s", 0.15, 0.4), "input_dependence": ("coef", 6.0, 15.0)},
    "n": {"offset": ("offset", 60.0, 150.0), "gain_error": ("gain", 1.04, 1.12),
          "drift": ("rate_per_s", 2.0, 5.0), "sensor_lag": ("tau_s", 0.3, 1.0),
          "dead_time": ("delay_s", 0.3, 1.0), "input_dependence": ("coef", 60.0, 150.0)},
}


def ranges(channel: str) -> dict[str, tuple[str, float, float]]:
    """The stated detectable range of every effect on ``channel``."""
    return SENSOR_DETECTABLE.get(channel, DETECTABLE)


def channels_for(effect: str, model_channels: tuple[str, ...]) -> list[str]:
    """Channels an effect can be hidden on: a sensor effect on any channel with a stated
    range (the model's own and its input sensors), a model effect on the model's channels."""
    if effect in MODEL_EFFECTS:
        return list(model_channels)
    return list(model_channels) + [c for c, r in SENSOR_DETECTABLE.items() if effect in r]


def _loguniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def draw_case(rng: np.random.Generator, effect: str | None, channel: str = "maf") -> dict:
    """Parameters of one hidden effect (``None``: a null case) on ``channel``."""
    if effect is None:
        return {}
    key, lo, hi = ranges(channel)[effect]
    size = _loguniform(rng, lo, hi)
    sign = 1.0 if rng.uniform() < 0.5 else -1.0
    if effect == "gain_error":
        return {"gain": size if sign > 0 else 1.0 / size}
    if effect in ("sensor_lag", "dead_time", "leak", "missing_harmonic"):
        p = {key: size}
        if effect == "missing_harmonic":
            p.update(order=float(rng.integers(2, 5)), phase_deg=float(rng.uniform(-180, 180)))
        return p
    if effect == "local_region":
        # a speed band >= 400-700 rpm wide where the window spends 40-70 % of its time (the
        # stated detectable range: a band visited briefly changes too few held-out blocks);
        # placed on the record by :func:`place_band`
        share = float(rng.uniform(*LOCAL_SHARE))
        return {"share": share, "width_rpm": float(rng.uniform(400.0, 700.0)),
                "offset": sign * size}
    return {key: sign * size}


def _extra_columns(rng: np.random.Generator, n_cols: int) -> list[dict]:
    """Random smooth shapes of the extra measured columns: per column its range and its sum
    of sinusoids (drawn in the order :func:`~.discrepancy_scenarios._smooth_random` draws)."""
    cols = []
    for _ in range(n_cols):
        lo = float(rng.uniform(-50.0, 300.0))
        hi = lo + float(rng.uniform(1.0, 40.0))
        periods = (float(rng.uniform(4.0, 15.0)), float(rng.uniform(30.0, 150.0)))
        waves = [(float(rng.uniform(*periods)), float(rng.uniform(0.5, 1.0)),
                  float(rng.uniform(0, 2 * np.pi))) for _ in range(int(rng.integers(2, 6)))]
        cols.append({"lo": lo, "hi": hi, "waves": waves})
    return cols


def _column(t: np.ndarray, spec: dict) -> np.ndarray:
    x = np.zeros_like(t)
    for per, amp, ph in spec["waves"]:
        x += amp * np.sin(2 * np.pi * t / per + ph)
    x = (x - x.min()) / max(x.max() - x.min(), 1e-12)
    return np.asarray(spec["lo"] + (spec["hi"] - spec["lo"]) * x, float)


def headline(effect: str, params: dict) -> float | None:
    """The one number a case is judged on (gain as gain - 1, input dependence: slope)."""
    if not params:
        return None
    if effect == "gain_error":
        return float(params["gain"]) - 1.0
    if effect == "input_dependence":
        c = params["coef"]
        return float(c[0] if isinstance(c, (list, tuple)) else c)
    return float(params[DETECTABLE[effect][0]])


@dataclass
class CaseResult:
    index: int
    effect: str | None
    channel: str
    truth: dict
    found: str | None
    found_channel: str | None
    found_params: dict
    tie: list = field(default_factory=list)
    tie_labels: list = field(default_factory=list)
    seconds: float = 0.0
    tie_channels: list = field(default_factory=list)

    @property
    def effect_right(self) -> bool:
        return self.found == self.effect

    @property
    def right(self) -> bool:
        """Top-1 effect and channel both right."""
        return self.effect is not None and self.effect_right and (
            self.found_channel == self.channel)

    @property
    def tied(self) -> bool:
        """Not top-1, but the truth is among the top finding's reported ties."""
        chans = self.tie_channels or [self.found_channel] * len(self.tie)
        return (self.effect is not None and not self.right
                and (self.effect, self.channel) in set(zip(self.tie, chans)))

    @property
    def param_rel_error(self) -> float | None:
        if self.effect is None or not self.effect_right:
            return None
        h, f = headline(self.effect, self.truth), headline(self.effect, self.found_params)
        if h is None or f is None or h == 0:
            return None
        return abs(f - h) / abs(h)

    def to_dict(self) -> dict:
        return {"index": self.index, "effect": self.effect, "channel": self.channel,
                "truth": self.truth, "found": self.found, "found_channel": self.found_channel,
                "found_params": self.found_params, "tie": self.tie,
                "tie_labels": self.tie_labels,
                "tie_channels": self.tie_channels,
                "effect_right": self.effect_right, "right": self.right, "tied": self.tied,
                "param_rel_error": self.param_rel_error, "seconds": self.seconds}


def draw_spec(index: int, rng: np.random.Generator, channels: tuple[str, ...],
              effect: str | None) -> dict:
    """Everything random about one case (replayable: :func:`run_spec` runs it)."""
    chans = channels_for(effect, channels) if effect else list(channels)
    channel = str(rng.choice(chans))
    params = draw_case(rng, effect, channel)
    seed = int(rng.integers(2000, 10**6))
    start = float(rng.uniform(0.0, 20.0))
    profile_seed = int(rng.integers(10**6))
    extra = _extra_columns(rng, int(rng.integers(1, 4)))
    if effect == "input_dependence":
        params["input"] = str(rng.choice([f"x{i + 1}" for i in range(len(extra))]))
    return {"index": index, "effect": effect, "channel": channel, "params": params,
            "seed": seed, "start": start, "profile_seed": profile_seed, "extra": extra}


def case_record(spec: dict, *, duration_s: float = 60.0):
    """The measured record of a case: a plant run with the effect hidden in it."""
    from fdi_ros.core.measured import Measured
    from fdi_ros.core.types import FaultEvent

    effect, params = spec["effect"], spec["params"]
    faults = []
    if effect == "leak":
        faults = [FaultEvent(t=0.0, fault="leak_ic_engine", size=params["diameter_mm"],
                             size_unit="mm")]
    start = spec["start"]
    rec = sc.plant_record(spec["seed"], duration_s=start + duration_s, faults=faults,
                          profile_seed=spec["profile_seed"])
    rec = rec.window(start, start + duration_s)
    extra = {f"x{i + 1}": _column(rec.t, c) for i, c in enumerate(spec["extra"])}
    sig = {k: v for k, v in rec.signals.items() if k not in ("T_amb", "u_aux")}
    units = {k: v for k, v in rec.units.items() if k not in ("T_amb", "u_aux")}
    sig.update(extra)
    units.update(dict.fromkeys(extra, "1"))
    rec = Measured(t=rec.t, signals=sig, units=units, alpha=rec.alpha, segment=rec.segment,
                   source=f"selftest case {spec['index']}", mapped=rec.mapped)
    if effect == "local_region" and "share" in params:
        params["n"] = place_band(rec["n"], params["width_rpm"], params["share"])
    if effect not in (None, "leak"):
        rec = sc.hide(rec, effect, params, channel=spec["channel"])
    return rec


def place_band(n: np.ndarray, width: float, share: float) -> tuple[float, float]:
    """The speed band at least ``width`` rpm wide whose share of the samples ``n`` is
    closest to ``share`` (the lowest such band, 10 rpm steps; widened in 50 rpm steps while
    no band of that width reaches the share, as on a window whose speed is spread wide)."""
    n = np.sort(n[np.isfinite(n)])
    if not n.size:
        raise ValueError("no finite engine speed to place a band on")
    while True:
        starts = np.arange(n[0] - width, n[-1] + 10.0, 10.0)
        shares = (np.searchsorted(n, starts + width) - np.searchsorted(n, starts)) / n.size
        if shares.max() >= share - 0.01 or width > n[-1] - n[0]:
            break
        width += 50.0
    n0 = float(starts[int(np.argmin(np.abs(shares - share)))])
    return (n0, n0 + width)


def run_spec(spec: dict, baseline, *, duration_s: float = 60.0) -> CaseResult:
    """Hide, analyse and judge one drawn case."""
    from fdi_ros.core.discrepancy import discover

    t0 = time.perf_counter()
    params = spec["params"]
    res, _ = discover(case_record(spec, duration_s=duration_s), baseline)
    top = res.findings[0] if res.findings else None
    tie = [a["effect"] for a in top.alternatives] if top else []
    tie_labels = [a["label"] for a in top.alternatives] if top else []
    tie_channels = [a.get("channel", top.channel) for a in top.alternatives] if top else []
    return CaseResult(index=spec["index"], effect=spec["effect"], channel=spec["channel"],
                      truth={k: (list(v) if isinstance(v, tuple) else v)
                             for k, v in params.items()},
                      found=top.effect if top else None,
                      found_channel=top.channel if top else None,
                      found_params=dict(top.params) if top else {}, tie=tie,
                      tie_labels=tie_labels, tie_channels=tie_channels,
                      seconds=time.perf_counter() - t0)


def own_channels(baseline) -> tuple[str, ...]:
    """The residuals an effect is hidden on: the baseline's channels but its checks (a
    check's signal is a sensor the main residuals read)."""
    return tuple(c for c in baseline.channels if c not in getattr(baseline, "checks", ()))


def run_case(index: int, rng: np.random.Generator, baseline, effect: str | None, *,
             duration_s: float = 60.0) -> CaseResult:
    """Draw, hide, analyse and judge one case."""
    spec = draw_spec(index, rng, own_channels(baseline), effect)
    return run_spec(spec, baseline, duration_s=duration_s)


def summarise(cases: list[CaseResult], *, param_tol: float = 0.3) -> dict:
    """Confusion matrix, channel accuracy, parameter errors, false discoveries, ties."""
    labels = list(EFFECTS) + ["none"]
    rows = {e: dict.fromkeys(labels, 0) for e in labels}
    for c in cases:
        rows[c.effect or "none"][c.found or "none"] += 1
    eff = [c for c in cases if c.effect is not None]
    nulls = [c for c in cases if c.effect is None]
    right = [c for c in eff if c.right]
    errs = [c.param_rel_error for c in right if c.param_rel_error is not None]
    within = [e for e in errs if e <= param_tol]
    ties = [c for c in eff if c.tied]
    chans = sorted({c.channel for c in eff})
    return {
        "n_cases": len(eff), "n_nulls": len(nulls),
        "confusion": {"labels": labels, "rows": rows},
        "top1_effect_and_channel": len(right) / len(eff) if eff else None,
        "top1_or_tie": (len(right) + len(ties)) / len(eff) if eff else None,
        "per_channel": {ch: {"cases": sum(c.channel == ch for c in eff),
                             "right": sum(c.right for c in eff if c.channel == ch),
                             "tied": sum(c.tied for c in eff if c.channel == ch)}
                        for ch in chans},
        "channel_accuracy": (sum(c.found_channel == c.channel for c in eff) / len(eff)
                             if eff else None),
        "parameter_rel_error": {"median": float(np.median(errs)) if errs else None,
                                "max": float(np.max(errs)) if errs else None,
                                "within_tolerance": len(within), "tolerance": param_tol,
                                "of": len(errs)},
        "false_discoveries": sum(c.found is not None for c in nulls),
        "ties_containing_truth": len(ties),
        "misses": [c.to_dict() for c in eff if not c.right],
    }


def run_selftest(n: int, seed: int, *, n_null: int | None = None, baseline=None,
                 progress=None, duration_s: float = 60.0,
                 only: set[int] | None = None) -> dict:
    """``n`` random effect cases plus ``n_null`` null cases (default ``max(1, n // 6)``);
    ``only``: run just these case indices of the same draw (a replay)."""
    if n < 0:
        raise ValueError("n must be >= 0")
    n_null = max(1, n // 6) if n_null is None else n_null
    if n_null < 0:
        raise ValueError("n_null must be >= 0")
    rng = np.random.default_rng(seed)
    if baseline is None:
        baseline = sc.diesel_baseline()
    kinds: list[str | None] = [str(rng.choice(EFFECTS)) for _ in range(n)] + [None] * n_null
    rng.shuffle(kinds)
    cases = []
    for i, kind in enumerate(kinds):
        spec = draw_spec(i, rng, own_channels(baseline), kind)
        if only is not None and i not in only:
            continue
        c = run_spec(spec, baseline, duration_s=duration_s)
        cases.append(c)
        if progress:
            progress(f"case {i + 1}/{len(kinds)}: hidden {c.effect or 'nothing'} on "
                     f"{c.channel} -> found {c.found or 'nothing'}"
                     f"{' on ' + c.found_channel if c.found_channel else ''} "
                     f"({c.seconds:.1f} s)")
    out = summarise(cases)
    out.update(seed=seed, cases=[c.to_dict() for c in cases],
               ranges={ch: {k: {"param": v[0], "lo": v[1], "hi": v[2]}
                            for k, v in ranges(ch).items()}
                       for ch in ("maf", *SENSOR_DETECTABLE)},
               duration_s=duration_s)
    return out
