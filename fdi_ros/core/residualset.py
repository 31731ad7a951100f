"""Several residuals of one plant as one baseline model for the discrepancy analysis.

One relation per component of an air path, each predicting one measured signal from others:

* :class:`~fdi_ros.core.meanvalue.SpeedDensityModel`: the air flow into the cylinders from
  speed, manifold pressure and temperature;
* :class:`ThrottleFlowModel`: the same air flow through the throttle, from the pressures on
  both sides, the temperature and the throttle position (isentropic orifice flow through an
  effective area that is a polynomial of the position, plus the air stored upstream while its
  pressure changes);
* :class:`PressureMapModel`: a pressure over a reference pressure as a static map of other
  signals (e.g. the boost pressure over ambient from speed, air flow and throttle).

:class:`ResidualSet` joins them: its ``channels`` are the residual names, ``measures`` says
which signal each one compares with its model and ``uses`` which signals each model reads, so
that an error of one signal is scored on every residual that reads it
(:mod:`fdi_ros.core.discrepancy.joint`): a sensor that two relations read is told apart from
one that only one of them reads.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fdi_ros.core.constants import R_AIR
from fdi_ros.core.discrepancy.context import LeakSpec, orifice_flux, smooth_derivative
from fdi_ros.core.meanvalue import (
    harmonic_basis,
    harmonic_regressors,
    pulsation,
    segment_smoothed,
    stacked_lstsq,
)
from fdi_ros.core.measured import Measured


def poly_basis(z: np.ndarray, degree: int) -> np.ndarray:
    """All monomials of the columns of ``z`` (N, k) up to total ``degree`` (N, m)."""
    n, k = z.shape
    cols = [np.ones(n)]
    terms: list[tuple[int, ...]] = [()]
    for _ in range(degree):
        nxt = []
        for t in terms:
            start = t[-1] if t else 0
            for j in range(start, k):
                nxt.append(t + (j,))
        for t in nxt:
            cols.append(np.prod(z[:, list(t)], axis=1))
        terms = nxt
    return np.stack(cols, axis=1)


def _ranges(recs: list[Measured], names: tuple[str, ...]) -> tuple[tuple[float, float], ...]:
    out = []
    for name in names:
        x = np.concatenate([np.asarray(r[name], float) for r in recs])
        x = x[np.isfinite(x)]
        lo, hi = float(x.min()), float(x.max())
        if not hi > lo:
            raise ValueError(f"identification data must vary in {name}")
        out.append((lo, hi))
    return tuple(out)


def _scaled(data: Measured, names: tuple[str, ...], ranges: tuple[tuple[float, float], ...],
            margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Inputs scaled to [0, 1] over their identified ranges, and the samples outside."""
    z = np.stack([(np.asarray(data[n], float) - lo) / (hi - lo)
                  for n, (lo, hi) in zip(names, ranges)], axis=1)
    out = np.any((z < -margin) | (z > 1.0 + margin), axis=1)
    return z, out


def _lists(x: Any) -> Any:
    """Tuples (nested) as lists, for JSON."""
    return [_lists(v) for v in x] if isinstance(x, (tuple, list)) else x


def _tuples(x: Any) -> Any:
    """Lists (nested) as tuples of floats or strings, back from JSON."""
    return tuple(_tuples(v) for v in x) if isinstance(x, list) else x


class _Saved:
    """Save and load a frozen dataclass model through its fields (``kind`` as ``type``)."""

    kind: str

    __dataclass_fields__: dict[str, Any]

    def to_params(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__ if k != "kind"}

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {k: _lists(v) for k, v in self.to_params().items()}
        d["type"] = self.kind
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Any:
        return cls(**{k: _tuples(v) for k, v in d.items() if k != "type"})


