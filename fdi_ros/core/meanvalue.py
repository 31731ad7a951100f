"""Speed-density mean-value intake model of a reciprocating engine (any displacement).

The air mass flow an engine of displacement V_D draws at speed n from a manifold at pressure p
and temperature T is that of an ideal displacement pump times the volumetric efficiency:

    m_air = eta_V(n, p) * n / (60 * 2) * V_D * p / (R * T)          [kg/s], n in rpm

(one intake stroke per cylinder every two revolutions). ``eta_V`` is a low-order polynomial in
normalised (n, p) whose coefficients are identified by linear least squares *in flow space*
(``m_meas = sum_j c_j * phi_j(n, p) * m_th``), so that the operating points with large flow
weigh as they do in the residual. A flow meter upstream of the compressor, intercooler and
manifold also sees the air stored in those volumes while their pressure changes; with
``storage`` signals p_j the model adds the filling flows (isothermal)

    m_meas = m_air + sum_j V_j / (R T) * d p_j / d t

with the volumes V_j identified in the same least-squares problem. For crank-angle resolved data (a
diesel's MAF pulsates with the cylinders' suction, period 180 deg CA) ``orders`` adds the pulsation
``sum_k a_k(n, p) cos(2 pi k alpha / 180) + b_k(n, p) sin(...)`` with polynomial amplitude maps,
identified in the same linear problem. Operating points outside the identified region (with a
margin) are predicted as NaN: the analysis masks them instead of extrapolating a polynomial.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fdi_ros.core.constants import R_AIR
from fdi_ros.core.discrepancy.context import LeakSpec, smooth_derivative
from fdi_ros.core.measured import Measured


def _basis(nz: np.ndarray, pz: np.ndarray, degree: int) -> np.ndarray:
    """Monomials ``nz**i * pz**j`` (i + j <= degree) along a last axis, from running powers
    (the model is re-run thousands of times per analysis: no power function, one array)."""
    npow, ppow = [np.ones_like(nz)], [np.ones_like(pz)]
    for _ in range(degree):
        npow.append(npow[-1] * nz)
        ppow.append(ppow[-1] * pz)
    terms = [(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)]
    out = np.empty((len(terms),) + np.broadcast_shapes(nz.shape, pz.shape))
    for k, (i, j) in enumerate(terms):
        np.multiply(npow[i], ppow[j], out=out[k])
    return np.moveaxis(out, 0, -1)


def harmonic_basis(nz: np.ndarray, pz: np.ndarray, degree: int, knots: int = 0) -> np.ndarray:
    """(N, m) functions of the operating point that a pulsation's Fourier coefficients are
    linear in: monomials of scaled speed ``nz`` and pressure ``pz`` up to ``degree``, or with
    ``knots`` piecewise-linear "hat" functions of the speed on that many equally spaced knots,
    each times the powers of the pressure up to ``degree``. The phase of an intake system's
    pulsation turns with the speed (duct delays, resonances) faster than a low-order
    polynomial can follow; the hats follow it. Outside the identified speeds the end values
    hold."""
    if not knots:
        return _basis(nz, pz, degree)
    grid = np.linspace(0.0, 1.0, knots)
    hat = np.clip(1.0 - np.abs(np.clip(nz, 0.0, 1.0)[:, None] - grid[None, :]) * (knots - 1),
                  0.0, None)
    ppow = [np.ones_like(pz)]
    for _ in range(degree):
        ppow.append(ppow[-1] * pz)
    return np.hstack([hat * p[:, None] for p in ppow])


def harmonic_regressors(poly: np.ndarray, alpha: np.ndarray, orders: tuple[float, ...]
                        ) -> np.ndarray:
    """(N, 2 * len(orders) * m): the basis ``poly`` times cos and sin of every order of the
    180 deg CA period, order by order."""
    cols = []
    for k in orders:
        th = 2.0 * np.pi * k * alpha / 180.0
        cols += [poly * np.cos(th)[:, None], poly * np.sin(th)[:, None]]
    return np.hstack(cols)


def pulsation(poly: np.ndarray, alpha: np.ndarray, orders: tuple[float, ...],
              coef: tuple[float, ...]) -> np.ndarray:
    """``harmonic_regressors(poly, alpha, orders) @ coef`` without the regressor matrix: per
    order the coefficient maps ``poly @ a_k``, ``poly @ b_k`` times cos and sin."""
    k = poly.shape[1]
    c = np.asarray(coef).reshape(len(orders), 2, k)
    amp = poly @ c.reshape(-1, k).T  # (N, 2 * orders): a_1, b_1, a_2, b_2, ...
    out = np.zeros(alpha.shape)
    for i, order in enumerate(orders):
        th = 2.0 * np.pi * order * alpha / 180.0
        out += amp[:, 2 * i] * np.cos(th) + amp[:, 2 * i + 1] * np.sin(th)
    return out


def stacked_lstsq(pairs: list[tuple[np.ndarray, np.ndarray]], what: str
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear least squares over the finite rows of several records' ``(A, y)``; at least
    ten rows per unknown. Returns the solution and the stacked ``A``, ``y`` it was fitted on."""
    rows, rhs = [], []
    for A, y in pairs:
        ok = np.isfinite(A).all(axis=1) & np.isfinite(y)
        rows.append(A[ok])
        rhs.append(y[ok])
    A, y = np.concatenate(rows), np.concatenate(rhs)
    if A.shape[0] < 10 * A.shape[1]:
        raise ValueError(f"too few valid samples ({A.shape[0]}) to identify {what}")
    sol, *_ = np.linalg.lstsq(A, y, rcond=None)
    return sol, A, y


