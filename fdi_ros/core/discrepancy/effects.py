"""The catalogue of model deficiencies: each effect is a parametric model extension.

An effect maps the current prediction ``base`` of one channel to an extended prediction
``apply(ctx, base, params)``; ``fit(ctx, base, train)`` identifies its parameters on the
training samples only (boolean mask), so that it can be evaluated on held-out blocks.

=====================  ===================================================  ===============
id                     extension (y: measured, yhat: model)                 parameters
=====================  ===================================================  ===============
``offset``             y = yhat + b [* 1(t >= t_on)]                        offset, onset_s
``gain_error``         y = yhat * (g [if t >= t_on]; 1 before)              gain, onset_s
``drift``              y = yhat + rate * (t - t_ref)                        rate_per_s
``sensor_lag``         y = first-order lag of yhat, tau dy/dt + y = yhat    tau_s
``dead_time``          y(t) = yhat(t - d)                                   delay_s
``input_dependence``   y = yhat + c1 z + c2 (z^2 - 1), z = (x - m) / s     input, coef
``local_region``       y = yhat + b inside a box of the model's inputs     region, offset
``leak``               y = yhat - CdA q(p_amb -> p) [* 1(t >= t_on)]        area_mm2, ...
``missing_harmonic``   y = yhat + A cos(2 pi k alpha / 180 deg + phi)       order, amplitude
=====================  ===================================================  ===============

``order`` k counts multiples of the 180 deg CA fundamental of a four-cylinder engine (k = 0.5 is
one event per revolution). The leak flux q is the isentropic orifice flow per unit area
(:func:`fdi_ros.core.discrepancy.context.orifice_flux`); CdA is constrained to be >= 0.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.signal import lfilter

from fdi_ros.core.discrepancy.context import ChannelContext, smooth_derivative
from fdi_ros.core.discrepancy.timing import estimate_delay

CATALOGUE = ("input_dependence", "missing_harmonic", "sensor_lag", "dead_time", "gain_error",
             "offset", "drift", "leak", "local_region")


def _ffill(x: np.ndarray) -> np.ndarray:
    """Forward-fill NaN (then back-fill the head) so recursive filters can run through."""
    ok = np.isfinite(x)
    if ok.all():
        return x
    if not ok.any():
        return np.zeros_like(x)
    idx = np.where(ok, np.arange(x.size), 0)
    np.maximum.accumulate(idx, out=idx)
    y = x[idx]
    y[: int(np.argmax(ok))] = x[int(np.argmax(ok))]
    return y


def segment_slices(segment: np.ndarray) -> list[slice]:
    """Contiguous runs of equal segment id (segments are contiguous in time)."""
    cuts = np.flatnonzero(np.diff(segment)) + 1
    edges = np.concatenate([[0], cuts, [segment.size]])
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def _lowpass_varying(x: np.ndarray, t: np.ndarray, tau_s: float, y0: float) -> np.ndarray:
    """Exact ZOH first-order lag for non-uniform sample times.

    ``y_k = a_k y_{k-1} + (1 - a_k) x_k`` with ``a_k = exp(-(t_k - t_{k-1}) / tau)``; the
    product of the a's is ``exp(-(t_k - t_c) / tau)``, so within a chunk the recursion is a
    weighted cumulative sum; chunks of at most 200 tau keep the exponentials finite.
    """
    y = np.empty_like(x)
    a = np.exp(-np.diff(t, prepend=t[0]) / tau_s)
    start, state = 0, y0
    n = x.size
    while start < n:
        stop = int(np.searchsorted(t, t[start] + 200.0 * tau_s, side="right"))
        stop = min(max(stop, start + 1), n)
        tc = t[start]
        g = np.exp((t[start:stop] - tc) / tau_s)
        acc = np.cumsum((1.0 - a[start:stop]) * x[start:stop] * g)
        y[start:stop] = (state * a[start] + acc) / g
        state = y[stop - 1]
        start = stop
    return y


def lowpass(x: np.ndarray, t: np.ndarray, segment: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order lag ``tau dy/dt + y = x`` per segment (zero-order-hold discretisation).

    Uniform sampling uses a recursive filter; crank-angle sampled data (time steps that vary
    with speed) the exact time-varying recursion.
    """
    out = np.empty_like(x, dtype=float)
    tau_s = max(tau_s, 1e-12)
    for idx in segment_slices(segment):
        xs = _ffill(x[idx])
        ts = t[idx]
        steps = np.diff(ts)
        if steps.size and steps.max() > 1.01 * steps.min():
            out[idx] = _lowpass_varying(xs, ts, tau_s, xs[0])
            continue
        dt = float(steps[0]) if steps.size else 1.0
        a = math.exp(-dt / tau_s)
        ys, _ = lfilter([1.0 - a], [1.0, -a], xs, zi=[a * xs[0]])
        out[idx] = ys
    out[~np.isfinite(x)] = np.nan
    return out


def delay(x: np.ndarray, t: np.ndarray, segment: np.ndarray, delay_s: float) -> np.ndarray:
    """``x(t - d)`` per segment by linear interpolation (held at the segment's first value)."""
    out = np.empty_like(x, dtype=float)
    for idx in segment_slices(segment):
        xs = _ffill(x[idx])
        out[idx] = np.interp(t[idx] - delay_s, t[idx], xs)
    out[~np.isfinite(x)] = np.nan
    return out


def _train_mask(ctx: ChannelContext, base: np.ndarray, train: np.ndarray,
                *extra: np.ndarray) -> np.ndarray:
    m = train & np.isfinite(ctx.y) & np.isfinite(base)
    for e in extra:
        m &= np.isfinite(e)
    return np.asarray(m, bool)