@dataclass(frozen=True)
class ThrottleFlowModel(_Saved):
    """Air flow through a throttle: ``m = A(theta) q(p_up, T, p_down) + V / (R T) dp_up/dt``.

    ``q`` the isentropic flux per unit area (:func:`~fdi_ros.core.discrepancy.context.
    orifice_flux`), ``A`` a polynomial of the position scaled to its identified range (an
    effective area: discharge coefficient and geometry), the second term the air stored in
    the volume upstream (the flow is metered before it); all coefficients from one linear
    least-squares fit. Positions below ``min_position`` (a nearly closed throttle, whose
    effective area is dominated by the position sensor's offset and the bypass) and
    operating points outside the identified range are not predicted (NaN).
    """

    name: str = "maf_throttle"
    channel: str = "maf"
    position: str = "throttle"
    p_up: str = "p_ic"
    p_down: str = "p_im"
    T: str = "T_im"
    flow_scale: float = 3600.0
    degree: int = 3
    storage: bool = True
    derivative_window_s: float = 0.1
    min_position: float = 0.0
    margin: float = 0.05
    coef: tuple[float, ...] = ()
    volume_l: float = 0.0
    position_range: tuple[float, float] = (0.0, 0.0)
    kind: str = field(default="throttle_flow", init=False)

    @property
    def inputs(self) -> tuple[str, ...]:
        return (self.position, self.p_up, self.p_down, self.T)

    def _flux(self, data: Measured) -> np.ndarray:
        p_up = np.asarray(data[self.p_up], float)
        p_dn = np.asarray(data[self.p_down], float)
        T = np.asarray(data[self.T], float)
        q = orifice_flux(np.maximum(p_up, p_dn), T, np.minimum(p_up, p_dn))
        return np.asarray(np.sign(p_up - p_dn) * q * self.flow_scale, float)

    def _regressors(self, data: Measured, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
        theta = np.asarray(data[self.position], float)
        z = (theta - lo) / (hi - lo)
        q = self._flux(data)
        cols = [q * z ** k for k in range(self.degree + 1)]
        if self.storage:
            T = np.asarray(data[self.T], float)
            cols.append(smooth_derivative(np.asarray(data[self.p_up], float), data.t,
                                          data.segment, self.derivative_window_s)
                        * 1e-3 / (R_AIR * T) * self.flow_scale)
        bad = (z < -self.margin) | (z > 1 + self.margin) | (theta < self.min_position)
        return np.stack(cols, axis=1), bad

    def predict(self, data: Measured) -> dict[str, np.ndarray]:
        if not self.coef:
            raise ValueError("the throttle-flow model is not identified yet (call fit)")
        A, bad = self._regressors(data, *self.position_range)
        c = np.asarray(self.coef + ((self.volume_l,) if self.storage else ()))
        return {self.name: np.where(bad, np.nan, A @ c)}

    def fit(self, data: Measured | list[Measured]) -> ThrottleFlowModel:
        recs = data if isinstance(data, list) else [data]
        (lo, hi), = _ranges(recs, (self.position,))
        pairs = []
        for r in recs:
            A, bad = self._regressors(r, lo, hi)
            pairs.append((A, np.where(bad, np.nan, np.asarray(r[self.channel], float))))
        sol, _, _ = stacked_lstsq(pairs, "the throttle")
        k = self.degree + 1
        return ThrottleFlowModel(**{**self.to_params(), "coef": tuple(float(v) for v in sol[:k]),
                                    "volume_l": float(sol[k]) if self.storage else 0.0,
                                    "position_range": (lo, hi)})



@dataclass(frozen=True)
class PressureMapModel(_Saved):
    """A pressure ratio as a map with a first-order lag: ``ln(p / p_ref) = L_tau[poly(x)]``.

    ``x`` the ``regressors`` scaled to their identified ranges (all monomials up to total
    degree ``degree``), ``L_tau`` a first-order lag (the pressure follows its operating point
    with a time constant, e.g. a turbocharger's inertia); NaN outside the identified ranges.
    Identification: for each time constant on a grid (``max_lag_s``; 0: a static map) the
    lagged regressors are fitted by linear least squares (the lag is linear), and the time
    constant with the lowest sum of squares is kept.
    """

    channel: str = "p_ic"
    reference: str = "p_amb"
    regressors: tuple[str, ...] = ("n", "maf", "throttle")
    degree: int = 2
    margin: float = 0.05
    max_lag_s: float = 0.0
    coef: tuple[float, ...] = ()
    ranges: tuple[tuple[float, float], ...] = ()
    lag_s: float = 0.0
    kind: str = field(default="pressure_map", init=False)

    @property
    def name(self) -> str:
        return self.channel

    @property
    def inputs(self) -> tuple[str, ...]:
        return (self.reference, *self.regressors)

    def _basis(self, data: Measured, ranges: tuple[tuple[float, float], ...], lag_s: float
               ) -> tuple[np.ndarray, np.ndarray]:
        z, out = _scaled(data, self.regressors, ranges, self.margin)
        A = poly_basis(z, self.degree)
        if lag_s > 0:
            A = np.stack([_lag(a, data, lag_s) for a in A.T], axis=1)
        return A, out

    def predict(self, data: Measured) -> dict[str, np.ndarray]:
        if not self.coef:
            raise ValueError("the pressure map is not identified yet (call fit)")
        z, out = _scaled(data, self.regressors, self.ranges, self.margin)
        ln_ratio = poly_basis(z, self.degree) @ np.asarray(self.coef)
        if self.lag_s > 0:  # the lag is linear: lag the map's output, not every regressor
            ln_ratio = _lag(ln_ratio, data, self.lag_s)
        p = np.asarray(data[self.reference], float) * np.exp(ln_ratio)
        return {self.channel: np.where(out, np.nan, p)}

    def fit(self, data: Measured | list[Measured]) -> PressureMapModel:
        recs = data if isinstance(data, list) else [data]
        ranges = _ranges(recs, self.regressors)
        best: tuple[float, float, np.ndarray] | None = None
        lags = [0.0] + (list(np.geomspace(0.05, self.max_lag_s, 24)) if self.max_lag_s > 0
                        else [])
        for lag in lags:
            pairs = []
            for r in recs:
                A, out = self._basis(r, ranges, lag)
                y = np.log(np.asarray(r[self.channel], float)
                           / np.asarray(r[self.reference], float))
                pairs.append((A, np.where(out, np.nan, y)))
            sol, A, y = stacked_lstsq(pairs, self.channel)
            sse = float(np.sum((y - A @ sol) ** 2))
            if best is None or sse < best[0]:
                best = (sse, float(lag), sol)
        assert best is not None
        return PressureMapModel(**{**self.to_params(), "coef": tuple(float(v) for v in best[2]),
                                   "ranges": ranges, "lag_s": best[1]})



@dataclass(frozen=True)
class PulsationMapModel(_Saved):
    """The crank-angle pulsation of one measured signal as a map of the operating point.

    ``x(alpha) = xbar + sum_k a_k(n, l) cos(2 pi k alpha / 180) + b_k(n, l) sin(...)``, with
    ``xbar`` the reading's own mean over a sliding 180 deg CA window and the Fourier
    coefficient maps linear in :func:`~fdi_ros.core.meanvalue.harmonic_basis` of the means of
    the speed ``n`` and of a ``load`` signal: a residual of the pulsation alone (the mean
    cancels). It checks explanations the mean-value residuals cannot tell apart: a gain of the
    reading scales its pulsation, a lag damps it, a dead time shifts it, an error of the load
    signal moves the prediction, while an error of any other sensor leaves it as it is. The
    load must not be the reading itself: a gain of the reading would move the prediction with
    it (the pulsation of a manifold pressure grows about in proportion to the pressure). For
    an intake manifold pressure the air flow is the load: the cylinders' suction drives the
    pulsation. Identified by linear least squares on fault-free crank-resolved records; NaN
    outside the identified speeds and loads (with a margin) and without a crank angle.
    """

    channel: str = "p2"
    n: str = "n"
    load: str = "maf"
    orders: tuple[float, ...] = (1.0,)
    harmonic_degree: int = 1
    harmonic_knots: int = 12
    margin: float = 0.05
    n_range: tuple[float, float] = (0.0, 0.0)
    load_range: tuple[float, float] = (0.0, 0.0)
    harm_coef: tuple[float, ...] = ()
    kind: str = field(default="pulsation_map", init=False)

    def __post_init__(self) -> None:
        if not self.orders:
            raise ValueError("a pulsation map needs at least one order")
        if self.channel in (self.n, self.load):
            raise ValueError(f"the pulsation of {self.channel} cannot be mapped over itself")

    @property
    def name(self) -> str:
        return f"{self.channel} pulsation"

    @property
    def inputs(self) -> tuple[str, ...]:
        return (self.n, self.load)

    @property
    def channels(self) -> tuple[str, ...]:
        return (self.name,)

    def region(self, data: Measured) -> dict[str, np.ndarray]:
        return {self.n: data[self.n], self.load: data[self.load]}

    def without_pulsation(self) -> None:
        """Nothing: on segment means the pulsation averages out."""
        return None

    def _basis(self, sm: Measured, ranges: tuple[tuple[float, float], ...]
               ) -> tuple[np.ndarray, np.ndarray]:
        z, out = _scaled(sm, self.inputs, ranges, self.margin)
        out |= ~np.isfinite(z).all(axis=1)  # the sliding window's ends
        z = np.where(out[:, None], 0.0, z)
        return harmonic_basis(z[:, 0], z[:, 1], self.harmonic_degree, self.harmonic_knots), out

    def predict(self, data: Measured) -> dict[str, np.ndarray]:
        if not self.harm_coef:
            raise ValueError("the pulsation map is not identified yet (call fit)")
        if data.alpha is None:
            return {self.name: np.full(data.n_samples, np.nan)}
        sm = segment_smoothed(data, {self.n, self.load, self.channel})
        poly, out = self._basis(sm, (self.n_range, self.load_range))
        x = np.asarray(sm[self.channel], float) + pulsation(
            poly, np.asarray(data.alpha, float), self.orders, self.harm_coef)
        return {self.name: np.where(out, np.nan, x)}

    def fit(self, data: Measured | list[Measured]) -> PulsationMapModel:
        recs = data if isinstance(data, list) else [data]
        if any(r.alpha is None for r in recs):
            raise ValueError("a pulsation map is identified on crank-resolved records")
        sms = [segment_smoothed(r, {self.n, self.load, self.channel}) for r in recs]
        ranges = _ranges(sms, self.inputs)
        pairs = []
        for r, s in zip(recs, sms):
            poly, out = self._basis(s, ranges)
            y = np.asarray(r[self.channel], float) - np.asarray(s[self.channel], float)
            pairs.append((harmonic_regressors(poly, np.asarray(r.alpha, float), self.orders),
                          np.where(out, np.nan, y)))
        sol, _, _ = stacked_lstsq(pairs, f"the pulsation of {self.channel}")
        return PulsationMapModel(**{**self.to_params(), "n_range": ranges[0],
                                    "load_range": ranges[1],
                                    "harm_coef": tuple(float(v) for v in sol)})



def _lag(x: np.ndarray, data: Measured, tau_s: float) -> np.ndarray:
    from fdi_ros.core.discrepancy.effects import lowpass

    return lowpass(x, data.t, data.segment, tau_s)


def _name(m: Any) -> str:
    return str(getattr(m, "name", None) or m.channels[0])


@dataclass(frozen=True)
class ResidualSet:
    """Residual models of one plant as one baseline (see the module docstring).

    The first model is the main one: its operating region spans the error map and its
    leaks are the leak candidates.
    """

    models: tuple[Any, ...]
    checks: tuple[str, ...] = ()  # residuals that only check the leading explanations
    kind: str = field(default="residual_set", init=False)

    def __post_init__(self) -> None:
        names = [_name(m) for m in self.models]
        if not names or len(set(names)) != len(names):
            raise ValueError(f"a residual set needs models with distinct names, got {names}")
        if not set(self.checks) <= set(names[1:]):
            raise ValueError(f"checks {list(self.checks)} must name residuals after the first "
                             f"({names})")

    @property
    def channels(self) -> tuple[str, ...]:
        return tuple(_name(m) for m in self.models)

    @property
    def measures(self) -> dict[str, str]:
        return {_name(m): str(getattr(m, "channel", _name(m))) for m in self.models}

    @property
    def uses(self) -> dict[str, tuple[str, ...]]:
        return {_name(m): tuple(m.inputs) for m in self.models}

    @property
    def inputs(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(s for m in self.models for s in m.inputs))

    @property
    def leaks(self) -> tuple[LeakSpec, ...]:
        return tuple(getattr(self.models[0], "leaks", ()))

    @property
    def orders(self) -> tuple[float, ...]:
        """The crank-angle orders any member predicts (empty: mean-value relations only)."""
        return tuple(sorted({o for m in self.models for o in getattr(m, "orders", ())}))

    def without_pulsation(self) -> ResidualSet:
        """The relations on segment means: every member without its pulsation terms, the
        members that predict nothing but a pulsation left out."""
        keep = []
        for m in self.models:
            if not getattr(m, "orders", ()):
                keep.append(m)
            elif (mean := m.without_pulsation()) is not None:
                keep.append(mean)
        names = {_name(m) for m in keep}
        return ResidualSet(models=tuple(keep),
                           checks=tuple(c for c in self.checks if c in names))

    def region(self, data: Measured) -> dict[str, np.ndarray]:
        return dict(self.models[0].region(data))

    def model_of(self, channel: str) -> Any:
        """The member model that predicts residual ``channel`` (re-running one relation is
        enough to see how an input's error moves its residual)."""
        return next(m for m in self.models if _name(m) == channel)

    def predict(self, data: Measured) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {}
        for m in self.models:
            pred = m.predict(data)
            out[_name(m)] = pred[next(iter(pred))] if len(pred) == 1 else pred[_name(m)]
        return out

    def fit(self, data: Measured | list[Measured]) -> ResidualSet:
        return ResidualSet(models=tuple(m.fit(data) for m in self.models), checks=self.checks)

    def to_dict(self) -> dict[str, Any]:
        return {"type": self.kind, "models": [m.to_dict() for m in self.models],
                "checks": list(self.checks)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ResidualSet:
        from fdi_ros.core.meanvalue import SpeedDensityModel

        kinds: dict[str, Any] = {"speed_density": SpeedDensityModel,
                                 "throttle_flow": ThrottleFlowModel,
                                 "pressure_map": PressureMapModel,
                                 "pulsation_map": PulsationMapModel}
        unknown = sorted({str(m.get("type")) for m in d["models"]} - set(kinds))
        if unknown:
            raise ValueError(f"residual set: unknown model types {unknown} (known: "
                             f"{sorted(kinds)})")
        return cls(models=tuple(kinds[m["type"]].from_dict(m) for m in d["models"]),
                   checks=tuple(d.get("checks", ())))