def _alpha(data: Measured) -> np.ndarray:
    if data.alpha is None:
        raise ValueError("this model predicts the crank-angle pulsation: the measured data "
                         "needs a crank angle (alpha)")
    return np.asarray(data.alpha, float)


def segment_smoothed(data: Measured, names: set[str]) -> Measured:
    """Crank-resolved signals ``names`` averaged over a sliding 180 deg CA window (NaN where
    the window is not full); data without a crank angle as it is."""
    if data.alpha is None:
        return data
    da = float(np.median(np.diff(data.alpha)))
    w = int(round(180.0 / da)) if da > 0 else 1
    if w <= 1:
        return data
    sig = dict(data.signals)
    k = np.ones(w) / w
    for name in names:
        x = data[name]
        sm = np.convolve(x, k, mode="same")
        sm[: w // 2] = np.nan
        sm[x.size - (w - 1 - w // 2):] = np.nan
        sig[name] = sm
    return Measured(t=data.t, signals=sig, units=dict(data.units), alpha=data.alpha,
                    segment=data.segment, source=data.source, mapped=data.mapped)


@dataclass(frozen=True)
class SpeedDensityModel:
    """Speed-density air-flow model ``maf = eta_V(n, p) * m_th(n, p, T)``.

    Attributes
    ----------
    displacement_l : V_D [L].
    n, p, T, channel : signal names of speed [rpm], manifold pressure [Pa], manifold
        temperature [K] and the metered air flow.
    flow_scale : channel units per kg/s (3600 for kg/h).
    coef : polynomial coefficients of eta_V (see :func:`fit`), empty before fitting.
    n_range, p_range : identified region [rpm], [Pa].
    leak_p_amb, leak_T_amb : signal names (or constants) of the surroundings for the leak
        candidate.
    """

    displacement_l: float
    n: str = "n"
    p: str = "p_im"
    T: str = "T_im"
    channel: str = "maf"
    flow_scale: float = 3600.0
    degree: int = 2
    coef: tuple[float, ...] = ()
    n_range: tuple[float, float] = (0.0, 0.0)
    p_range: tuple[float, float] = (0.0, 0.0)
    margin: float = 0.05
    leak_p_amb: str | float = "p_amb"
    leak_T_amb: str | float = "T_amb"
    leak_cd: float = 0.7
    storage: tuple[str, ...] = ()
    volumes_l: tuple[float, ...] = ()
    derivative_window_s: float = 0.25
    orders: tuple[float, ...] = ()
    harmonic_degree: int = 2
    harm_coef: tuple[float, ...] = ()
    harmonic_knots: int = 0
    kind: str = field(default="speed_density", init=False)

    def __post_init__(self) -> None:
        if not self.displacement_l > 0:
            raise ValueError("displacement_l must be > 0")
        if self.degree < 0 or self.degree > 4:
            raise ValueError("degree must be in 0..4")
        if self.harmonic_knots == 1 or self.harmonic_knots < 0:
            raise ValueError("harmonic_knots must be 0 (polynomial maps) or >= 2")

    # --- the baseline-model interface of the discrepancy analysis -------------------------
    @property
    def inputs(self) -> tuple[str, ...]:
        return (self.n, self.p, self.T) + tuple(s for s in self.storage if s != self.p)

    @property
    def channels(self) -> tuple[str, ...]:
        return (self.channel,)

    @property
    def leaks(self) -> tuple[LeakSpec, ...]:
        return (LeakSpec(channel=self.channel, p_in=self.p, T_in=self.T, p_amb=self.leak_p_amb,
                         T_amb=self.leak_T_amb, flow_scale=self.flow_scale, cd=self.leak_cd),)

    def region(self, data: Measured) -> dict[str, np.ndarray]:
        return {self.n: data[self.n], self.p: data[self.p]}

    def m_th(self, data: Measured) -> np.ndarray:
        """Ideal displacement-pump flow in channel units."""
        n, p, T = data[self.n], data[self.p], data[self.T]
        return np.asarray(n / 120.0 * self.displacement_l * 1e-3 * p / (R_AIR * T)
                          * self.flow_scale, float)

    def _z(self, data: Measured) -> tuple[np.ndarray, np.ndarray]:
        (n0, n1), (p0, p1) = self.n_range, self.p_range
        return ((data[self.n] - n0) / (n1 - n0), (data[self.p] - p0) / (p1 - p0))

    def eta_v(self, data: Measured) -> np.ndarray:
        if not self.coef:
            raise ValueError("the speed-density model is not identified yet (call fit)")
        nz, pz = self._z(data)
        eta = _basis(nz, pz, self.degree) @ np.asarray(self.coef)
        out = (nz < -self.margin) | (nz > 1 + self.margin) | (pz < -self.margin) | (
            pz > 1 + self.margin)
        return np.where(out, np.nan, eta)

    def filling_regressors(self, data: Measured) -> np.ndarray:
        """(N, len(storage)) filling flow per litre of volume, in channel units."""
        T = data[self.T]
        cols = [smooth_derivative(data[s], data.t, data.segment, self.derivative_window_s)
                * 1e-3 / (R_AIR * T) * self.flow_scale for s in self.storage]
        return np.stack(cols, axis=1) if cols else np.zeros((data.n_samples, 0))

    def _segment_smoothed(self, data: Measured) -> Measured:
        """Crank-resolved inputs averaged over a sliding 180 deg CA window.

        The mean-value part of the model must see the mean manifold state, not its pulsation
        (the pulsation of p2 times eta_V, or its derivative, is not an air flow).
        """
        return segment_smoothed(data, set(self.inputs))

    def without_pulsation(self) -> SpeedDensityModel:
        """The same mean-value model without the crank-angle pulsation terms."""
        return SpeedDensityModel(**{**self.to_params(), "orders": (), "harm_coef": ()})

    def _harmonic_basis(self, data: Measured) -> np.ndarray:
        nz, pz = self._z(data)
        return harmonic_basis(nz, pz, self.harmonic_degree, self.harmonic_knots)

    def harmonic_regressors(self, data: Measured) -> np.ndarray:
        """(N, 2 * len(orders) * n_poly) pulsation regressors (empty without orders)."""
        if not self.orders:
            return np.zeros((data.n_samples, 0))
        return harmonic_regressors(self._harmonic_basis(data), _alpha(data), self.orders)

    def predict(self, data: Measured) -> dict[str, np.ndarray]:
        data = self._segment_smoothed(data)
        m = self.eta_v(data) * self.m_th(data)
        if self.storage:
            m = m + self.filling_regressors(data) @ np.asarray(self.volumes_l)
        if self.orders and self.harm_coef:
            m = m + self._pulsation(data)
        return {self.channel: m}

    def _pulsation(self, data: Measured) -> np.ndarray:
        return pulsation(self._harmonic_basis(data), _alpha(data), self.orders, self.harm_coef)

    # --- identification and persistence -----------------------------------------------------
    def fit(self, data: Measured | list[Measured]) -> SpeedDensityModel:
        """Identify eta_V by least squares in flow space on (a list of) fault-free records.

        With pulsation ``orders`` and crank-resolved records, the mean-value part is
        identified on 180 deg CA segment means (derivatives of the pulsating pressure would
        be noise) and the pulsation maps on the crank-resolved residual of that part.
        """
        recs = data if isinstance(data, list) else [data]
        if self.orders and all(r.alpha is not None for r in recs):
            from fdi_ros.core.measured import segment_means

            mean = self.without_pulsation().fit([segment_means(r) for r in recs])
            full = SpeedDensityModel(**{**mean.to_params(), "orders": tuple(self.orders),
                                        "harm_coef": ()})
            A = np.vstack([full.harmonic_regressors(full._segment_smoothed(r))
                           for r in recs])
            y = np.concatenate([r[self.channel] - mean.predict(r)[self.channel]
                                for r in recs])
            ok = np.isfinite(A).all(axis=1) & np.isfinite(y)
            sol, *_ = np.linalg.lstsq(A[ok], y[ok], rcond=None)
            return SpeedDensityModel(**{**full.to_params(),
                                        "harm_coef": tuple(float(v) for v in sol)})
        n_all = np.concatenate([r[self.n] for r in recs])
        p_all = np.concatenate([r[self.p] for r in recs])
        ok_all = np.isfinite(n_all) & np.isfinite(p_all)
        n_range = (float(n_all[ok_all].min()), float(n_all[ok_all].max()))
        p_range = (float(p_all[ok_all].min()), float(p_all[ok_all].max()))
        if n_range[1] <= n_range[0] or p_range[1] <= p_range[0]:
            raise ValueError("identification data must vary in speed and pressure")
        proto = SpeedDensityModel(**{**self.to_params(), "n_range": n_range,
                                     "p_range": p_range, "coef": (1.0,),
                                     "volumes_l": (0.0,) * len(self.storage),
                                     "harm_coef": ()})
        pairs = []
        for r in recs:
            nz, pz = proto._z(r)
            mth = proto.m_th(r)
            pairs.append((np.hstack([_basis(nz, pz, self.degree) * mth[:, None],
                                     self.filling_regressors(r),
                                     proto.harmonic_regressors(r)]),
                          np.asarray(r[self.channel], float)))
        sol, _, _ = stacked_lstsq(pairs, "eta_V")
        k = _basis(np.zeros(1), np.zeros(1), self.degree).shape[1]
        kv = k + len(self.storage)
        return SpeedDensityModel(**{**self.to_params(), "n_range": n_range, "p_range": p_range,
                                    "coef": tuple(float(c) for c in sol[:k]),
                                    "volumes_l": tuple(float(v) for v in sol[k:kv]),
                                    "harm_coef": tuple(float(v) for v in sol[kv:])})

    def to_params(self) -> dict[str, Any]:
        return dict(displacement_l=self.displacement_l, n=self.n, p=self.p, T=self.T,
                    channel=self.channel, flow_scale=self.flow_scale, degree=self.degree,
                    coef=tuple(self.coef), n_range=tuple(self.n_range),
                    p_range=tuple(self.p_range), margin=self.margin,
                    leak_p_amb=self.leak_p_amb, leak_T_amb=self.leak_T_amb,
                    leak_cd=self.leak_cd, storage=tuple(self.storage),
                    volumes_l=tuple(self.volumes_l),
                    derivative_window_s=self.derivative_window_s,
                    orders=tuple(self.orders), harmonic_degree=self.harmonic_degree,
                    harm_coef=tuple(self.harm_coef), harmonic_knots=self.harmonic_knots)

    def to_dict(self) -> dict[str, Any]:
        d = self.to_params()
        d["type"] = self.kind
        for k in ("coef", "n_range", "p_range", "storage", "volumes_l", "orders", "harm_coef"):
            d[k] = list(d[k])
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SpeedDensityModel:
        d = {k: v for k, v in d.items() if k != "type"}
        for k in ("coef", "n_range", "p_range", "volumes_l", "orders", "harm_coef"):
            if k in d:
                d[k] = tuple(float(v) for v in d[k])
        if "storage" in d:
            d["storage"] = tuple(d["storage"])
        return cls(**d)

