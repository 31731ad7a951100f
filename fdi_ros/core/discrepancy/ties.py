"""Honest ties between a gain on the model's channel and a gain on one of its input sensors.

A model with one residual per channel cannot always say which sensor is wrong: in a
speed-density model the predicted air flow is nearly proportional to the manifold pressure, so
a reading of the pressure sensor scaled by k looks like the flow sensor scaled by about 1/k.
For a gain-error finding on channel c, every input sensor s of the model is re-scaled (after
the finding's onset) by the factor k that fits the data best (reported as the sensor's gain
1/k), the model is re-run, and the two
explanations are compared on contiguous 5 s blocks after the onset (two-sided Wilcoxon
signed-rank test on the blockwise MSE differences). When they cannot be told apart, the input
gain is reported as a tie, with its fitted factor, why the data cannot separate them and
which measurement would.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from scipy import stats
from scipy.optimize import minimize_scalar

from fdi_ros.core.measured import Measured


def _scaled(data: Measured, name: str, k: float, after: np.ndarray) -> Measured:
    sig = dict(data.signals)
    sig[name] = np.where(after, data[name] * k, data[name])
    return Measured(t=data.t, signals=sig, units=dict(data.units), alpha=data.alpha,
                    segment=data.segment, source=data.source, mapped=data.mapped)


def _windows(data: Measured, max_samples: int, n_windows: int = 12) -> Measured:
    """At most ``max_samples`` samples in ``n_windows`` contiguous windows spread over the
    record (each window keeps its crank-angle and time structure; windows are segments)."""
    n = data.n_samples
    if n <= max_samples:
        return data
    w = max_samples // n_windows
    starts = np.linspace(0, n - w, n_windows).astype(int)
    keep = np.zeros(n, bool)
    win = np.zeros(n, int)
    for i, a in enumerate(starts):
        keep[a:a + w] = True
        win[a:a + w] = i
    seg = np.asarray(data.segment)[keep]
    wk = win[keep]
    change = np.concatenate([[0], (np.diff(seg) != 0) | (np.diff(wk) != 0)])
    return Measured(t=data.t[keep], signals={k: np.asarray(v)[keep] for k, v in
                                             data.signals.items()},
                    units=dict(data.units),
                    alpha=None if data.alpha is None else data.alpha[keep],
                    segment=np.cumsum(change).astype(int), source=data.source,
                    mapped=data.mapped)


def _block_mse(e2: np.ndarray, t: np.ndarray, block_s: float) -> np.ndarray:
    ok = np.isfinite(e2)
    if not ok.any():
        return np.zeros(0)
    b = ((t - t[ok][0]) // block_s).astype(int)
    nb = int(b[ok].max()) + 1
    s = np.bincount(b[ok], weights=e2[ok], minlength=nb)
    c = np.bincount(b[ok], minlength=nb)
    return (s / np.maximum(c, 1))[c >= 10]


def input_gain_ties(data: Measured, model: Any, channel: str, gain: float, onset_s: float | None,
                    *, alpha: float = 0.05, block_s: float = 5.0,
                    bounds: tuple[float, float] = (0.6, 1.6),
                    max_samples: int = 40_000) -> list[dict[str, Any]]:
    """Input-sensor gains that explain the data as well as ``gain`` on ``channel``.

    Long records are judged on ``max_samples`` samples in contiguous windows spread over
    the record (each refit re-runs the model). An input gain is kept unless it explains the
    data significantly worse (one-sided test); when it explains them significantly better,
    ``fits_better`` says so (the channel gain stays the finding: it is the extension of the
    channel's prediction).
    Returns one dict per tied input: effect, label, channel, params (gain, onset_s),
    ``p_distinguish`` (two-sided test that the two explanations differ), ``fits_better``,
    ``why`` and ``separate_by``.
    """
    data = _windows(data, max_samples)
    t = data.t
    after = np.ones(t.shape, bool) if onset_s is None else t >= onset_s
    y = np.asarray(data[channel], float)
    yhat = np.asarray(model.predict(data)[channel], float)
    e_ch = y - np.where(after, yhat * gain, yhat)
    out = []
    for name in dict.fromkeys(model.inputs):
        if name == channel or name not in data.signals:
            continue
        x = np.asarray(data[name], float)
        if not np.isfinite(x).any() or np.nanstd(x[after]) == 0:
            continue

        def resid(k: float, name: str = name) -> np.ndarray:
            e: np.ndarray = y - np.asarray(model.predict(_scaled(data, name, k, after))[channel],
                                           float)
            return e

        def cost(k: float, resid: Callable[[float], np.ndarray] = resid) -> float:
            e = resid(k)[after]
            e = e[np.isfinite(e)]
            # samples the scaled input pushes outside the model's region count as misses
            return float(np.mean(e ** 2)) * (after.sum() / max(e.size, 1)) if e.size else np.inf

        try:
            res = minimize_scalar(cost, bounds=bounds, method="bounded",
                                  options={"xatol": 1e-4})
        except (ValueError, FloatingPointError):
            continue
        k = float(res.x)
        if not np.isfinite(res.fun) or abs(k - 1.0) < 0.01 or min(k - bounds[0],
                                                                  bounds[1] - k) < 1e-3:
            continue
        e_in = resid(k)
        both = after & np.isfinite(e_in) & np.isfinite(e_ch)
        if both.sum() < 0.9 * after.sum():
            continue
        m_ch = _block_mse(np.where(both, e_ch ** 2, np.nan), t, block_s)
        m_in = _block_mse(np.where(both, e_in ** 2, np.nan), t, block_s)
        if m_ch.size < 4:
            continue
        d = m_in - m_ch
        if np.all(d == 0):
            p, p_worse = 1.0, 1.0
        else:
            p = float(stats.wilcoxon(d).pvalue)
            p_worse = float(stats.wilcoxon(d, alternative="greater").pvalue)
        if p_worse < alpha:
            continue  # the input gain explains the data significantly worse: no tie
        r_ch = float(np.sqrt(np.mean(e_ch[both] ** 2)))
        r_in = float(np.sqrt(np.mean(e_in[both] ** 2)))
        better = p < alpha and float(np.median(d)) < 0
        out.append({
            "effect": "gain_error", "label": f"gain error on {name}", "channel": name,
            # the sensor's own gain (its reading / the truth): the model is fed reading / gain
            "params": {"gain": 1.0 / k, "onset_s": onset_s},
            "rmse_after_onset": {channel: r_ch, name: r_in},
            "p_distinguish": p,
            "fits_better": better,
            "gain_pct": float("nan"),
            "why": (f"the model predicts {channel} from {name}; scaling {name} by {k:.3f} "
                    f"(a {name} sensor gain of {1.0 / k:.3f}) "
                    f"moves the prediction as a gain {gain:.3f} on {channel} moves the "
                    f"measurement (RMSE after the onset {r_in:.4g} vs {r_ch:.4g}, blockwise "
                    f"test p = {p:.2g}"
                    + (f"; the {name} gain fits significantly better: the more likely cause"
                       if better else "") +
                    "): one residual per channel cannot prove which sensor is wrong"),
            "separate_by": (f"a second relation that uses {name} but not {channel}, or "
                            f"{channel} but not {name} (e.g. a redundant {name} sensor, or a "
                            f"flow relation across another component that uses {name})"),
        })
    return out


def tie_reason(choice: Any, other: Any, model_channel: str,
               basis: str = "held-out error within one standard error") -> dict[str, str]:
    """Why two candidates (``choice``, ``other``: objects with ``effect``, ``label``,
    ``channel`` and optionally ``residuals``, the residuals each moves) explain the data
    alike (``basis``: the criterion that tied them), and which measurement would tell them
    apart."""
    a, b = choice.channel, other.channel
    lag_pair = {choice.effect, other.effect} == {"sensor_lag", "dead_time"}
    ra = set(getattr(choice, "residuals", ()) or (model_channel,))
    rb = set(getattr(other, "residuals", ()) or (model_channel,))
    if a != b:
        if ra == rb:
            shown = " and ".join(sorted(ra))
            why = (f"{other.label} ({b}) moves the {shown} residual{'s' if len(ra) > 1 else ''}"
                   f" as {choice.label} ({a}) does: every relation here reads both signals "
                   "or neither, so the residuals cannot prove which signal is wrong "
                   f"({basis})")
            sep = (f"a relation that reads {a} but not {b}, or {b} but not {a} (a redundant "
                   f"sensor, or a model of another component that reads one of them)")
        else:
            only = sorted(ra ^ rb)
            why = (f"{other.label} ({b}) moves the residuals {sorted(rb)}, {choice.label} "
                   f"({a}) moves {sorted(ra)}; where only one of them acts ({only}) the two "
                   f"are not told apart on these data ({basis})")
            sep = (f"operating points where the {' and '.join(only)} relation responds "
                   f"more strongly to {a} or {b}, or a relation that reads {a} but not {b}, "
                   f"or {b} but not {a}")
    elif {choice.effect, other.effect} == {"gain_error", "offset"}:
        why = (f"on {a} a gain and an offset differ by (gain - 1) times the reading's "
               "departure from its mean: over the narrow range the reading covered here the "
               f"two fit alike ({basis})")
        sep = (f"readings of {a} over a wider range (a gain error grows with the reading, an "
               "offset does not)")
    elif lag_pair:
        why = (f"on {a} a first-order lag tau and a dead time d = tau both make a slowly "
               "varying reading trail the truth by about tau dx/dt; they differ only in "
               "faster content")
        sep = (f"the crank-angle pulsation of {a} (a lag damps it, a dead time shifts its "
               "phase in proportion to speed) or steeper transients")
    else:
        why = f"{other.label} and {choice.label} fit the held-out blocks alike ({basis})"
        sep = ("data that excite the two differently: a wider operating range, other "
               "transients, or a measured column that follows one of them")
    return {"why": why, "separate_by": sep}