def _fit_scalar(r: np.ndarray, g: np.ndarray, t: np.ndarray, m: np.ndarray, *, onset: bool,
                nonneg: bool) -> tuple[float, float | None]:
    """Least-squares ``r ~ beta * g * 1(t >= t_on)``; ``t_on`` located when ``onset``.

    The onset is the change point of the ratio ``r / g`` (:func:`ratio_change_point`): the
    effect per unit of its regressor steps from 0 to beta at the onset whatever the operating
    point, where a squared-error fit of ``r`` would put the onset where the regressor is
    large. Beta is then the least-squares fit on the samples after the onset.
    Returns (beta, t_on or None).
    """
    t_on = ratio_change_point(r, g, t, m) if onset else None
    idx = np.flatnonzero(m if t_on is None else m & (t >= t_on))
    if idx.size < 3:
        return 0.0, None
    den = float(np.dot(g[idx], g[idx]))
    beta = float(np.dot(r[idx], g[idx])) / den if den > 0 else 0.0
    return (max(beta, 0.0) if nonneg else beta), t_on


def _fit_piecewise(r: np.ndarray, g: np.ndarray, t: np.ndarray, m: np.ndarray, *,
                   nonneg: bool, max_changes: int = 8, min_gain: float = 0.01
                   ) -> tuple[list[float], list[float]]:
    """Least-squares ``r ~ beta(t) * g`` with ``beta`` piecewise constant in time.

    Binary segmentation: split the segment whose best split lowers the training SSE most, as
    long as the decrease exceeds ``min_gain`` of the total sum of squares (the held-out test
    judges the result); at most ``max_changes`` change times. Returns (change times [s],
    beta per piece).
    """
    idx = np.flatnonzero(m)
    n = idx.size
    if n < 40:
        return [], [0.0]
    rg, gg = r[idx] * g[idx], g[idx] ** 2
    crg = np.concatenate([[0.0], np.cumsum(rg)])
    cgg = np.concatenate([[0.0], np.cumsum(gg)])
    total = float(np.dot(r[idx], r[idx])) or 1.0
    min_len = max(20, n // 100)

    def red(s_rg: np.ndarray, s_gg: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            v = np.where(s_gg > 0, s_rg ** 2 / s_gg, 0.0)
        return np.where(s_rg > 0, v, 0.0) if nonneg else v

    cuts = [0, n]
    for _ in range(max_changes):
        best: tuple[float, int | None] = (0.0, None)
        for a, b in zip(cuts[:-1], cuts[1:]):
            if b - a < 2 * min_len:
                continue
            k = np.arange(a + min_len, b - min_len + 1)
            gain = (red(crg[k] - crg[a], cgg[k] - cgg[a]) + red(crg[b] - crg[k], cgg[b] - cgg[k])
                    - red(crg[b] - crg[a], cgg[b] - cgg[a]))
            j = int(np.argmax(gain))
            if gain[j] > best[0]:
                best = (float(gain[j]), int(k[j]))
        if best[1] is None or best[0] < min_gain * total:
            break
        cuts = sorted(cuts + [best[1]])
    betas = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        s_gg = cgg[b] - cgg[a]
        beta = (crg[b] - crg[a]) / s_gg if s_gg > 0 else 0.0
        betas.append(max(beta, 0.0) if nonneg else float(beta))
    return [float(t[idx[c]]) for c in cuts[1:-1]], betas


def ratio_change_point(r: np.ndarray, g: np.ndarray, t: np.ndarray, m: np.ndarray
                       ) -> float | None:
    """Onset of an effect ``r = beta g`` that switches on: the mean-shift change point of the
    ratio ``r / g``.

    The ratio steps from its level before (0 for a fault-free model) to ``beta`` at the onset
    whatever the regressor's size: for a gain (``g`` the prediction) it is the relative
    residual ``y / yhat - 1``, which steps at idle as well, where the absolute residual of a
    10 % gain is smaller than the model's own error; a squared-error fit of ``r`` would put
    the onset where the load returns. Samples with ``|g|`` below 5 % of its median magnitude
    are left out (the ratio is noise there); each sample's ratio is clipped to the 1-99 %
    quantiles so a few outliers cannot place the change. The split maximises the CUSUM
    statistic ``n / (k (n - k)) (sum of the first k demeaned ratios)^2`` (at least 2 % of
    the samples, and 20, on each side). Returns None when there is no split.
    """
    scale = float(np.median(np.abs(g[m]))) if m.any() else 0.0
    mm = m & np.isfinite(r) & (np.abs(g) > 0.05 * scale)
    if mm.sum() < 40 or scale == 0.0:
        return None
    idx = np.flatnonzero(mm)
    rr = r[idx] / g[idx]
    lo, hi = np.quantile(rr, [0.01, 0.99])
    x = np.clip(rr, lo, hi)
    x = x - x.mean()
    n = idx.size
    k = np.arange(1, n)
    c = np.cumsum(x)[:-1]
    stat = c ** 2 * n / (k * (n - k))
    lo_k = max(20, n // 50)
    stat[: lo_k - 1] = 0.0
    stat[n - lo_k:] = 0.0
    j = int(np.argmax(stat))
    return float(t[idx[j + 1]]) if stat[j] > 0 else None


def _relative_change_point(y: np.ndarray, base: np.ndarray, t: np.ndarray, m: np.ndarray
                           ) -> float | None:
    """Onset of a gain change: :func:`ratio_change_point` of the relative residual."""
    return ratio_change_point(y - base, base, t, m)


def _piecewise_beta(t: np.ndarray, params: dict[str, Any]) -> np.ndarray:
    return np.asarray(params["values"])[np.searchsorted(params["changes_s"], t, side="right")]


def _label(name: str, eff: object) -> str:
    if getattr(eff, "piecewise", False):
        return f"{name} (piecewise in time)"
    return f"{name} after onset" if getattr(eff, "onset", False) else name


def _step(t: np.ndarray, onset: float | None) -> np.ndarray:
    return np.ones_like(t) if onset is None else (t >= onset).astype(float)


@dataclass(frozen=True)
class Effect:
    """Base of the catalogue effects (one candidate extension of one channel)."""

    id = ""

    @property
    def label(self) -> str:
        return self.id

    @property
    def n_params(self) -> int:
        return 1

    def fit(self, ctx: ChannelContext, base: np.ndarray, train: np.ndarray, *,
            refine: bool = False) -> dict[str, Any]:
        """Parameters fitted on the ``train`` samples; ``refine``: final (polished) fit."""
        raise NotImplementedError

    def apply(self, ctx: ChannelContext, base: np.ndarray, params: dict[str, Any]) -> np.ndarray:
        raise NotImplementedError

    def to_dict(self) -> dict[str, Any]:
        d = {"effect": self.id}
        d.update({k: getattr(self, k) for k in self.__dataclass_fields__})
        return d


@dataclass(frozen=True)
class _StepError(Effect):
    """An additive or multiplicative error, constant, from an onset on, or piecewise constant
    (``name``: label, ``key``: its parameter; subclasses say how it enters the model)."""

    onset: bool = False
    piecewise: bool = False
    name = ""
    key = ""

    @property
    def label(self) -> str:
        return _label(self.name, self)

    @property
    def n_params(self) -> int:
        return 4 if self.piecewise else 2 if self.onset else 1

    def _regressor(self, base: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _value(self, b: float) -> float:
        """The parameter of a fitted coefficient ``b``."""
        return b

    def _with(self, base: np.ndarray, delta: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def fit(self, ctx: ChannelContext, base: np.ndarray, train: np.ndarray, *,
            refine: bool = False) -> dict[str, Any]:
        m = _train_mask(ctx, base, train)
        if self.piecewise:
            ch, vals = _fit_piecewise(ctx.y - base, self._regressor(base), ctx.t, m,
                                      nonneg=False)
            k = int(np.argmax(np.abs(vals)))
            return {self.key: self._value(vals[k]), "changes_s": ch, "values": vals}
        b, t_on = _fit_scalar(ctx.y - base, self._regressor(base), ctx.t, m, onset=self.onset,
                              nonneg=False)
        return {self.key: self._value(b), "onset_s": t_on}

    def apply(self, ctx: ChannelContext, base: np.ndarray, params: dict[str, Any]
              ) -> np.ndarray:
        if "changes_s" in params:
            return self._with(base, _piecewise_beta(ctx.t, params))
        return self._with(base, (params[self.key] - self._value(0.0))
                          * _step(ctx.t, params.get("onset_s")))


@dataclass(frozen=True)
class Offset(_StepError):
    id = "offset"
    name = "offset"
    key = "offset"

    def _regressor(self, base: np.ndarray) -> np.ndarray:
        return np.ones_like(base)

    def _with(self, base: np.ndarray, delta: np.ndarray) -> np.ndarray:
        return np.asarray(base + delta, float)


@dataclass(frozen=True)
class GainError(_StepError):
    """A gain of the channel: the prediction times (1 + b)."""

    id = "gain_error"
    name = "gain error"
    key = "gain"

    def _value(self, b: float) -> float:
        return 1.0 + b

    def _regressor(self, base: np.ndarray) -> np.ndarray:
        return base

    def _with(self, base: np.ndarray, delta: np.ndarray) -> np.ndarray:
        return base * (1.0 + delta)

    def fit(self, ctx: ChannelContext, base: np.ndarray, train: np.ndarray, *,
            refine: bool = False) -> dict[str, Any]:
        if not self.onset or self.piecewise:
            return super().fit(ctx, base, train, refine=refine)
        # A sensor gain from an onset on: the onset is the change point of the relative
        # residual y / yhat - 1 (seen even at low load, where the absolute residual is small).
        m = _train_mask(ctx, base, train)
        t_on = _relative_change_point(ctx.y, base, ctx.t, m)
        after = m & (ctx.t >= t_on) if t_on is not None else m
        b, _ = _fit_scalar(ctx.y - base, base, ctx.t, after, onset=False, nonneg=False)
        return {"gain": 1.0 + b, "onset_s": t_on}


@dataclass(frozen=True)
class Drift(Effect):
    id = "drift"

    def fit(self, ctx: ChannelContext, base: np.ndarray, train: np.ndarray, *,
            refine: bool = False) -> dict[str, Any]:
        m = _train_mask(ctx, base, train)
        rate, _ = _fit_scalar(ctx.y - base, ctx.t - ctx.t_ref, ctx.t, m, onset=False,
                              nonneg=False)
        return {"rate_per_s": rate, "t_ref_s": ctx.t_ref}

    def apply(self, ctx: ChannelContext, base: np.ndarray, params: dict[str, Any]
              ) -> np.ndarray:
        return np.asarray(base + params["rate_per_s"] * (ctx.t - params["t_ref_s"]), float)


def _fit_1d(ctx: ChannelContext, base: np.ndarray, train: np.ndarray,
            transform: Callable[[float], np.ndarray], lo: float,
            hi: float, *, log: bool, key: str, refine: bool, n_grid: int = 40
            ) -> float:
    """Minimise the training SSE of ``transform(value)`` over [lo, hi].

    The grid is evaluated once per base prediction for all folds together: the engine puts the
    index intervals each fold leaves out on the context (``ctx.folds``), and a fold's training SSE
    is the total minus those intervals, from one cumulative sum per grid value. The minimum is
    located by a parabola through the best grid point and its neighbours (in log space for
    ``log``); ``refine`` polishes it with Brent's method (the final fit on all samples).
    """
    grid = np.geomspace(lo, hi, n_grid) if log else np.linspace(lo, hi, n_grid)
    valid = np.isfinite(ctx.y) & np.isfinite(base)
    folds = ctx.folds
    k_fold = ctx.fold_ids.get(id(train)) if folds is not None else None

    def sq_err(v: float) -> np.ndarray:
        e = ctx.y - transform(v)
        ok = valid & np.isfinite(e)
        return np.where(ok, e, 0.0) ** 2

    if k_fold is not None:
        cache = ctx.cache.get(key)
        if cache is None or cache["base"] is not base:  # one base per effect
            # every fold trains on the valid samples minus a few index intervals: its SSE is
            # the total minus those intervals' sums, read off one cumulative sum
            assert folds is not None
            i0, i1, owner = folds
            okv = ctx.ok & valid
            table = np.empty((n_grid, int(owner.max()) + 1))
            for g, v in enumerate(grid):
                cs = np.concatenate([[0.0], np.cumsum(np.where(okv, sq_err(float(v)), 0.0))])
                table[g] = cs[-1] - np.bincount(owner, weights=cs[i1] - cs[i0],
                                                minlength=table.shape[1])
            cache = ctx.cache[key] = {"base": base, "table": table}
        costs = cache["table"][:, k_fold]
    else:
        m = train & valid
        costs = np.array([float(sq_err(float(v))[m].sum()) for v in grid])

    def sse(v: float) -> float:
        return float(sq_err(v)[train & valid].sum())

    k = int(np.argmin(costs))
    best = float(grid[k])
    if 0 < k < n_grid - 1:
        x = np.log(grid[k - 1:k + 2]) if log else grid[k - 1:k + 2]
        c2, c1, _ = np.polyfit(x - x[1], costs[k - 1:k + 2], 2)
        if c2 > 0:
            xv = float(np.clip(-c1 / (2 * c2), x[0] - x[1], x[2] - x[1])) + x[1]
            best = float(np.exp(xv)) if log else xv
    if refine:
        a, b = grid[max(k - 1, 0)], grid[min(k + 1, n_grid - 1)]
        if b > a:
            res = minimize_scalar(lambda v: sse(float(v)), bounds=(a, b), method="bounded",
                                  options={"xatol": (b - a) * 1e-4})
            if res.fun <= sse(best):
                best = float(res.x)
    return best


def _upper(ctx: ChannelContext, cap: float, fraction: int | float, floor: float) -> float:
    """Upper end of a time-constant search: ``cap``, at most the record length / ``fraction``,
    at least ``floor``."""
    return float(max(min(cap, (ctx.t[-1] - ctx.t[0]) / fraction), floor))


@dataclass(frozen=True)
class _Filter(Effect):
    """A one-parameter transformation of the prediction (its parameter ``key``), fitted by a
    grid search with parabolic refinement (:func:`_fit_1d`)."""

    key = ""

    def _grid(self, ctx: ChannelContext) -> tuple[float, float, bool, int]:
        """(lowest, highest value, logarithmic grid?, grid points)."""
        raise NotImplementedError

    def _transform(self, ctx: ChannelContext, base: np.ndarray, v: float) -> np.ndarray:
        raise NotImplementedError

    def fit(self, ctx: ChannelContext, base: np.ndarray, train: np.ndarray, *,
            refine: bool = False) -> dict[str, Any]:
        lo, hi, log, n_grid = self._grid(ctx)
        v = _fit_1d(ctx, base, train, lambda x: self._transform(ctx, base, x), lo, hi,
                    log=log, key=self.label, refine=refine, n_grid=n_grid)
        return {self.key: v}

    def apply(self, ctx: ChannelContext, base: np.ndarray, params: dict[str, Any]
              ) -> np.ndarray:
        return self._transform(ctx, base, float(params[self.key]))


@dataclass(frozen=True)
class SensorLag(_Filter):
    id = "sensor_lag"
    key = "tau_s"
    max_tau_s: float = 5.0

    def _grid(self, ctx: ChannelContext) -> tuple[float, float, bool, int]:
        return 0.2 * ctx.dt, _upper(ctx, self.max_tau_s, 10.0, ctx.dt), True, 40

    def _transform(self, ctx: ChannelContext, base: np.ndarray, v: float) -> np.ndarray:
        return lowpass(base, ctx.t, ctx.segment, v)


@dataclass(frozen=True)
class DeadTime(_Filter):
    id = "dead_time"
    key = "delay_s"
    max_delay_s: float = 0.5

    def _transform(self, ctx: ChannelContext, base: np.ndarray, v: float) -> np.ndarray:
        return delay(base, ctx.t, ctx.segment, v)

    def _grid(self, ctx: ChannelContext) -> tuple[float, float, bool, int]:
        hi = _upper(ctx, self.max_delay_s, 20.0, 2 * ctx.dt)
        # one grid point per sample step: with a pulsating signal the error is multimodal in
        # the delay (period of the pulsation), a coarse grid misses
        return 0.0, hi, False, int(min(600, max(12, hi / ctx.dt + 1)))

    def fit(self, ctx: ChannelContext, base: np.ndarray, train: np.ndarray, *,
            refine: bool = False) -> dict[str, Any]:
        """The delay of the measurement behind the prediction from the two signals
        (:func:`~fdi_ros.core.discrepancy.timing.estimate_delay`: cross-correlation, then the
        cross-spectrum phase for the fraction of a sample), on the training samples only
        (each contiguous run of them on its own); a grid search of the training error when
        the two are not clearly correlated."""
        _, hi, _, _ = self._grid(ctx)
        m = _train_mask(ctx, base, train)
        cut = np.r_[False, (np.diff(m.astype(int)) != 0) | (np.diff(ctx.segment) != 0)]
        est = estimate_delay(np.where(m, ctx.y, np.nan), np.where(m, base, np.nan), ctx.t,
                             segment=np.cumsum(cut), max_delay_s=hi)
        if est.success and est.peak_corr >= 0.5:
            return {self.key: float(np.clip(est.delay_s, 0.0, hi))}
        return super().fit(ctx, base, train, refine=refine)


@dataclass(frozen=True)
class InputDependence(Effect):
    """The residual varies with a measured column x: ``c1 z + c2 (z^2 - <z^2>)``.

    ``z = (x - mean) / std`` over the training samples, and the quadratic term is centred too,
    so the correction has zero training mean: a constant part is left to ``offset`` and the
    name says what varies with what.
    """

    column: str = ""
    degree: int = 2
    id = "input_dependence"

    @property
    def label(self) -> str:
        return f"input_dependence on {self.column}"

    @property
    def n_params(self) -> int:
        return self.degree

    def _basis(self, x: np.ndarray, center: float, scale: float, sq_mean: float,
               z_range: Any = None) -> np.ndarray:
        z = (x - center) / scale
        if z_range is not None:
            # no extrapolation beyond one span of the fitted z on either side: a column that
            # barely moved while fitted (the derivative of an ambient pressure) can jump
            # elsewhere, and its square would then predict nonsense (1e20)
            lo, hi = float(z_range[0]), float(z_range[1])
            span = hi - lo
            z = np.clip(z, lo - span, hi + span)
        cols = [z] + ([z ** 2 - sq_mean] if self.degree >= 2 else [])
        return np.stack(cols, axis=1)

    def fit(self, ctx: ChannelContext, base: np.ndarray, train: np.ndarray, *,
            refine: bool = False) -> dict[str, Any]:
        x = ctx.columns[self.column]
        m = _train_mask(ctx, base, train, x)
        if m.sum() < 10 * self.degree:
            return {"input": self.column, "center": 0.0, "scale": 1.0, "sq_mean": 0.0,
                    "coef": [0.0] * self.degree}
        center = float(np.mean(x[m]))
        scale = float(np.std(x[m])) or 1.0
        A = self._basis(x[m], center, scale, 1.0)
        coef, *_ = np.linalg.lstsq(A, ctx.y[m] - base[m], rcond=None)
        z = (x[m] - center) / scale
        return {"input": self.column, "center": center, "scale": scale, "sq_mean": 1.0,
                "coef": [float(c) for c in coef],
                "z_range": [float(np.min(z)), float(np.max(z))]}

    def apply(self, ctx: ChannelContext, base: np.ndarray, params: dict[str, Any]
              ) -> np.ndarray:
        x = ctx.columns[params["input"]]
        corr = self._basis(x, params["center"], params["scale"], params["sq_mean"],
                           params.get("z_range")) @ np.asarray(params["coef"])
        # where the explaining column is missing, the extension falls back to the model
        return base + np.where(np.isfinite(corr), corr, 0.0)


@dataclass(frozen=True)
class Leak(Effect):
    onset: bool = False
    piecewise: bool = False
    id = "leak"

    @property
    def label(self) -> str:
        return _label("leak", self)

    @property
    def n_params(self) -> int:
        return 4 if self.piecewise else 2 if self.onset else 1

    def fit(self, ctx: ChannelContext, base: np.ndarray, train: np.ndarray, *,
            refine: bool = False) -> dict[str, Any]:
        q, spec = ctx.leak_q, ctx.leak
        if q is None or spec is None:
            raise ValueError(f"no leak regressor for {ctx.channel}")
        m = _train_mask(ctx, base, train, q)
        cd = spec.cd
        if self.piecewise:
            ch, vals = _fit_piecewise(ctx.y - base, -q, ctx.t, m, nonneg=True)
            cda = max(vals)
            areas = [v / cd * 1e6 for v in vals]
            return {"cda_mm2": cda * 1e6, "area_mm2": cda / cd * 1e6, "cd": cd,
                    "diameter_mm": math.sqrt(4.0 * cda / cd * 1e6 / math.pi),
                    "changes_s": ch, "values": vals,
                    "diameters_mm": [math.sqrt(4.0 * a / math.pi) for a in areas]}
        cda, t_on = _fit_scalar(ctx.y - base, -q, ctx.t, m, onset=self.onset, nonneg=True)
        area = cda / cd * 1e6
        return {"cda_mm2": cda * 1e6, "area_mm2": area, "cd": cd,
                "diameter_mm": math.sqrt(4.0 * area / math.pi), "onset_s": t_on}

    def apply(self, ctx: ChannelContext, base: np.ndarray, params: dict[str, Any]
              ) -> np.ndarray:
        if "changes_s" in params:
            corr = _piecewise_beta(ctx.t, params) * ctx.leak_q
        else:
            corr = params["cda_mm2"] * 1e-6 * ctx.leak_q * _step(ctx.t, params.get("onset_s"))
        return base - np.where(np.isfinite(corr), corr, 0.0)


@dataclass(frozen=True)
class MissingHarmonic(Effect):
    orders: tuple[float, ...] = tuple(np.arange(0.5, 8.01, 0.5))
    id = "missing_harmonic"

    @property
    def n_params(self) -> int:
        return 3

    @staticmethod
    def _basis(alpha: np.ndarray, order: float) -> np.ndarray:
        th = 2.0 * np.pi * order * alpha / 180.0
        return np.stack([np.cos(th), np.sin(th)], axis=1)

    def fit(self, ctx: ChannelContext, base: np.ndarray, train: np.ndarray, *,
            refine: bool = False) -> dict[str, Any]:
        if ctx.alpha is None:
            raise ValueError("a missing harmonic needs the crank angle")
        m = _train_mask(ctx, base, train, ctx.alpha)
        key = ("harmonic basis", self.orders)
        if key not in ctx.cache:  # the basis does not depend on the fold: build it once
            alpha = np.where(np.isfinite(ctx.alpha), ctx.alpha, 0.0)
            th = 2.0 * np.pi * np.outer(self.orders, alpha) / 180.0
            C, S = np.cos(th), np.sin(th)
            ctx.cache[key] = (C, S, C * C, S * S, C * S)
        C, S, CC, SS, CS = ctx.cache[key]
        w = m.astype(float)
        r = np.where(m, ctx.y - base, 0.0)
        # per order the 2x2 normal equations of r ~ a cos + b sin on the training samples
        gc, gs = C @ r, S @ r
        acc, ass, acs = CC @ w, SS @ w, CS @ w
        det = acc * ass - acs * acs
        ok = det > 1e-12 * np.maximum(acc * ass, 1e-300)
        av = np.where(ok, (ass * gc - acs * gs) / np.where(ok, det, 1.0), 0.0)
        bv = np.where(ok, (acc * gs - acs * gc) / np.where(ok, det, 1.0), 0.0)
        reduction = av * gc + bv * gs  # SSE decrease of the least-squares fit
        k = int(np.argmax(reduction))
        a, b = float(av[k]), float(bv[k])
        return {"order": float(self.orders[k]), "amplitude": float(math.hypot(a, b)),
                "phase_deg": float(math.degrees(math.atan2(-b, a))), "a": a, "b": b}

    def apply(self, ctx: ChannelContext, base: np.ndarray, params: dict[str, Any]
              ) -> np.ndarray:
        if ctx.alpha is None:
            return base.copy()
        A = self._basis(ctx.alpha, params["order"])
        return np.asarray(base + A @ np.array([params["a"], params["b"]]), float)


# sensor errors an input sensor can carry: direction of the error (ChannelContext.
# sensor_response), the parameter, and the parameter from the fitted coefficient beta of
# ``r ~ beta * D(direction)`` (the model must be fed the reading minus the error)
SENSOR_KINDS: dict[str, tuple[str, str, Any]] = {
    "offset": ("one", "offset", lambda b: -b),
    "gain_error": ("x", "gain", lambda b: 1.0 / (1.0 + b) if b > -1.0 else math.inf),
    "drift": ("t", "rate_per_s", lambda b: -b),
    "sensor_lag": ("shift", "tau_s", lambda b: b),  # fitted on a grid (see SensorError)
    "dead_time": ("shift", "delay_s", lambda b: b),
    "input_dependence": ("col", "coef", lambda b: -b),
}


@dataclass(frozen=True)
class SensorError(Effect):
    """An error of an input sensor of the model, seen through the model on this channel.

    A sensor reading ``x = x_true + e(t)`` feeds the model a wrong input; the channel's
    prediction is wrong by about ``D(e)`` (:meth:`ChannelContext.sensor_response`). The fit
    regresses the residual on ``D`` of the error's shape: an offset (constant), a gain
    (proportional to the reading), a drift (proportional to time) or a dependence on a
    measured column. A dead time is fitted as the advance of the reading that explains the
    residual best (:meth:`ChannelContext.sensor_shift_response`), a first-order lag as the
    reading plus tau times its slope (:meth:`ChannelContext.sensor_lag_response`); on a slowly
    varying reading the two are nearly alike (reported as a tie when the data cannot tell).
    ``onset``: offset and gain switch on at an unknown time (an abrupt fault).
    """

    sensor: str = ""
    kind: str = "offset"
    column: str = ""
    onset: bool = False
    piecewise = False  # (class constant) never piecewise in time: nests only by onset

    @property
    def id(self) -> str:  # type: ignore[override]
        return self.kind

    @property
    def label(self) -> str:
        name = {"gain_error": "gain error", "sensor_lag": "sensor lag",
                "dead_time": "dead time"}.get(self.kind, self.kind)
        if self.kind == "input_dependence":
            name = f"input_dependence on {self.column}"
        return f"{name} of {self.sensor}" + (" after onset" if self.onset else "")

    @property
    def n_params(self) -> int:
        return 2 if self.onset else 1

    def _direction(self) -> str:
        d = SENSOR_KINDS[self.kind][0]
        return f"col:{self.column}" if d == "col" else d

    max_delay_s: float = 5.0

    def _shifted(self, ctx: ChannelContext, base: np.ndarray, v: float) -> np.ndarray:
        corr = (ctx.sensor_lag_response(self.sensor, v) if self.kind == "sensor_lag"
                else ctx.sensor_shift_response(self.sensor, v))
        return base + np.where(np.isfinite(corr), corr, 0.0)

    def fit(self, ctx: ChannelContext, base: np.ndarray, train: np.ndarray, *,
            refine: bool = False) -> dict[str, Any]:
        _, key, value = SENSOR_KINDS[self.kind]
        if self.kind in ("sensor_lag", "dead_time"):
            hi = _upper(ctx, self.max_delay_s, 12.0, 2 * ctx.dt)
            v = _fit_1d(ctx, base, train, lambda d: self._shifted(ctx, base, d), 0.2 * ctx.dt,
                        hi, log=True, key=self.label, refine=refine, n_grid=36)
            return {key: float(v), "sensor": self.sensor}
        g = ctx.sensor_response(self.sensor, self._direction())
        m = _train_mask(ctx, base, train, g)
        if self.onset and self.kind == "gain_error":
            # as for a gain of the channel: the onset is the change point of the relative
            # residual (a gain of an input scales the prediction too), seen at low load as well
            t_on = _relative_change_point(ctx.y, base, ctx.t, m)
            after = m & (ctx.t >= t_on) if t_on is not None else m
            b, _ = _fit_scalar(ctx.y - base, g, ctx.t, after, onset=False, nonneg=False)
        else:
            b, t_on = _fit_scalar(ctx.y - base, g, ctx.t, m, onset=self.onset, nonneg=False)
        v = self._exact_size(ctx, base, m if t_on is None else m & (ctx.t >= t_on),
                             float(value(b)), t_on, g, 4 if refine else 2)
        b = 1.0 / v - 1.0 if self.kind == "gain_error" else -v
        out: dict[str, Any] = {key: v, "beta": float(b), "sensor": self.sensor}
        if self.onset:
            out["onset_s"] = t_on
        if self.kind == "drift":
            out["t_ref_s"] = ctx.t_ref
        if self.kind == "input_dependence":
            out["input"] = self.column
        return out

    def _exact_size(self, ctx: ChannelContext, base: np.ndarray, m: np.ndarray, v: float,
                    onset: float | None, slope: np.ndarray, iterations: int) -> float:
        """Newton steps from the linearised size ``v`` on the exact prediction (the model
        re-run with the reading corrected): a gain of 10 % of an input moves a curved map by
        more than its slope says. The first step uses the sensitivity at the reading
        (``slope`` per unit of the linear coefficient), the next ones the secant between the
        last two re-runs: one re-run per step."""
        if not np.isfinite(v) or (self.kind == "gain_error" and v <= 0):
            return v
        r = ctx.y - base
        st = _step(ctx.t, onset)
        last: tuple[float, np.ndarray] | None = None
        for _ in range(iterations):
            p0 = ctx.sensor_error_response(self.sensor, self.kind, v, onset, self.column,
                                           keep=False)
            if last is not None and last[0] != v:
                jac = (p0 - last[1]) / (v - last[0])  # secant: the slope between two re-runs
            else:
                # d(beta)/d(size): beta = 1/g - 1 for a gain, -size for the others
                dbeta = -1.0 / v ** 2 if self.kind == "gain_error" else -1.0
                jac = slope * st * dbeta
            last = (v, p0)
            ok = m & np.isfinite(jac) & np.isfinite(p0) & np.isfinite(r)
            den = float(np.dot(jac[ok], jac[ok]))
            if not ok.any() or den <= 0.0:
                break
            step = float(np.dot(jac[ok], (r - p0)[ok])) / den
            if self.kind == "gain_error":
                step = float(np.clip(step, -0.5 * v, 0.5 * v))
            v += step
            if abs(step) <= 1e-6 * max(abs(v), 1e-9):
                break
        return float(v)

    def apply(self, ctx: ChannelContext, base: np.ndarray, params: dict[str, Any]
              ) -> np.ndarray:
        key = SENSOR_KINDS[self.kind][1]
        if self.kind in ("sensor_lag", "dead_time"):
            return self._shifted(ctx, base, float(params[key]))
        corr = ctx.sensor_error_response(self.sensor, self.kind, float(params[key]),
                                         params.get("onset_s"), self.column)
        return base + np.where(np.isfinite(corr), corr, 0.0)

    def error(self, ctx: ChannelContext, params: dict[str, Any]) -> np.ndarray:
        """The fitted error of the sensor's reading (reading - truth) per sample, in the
        sensor's units."""
        x = ctx.sensor_reading(self.sensor)
        value = float(params[SENSOR_KINDS[self.kind][1]])
        if self.kind == "sensor_lag" and ctx.source is not None:
            data = ctx.source[0]
            return np.asarray(-value * smooth_derivative(x, data.t, data.segment,
                                                         max(value, 0.05)), float)
        if self.kind in ("sensor_lag", "dead_time"):
            return np.asarray(x - ctx.sensor_reading(self.sensor, value), float)
        g = ctx.sensor_response(self.sensor, self._direction())
        # the regressor is D(direction): the error is -beta times the direction itself
        d = {"one": np.ones_like(x), "x": x, "t": ctx.t - ctx.t_ref}.get(self._direction())
        if d is None:  # a measured column, standardised as in sensor_response
            col = np.asarray(ctx.source[0][self.column] if ctx.source is not None else g,
                             float)
            d = (col - np.nanmean(col)) / (np.nanstd(col) or 1.0)
        return np.asarray(-float(params["beta"]) * d * _step(ctx.t, params.get("onset_s")),
                          float)

    def to_dict(self) -> dict[str, Any]:
        return {"effect": "sensor_error", "sensor": self.sensor, "kind": self.kind,
                "column": self.column, "onset": self.onset}


def _box_mask(region: dict[str, np.ndarray], box: dict[str, list[float]]) -> np.ndarray:
    m = None
    for name, (lo, hi) in box.items():
        x = region[name]
        k = (x >= lo) & (x < hi)
        m = k if m is None else m & k
    if m is None:
        raise ValueError("an empty region box")
    return np.asarray(m, bool)


@dataclass(frozen=True)
class LocalRegion(Effect):
    """An offset confined to an axis-aligned box of the model's operating region.

    The box comes from the training error map: quantile bins per axis, bin means tested
    against an autocorrelation-corrected standard error, the connected cluster of significant
    same-sign bins around the strongest one, and its bounding box.
    """

    bins: int = 6
    z_min: float = 4.0
    id = "local_region"

    @property
    def n_params(self) -> int:
        return 5

    def fit(self, ctx: ChannelContext, base: np.ndarray, train: np.ndarray, *,
            refine: bool = False) -> dict[str, Any]:
        names = list(ctx.region)[:2]
        cols = [ctx.region[n] for n in names]
        m = _train_mask(ctx, base, train, *cols)
        none = {"region": {}, "offset": 0.0}
        if len(names) == 0 or m.sum() < 10 * self.bins ** len(names):
            return none
        r = ctx.y[m] - base[m]
        edges = [np.unique(np.quantile(c[m], np.linspace(0, 1, self.bins + 1))) for c in cols]
        idx = [np.clip(np.searchsorted(e, c[m], side="right") - 1, 0, len(e) - 2)
               for e, c in zip(edges, cols)]
        shape = tuple(len(e) - 1 for e in edges)
        flat = np.ravel_multi_index(idx, shape)
        cnt = np.bincount(flat, minlength=int(np.prod(shape))).reshape(shape)
        s = np.bincount(flat, weights=r, minlength=int(np.prod(shape))).reshape(shape)
        mean = np.where(cnt > 0, s / np.maximum(cnt, 1), 0.0)
        # noise level and serial correlation from the within-bin residual (the effect itself
        # must not count as noise); correlation inflates a bin mean's variance by about
        # (1 + rho) / (1 - rho)
        rc = r - mean.ravel()[flat]
        rho = float(np.clip(np.dot(rc[1:], rc[:-1]) / max(np.dot(rc, rc), 1e-300), 0.0, 0.995))
        infl = (1 + rho) / (1 - rho)
        se = np.std(rc) * np.sqrt(infl / np.maximum(cnt, 1))
        z = np.where(cnt >= 5, mean / np.maximum(se, 1e-300), 0.0)
        k0 = np.unravel_index(int(np.argmax(np.abs(z))), shape)
        if abs(z[k0]) < self.z_min:
            return none
        sign = np.sign(z[k0])
        good = sign * z >= self.z_min
        cluster = {k0}
        stack = [k0]
        while stack:
            cur = stack.pop()
            for ax in range(len(shape)):
                for step in (-1, 1):
                    nbl = list(cur)
                    nbl[ax] += step
                    nb = tuple(nbl)
                    if 0 <= nb[ax] < shape[ax] and good[nb] and nb not in cluster:
                        cluster.add(nb)
                        stack.append(nb)
        box = {}
        for ax, name in enumerate(names):
            lo_i = min(c[ax] for c in cluster)
            hi_i = max(c[ax] for c in cluster)
            # finite edges even at the ends of the training data: no extrapolation of a
            # local effect beyond the operating points it was seen at
            lo = float(edges[ax][lo_i])
            hi = float(np.nextafter(edges[ax][hi_i + 1], np.inf))
            box[name] = [lo, hi]
        reg = {n: c[m] for n, c in zip(names, cols)}

        def gain(b: dict[str, Any]) -> float:  # SSE reduction of the best offset inside box b
            ins = _box_mask(reg, b)
            k = int(ins.sum())
            return float(r[ins].sum()) ** 2 / k if k >= 5 else 0.0

        # the bins only place the edges to a bin width: move each edge over the two bins
        # around it (coordinate search on the training SSE)
        for ax, name in enumerate(names):
            e = edges[ax]
            for side in (0, 1):
                edge = box[name][side]
                j = int(np.clip(np.searchsorted(e, edge), 1, len(e) - 2))
                cands = np.linspace(e[j - 1], e[j + 1], 25)
                best_v, best_g = edge, gain(box)
                for v in cands:
                    trial = {**box, name: list(box[name])}
                    trial[name][side] = float(v)
                    if trial[name][0] < trial[name][1]:
                        g = gain(trial)
                        if g > best_g:
                            best_v, best_g = float(v), g
                box[name][side] = best_v
        inside = _box_mask(reg, box)
        off = float(r[inside].mean()) if inside.any() else 0.0
        return {"region": box, "offset": off}

    def apply(self, ctx: ChannelContext, base: np.ndarray, params: dict[str, Any]
              ) -> np.ndarray:
        if not params["region"]:
            return base.copy()
        inside = _box_mask(ctx.region, params["region"])
        return np.asarray(base + params["offset"] * inside, float)


EFFECT_TYPES = {cls.id: cls for cls in (Offset, GainError, Drift, SensorLag, DeadTime,
                                        InputDependence, Leak, MissingHarmonic, LocalRegion)}


def effect_from_dict(d: dict[str, Any]) -> Effect:
    """Rebuild an effect from :meth:`Effect.to_dict`."""
    d = dict(d)
    kind = d.pop("effect")
    if kind == "sensor_error":
        return SensorError(**d)
    if kind not in EFFECT_TYPES:
        raise ValueError(f"unknown effect {kind!r}; known: {sorted(EFFECT_TYPES)}")
    if "orders" in d:
        d["orders"] = tuple(d["orders"])
    return EFFECT_TYPES[kind](**d)


def candidates(ctx: ChannelContext, *, effects: tuple[str, ...] = CATALOGUE,
               onset: bool = True, sensor_effects: tuple[str, ...] | None = None
               ) -> list[Effect]:
    """Every candidate extension applicable to this channel's data: the ``effects`` on the
    channel itself, and the ``sensor_effects`` (default: ``effects``) on each input sensor of
    its model (:class:`SensorError`; only when the context names sensors)."""
    out: list[Effect] = []
    for e in (effects if sensor_effects is None else sensor_effects):
        if e in SENSOR_KINDS:
            out += _sensor_candidates(ctx, e, onset)
    for e in effects:
        if e == "offset":
            out += [Offset()] + ([Offset(onset=True), Offset(piecewise=True)] if onset else [])
        elif e == "gain_error":
            out += [GainError()] + ([GainError(onset=True), GainError(piecewise=True)]
                                    if onset else [])
        elif e == "drift":
            out.append(Drift())
        elif e == "sensor_lag":
            out.append(SensorLag())
        elif e == "dead_time":
            out.append(DeadTime())
        elif e == "input_dependence":
            # a measured signal: linear, and linear with a square (the linear case nests in
            # it: parsimony names it when the square adds nothing held-out); a slope: linear
            for c in ctx.columns:
                out += [InputDependence(column=c, degree=1)] + (
                    [] if c.startswith("d/dt ") else [InputDependence(column=c, degree=2)])
        elif e == "leak" and ctx.leak_q is not None:
            out += [Leak()] + ([Leak(onset=True), Leak(piecewise=True)] if onset else [])
        elif e == "missing_harmonic" and ctx.alpha is not None:
            # orders the crank-angle sampling resolves (below 0.45 of the Nyquist order)
            da = float(np.median(np.diff(ctx.alpha)))
            top = 0.45 * 180.0 / da if da > 0 else 0.0
            orders = tuple(k for k in MissingHarmonic().orders if k <= top)
            if orders:
                out.append(MissingHarmonic(orders=orders))
        elif e == "local_region" and ctx.region:
            out.append(LocalRegion())
    return out


def _sensor_candidates(ctx: ChannelContext, kind: str, onset: bool) -> list[Effect]:
    """The errors of kind ``kind`` on each input sensor of the channel's model."""
    out: list[Effect] = []
    for s in ctx.sensors:
        if kind == "input_dependence":
            out += [SensorError(sensor=s, kind=kind, column=c) for c in ctx.columns
                    if not c.startswith("d/dt ")]
        else:
            out.append(SensorError(sensor=s, kind=kind))
            if onset and kind in ("offset", "gain_error"):
                out.append(SensorError(sensor=s, kind=kind, onset=True))
    return out
