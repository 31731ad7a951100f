"""Takagi-Sugeno fuzzy systems trained by Levenberg-Marquardt (Diao & Passino 2004, sec. 2).

Model (paper eqs. 9-13 with the premise on one input)::

    f(x) = sum_r w_r(z_p) g_r(z) / sum_r w_r(z_p)
    w_r(z_p) = exp(-1/2 ((z_p - c_r) / s_r)^2)             Gaussian premise, rule r = 1..R
    g_r(z) = a_r0 + sum_j a_rj z_j                         affine consequent
    z = (x - offset) / scale                               fixed input normalisation

with x the raw inputs (here XNL, XNH, WF36) and p the premise input (XNL). The parameters
theta = (c_1..c_R, s_1..s_R, a_10..a_Rn) enter nonlinearly and are fitted by minimising
``sum_k (f(x_k) - y_k)^2`` with ``scipy.optimize.least_squares(method="lm")`` and the analytic
Jacobian (xi_r = w_r / sum w, the normalised firing strengths)::

    df/da_rj = xi_r z_j                        (z_0 = 1)
    df/dc_r  = xi_r (g_r - f) (z_p - c_r) / s_r^2
    df/ds_r  = xi_r (g_r - f) (z_p - c_r)^2 / s_r^3

A one-rule system is an affine model and its LM fit equals affine least squares (test oracle).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True)
class _TSParameters:
    """Parameters of one (or, with leading batch axes, many) Takagi-Sugeno systems."""

    centers: np.ndarray
    sigmas: np.ndarray
    coef: np.ndarray
    offset: np.ndarray
    scale: np.ndarray
    premise: int = 0


@dataclass(frozen=True)
class TakagiSugeno(_TSParameters):
    """A fitted Takagi-Sugeno system (immutable).

    Attributes
    ----------
    centers, sigmas : (R,) premise Gaussians in normalised premise units.
    coef : (R, n_in + 1) consequent coefficients [a_r0, a_r1..a_rn] on normalised inputs.
    offset, scale : (n_in,) input normalisation ``z = (x - offset) / scale``.
    premise : index of the premise input.
    """

    def __post_init__(self) -> None:
        r = self.centers.shape[0]
        n_in = self.offset.shape[0]
        if self.sigmas.shape != (r,) or self.coef.shape != (r, n_in + 1):
            raise ValueError("inconsistent Takagi-Sugeno parameter shapes")
        if self.scale.shape != (n_in,) or np.any(self.scale <= 0):
            raise ValueError("scale must be positive, one per input")
        if not 0 <= self.premise < n_in:
            raise ValueError("premise index out of range")
        if np.any(self.sigmas <= 0):
            raise ValueError("premise widths must be positive")

    @property
    def n_rules(self) -> int:
        return int(self.centers.shape[0])

    def normalise(self, x: Array) -> Array:
        z: Array = (np.asarray(x, dtype=float) - self.offset) / self.scale
        return z

    def __call__(self, x: Array) -> Array:
        """f(x) for raw inputs x (..., n_in)."""
        return _evaluate(self.normalise(x), self.premise, self.centers, self.sigmas,
                         self.coef)[0]

    def theta(self) -> np.ndarray:
        return np.concatenate([self.centers, self.sigmas, self.coef.ravel()])

    def with_theta(self, theta: np.ndarray) -> TakagiSugeno:
        c, s, a = _split(np.asarray(theta, dtype=float), self.n_rules, self.offset.shape[0])
        return TakagiSugeno(centers=c, sigmas=np.abs(s), coef=a, offset=self.offset,
                            scale=self.scale, premise=self.premise)

    def jacobian(self, x: Array) -> Array:
        """Analytic d f(x_k) / d theta, shape (n, 2R + R (n_in + 1))."""
        return _jacobian(self.normalise(x), self.premise, self.centers, self.sigmas, self.coef)


def _split(theta: Array, r: int, n_in: int) -> tuple[Array, Array, Array]:
    return theta[:r], theta[r:2 * r], theta[2 * r:].reshape(r, n_in + 1)


def _evaluate(z: Array, premise: int, c: Array, s: Array, a: Array
              ) -> tuple[Array, Array, Array, Array]:
    """f, normalised strengths xi (..., R), consequents g (..., R), regressors phi (..., n+1)."""
    zp = z[..., premise, None]
    logw = -0.5 * ((zp - c) / s) ** 2
    logw = logw - logw.max(axis=-1, keepdims=True)  # scaling cancels in xi; avoids underflow
    w = np.exp(logw)
    xi = w / w.sum(axis=-1, keepdims=True)
    phi = np.concatenate([np.ones(z.shape[:-1] + (1,)), z], axis=-1)
    g = np.einsum("...rj,...j->...r", a, phi)
    return (xi * g).sum(axis=-1), xi, g, phi


def _jacobian(z: Array, premise: int, c: Array, s: Array, a: Array) -> Array:
    f, xi, g, phi = _evaluate(z, premise, c, s, a)
    d = z[..., premise, None] - c
    common = xi * (g - f[..., None])
    dc = common * d / s**2
    ds = common * d**2 / s**3
    da = (xi[..., :, None] * phi[..., None, :]).reshape(z.shape[:-1] + (-1,))
    return np.concatenate([dc, ds, da], axis=-1)


@dataclass(frozen=True)
class TSFitResult:
    """Result record of :func:`fit_ts` (like scipy's OptimizeResult)."""

    model: TakagiSugeno
    x: np.ndarray
    success: bool
    message: str
    nfev: int
    njev: int
    cost: float
    rmse: float
    cost_history: np.ndarray = field(repr=False)
    time_s: float = 0.0


def initial_model(x: np.ndarray, y: np.ndarray, *, n_rules: int, premise: int,
                  offset: np.ndarray, scale: np.ndarray) -> TakagiSugeno:
    """Starting point: centres at premise quantiles, widths from their spacing, consequents by
    least squares given those premises (the problem is linear in the consequents)."""
    z = (x - offset) / scale
    zp = z[:, premise]
    if n_rules == 1:
        c = np.array([float(np.median(zp))])
        s = np.array([max(float(np.ptp(zp)), 1e-3)])
    else:
        c = np.quantile(zp, (np.arange(n_rules) + 0.5) / n_rules)
        spacing = max(float(np.min(np.diff(c))), 1e-3)
        s = np.full(n_rules, spacing)
    a0 = np.zeros((n_rules, x.shape[1] + 1))
    _, xi, _, phi = _evaluate(z, premise, c, s, a0)
    reg = (xi[:, :, None] * phi[:, None, :]).reshape(len(y), -1)
    sol, *_ = np.linalg.lstsq(reg, y, rcond=None)
    return TakagiSugeno(centers=c, sigmas=s, coef=sol.reshape(n_rules, -1), offset=offset,
                        scale=scale, premise=premise)


def fit_ts(x: np.ndarray, y: np.ndarray, *, n_rules: int = 3, premise: int = 0,
           offset: np.ndarray | None = None, scale: np.ndarray | None = None,
           init: TakagiSugeno | None = None, max_nfev: int = 400) -> TSFitResult:
    """Fit a Takagi-Sugeno system to samples by Levenberg-Marquardt with analytic Jacobian.

    Parameters
    ----------
    x : (n, n_in) raw inputs; y : (n,) targets (e.g. XNLdot [rpm/s]).
    n_rules : R; premise : index of the premise input (paper: XNL, index 0).
    offset, scale : input normalisation (default: sample mean and standard deviation).
    init : starting model (default :func:`initial_model`).
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    if x.ndim != 2 or y.shape != (x.shape[0],):
        raise ValueError(f"x must be (n, n_in) and y (n,), got {x.shape} and {y.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ValueError("training data contain NaN or inf")
    n_par = 2 * n_rules + n_rules * (x.shape[1] + 1)
    if n_rules < 1 or x.shape[0] < n_par:
        raise ValueError(f"need n_rules >= 1 and at least {n_par} samples")
    offset = x.mean(axis=0) if offset is None else np.asarray(offset, dtype=float)
    scale = x.std(axis=0) if scale is None else np.asarray(scale, dtype=float)
    scale = np.where(scale > 0, scale, 1.0)
    model0 = init or initial_model(x, y, n_rules=n_rules, premise=premise, offset=offset,
                                   scale=scale)
    z = (x - offset) / scale
    history: list[float] = []

    def fun(theta: Array) -> Array:
        c, s, a = _split(theta, n_rules, x.shape[1])
        r: Array = _evaluate(z, premise, c, s, a)[0] - y
        history.append(0.5 * float(r @ r))
        return r

    def jac(theta: Array) -> Array:
        c, s, a = _split(theta, n_rules, x.shape[1])
        return _jacobian(z, premise, c, s, a)

    from scipy.optimize import least_squares  # training only: a model node never loads it

    t0 = time.perf_counter()
    sol = least_squares(fun, model0.theta(), jac=jac, method="lm", max_nfev=max_nfev,
                        x_scale="jac")
    model = model0.with_theta(sol.x)
    return TSFitResult(model=model, x=sol.x, success=bool(sol.success), message=sol.message,
                       nfev=int(sol.nfev), njev=int(sol.njev or 0), cost=float(sol.cost),
                       rmse=float(np.sqrt(2 * sol.cost / len(y))),
                       cost_history=np.asarray(history), time_s=time.perf_counter() - t0)


@dataclass(frozen=True)
class StackedTS(_TSParameters):
    """Many Takagi-Sugeno systems with the same shape, evaluated together (batch axes first).

    ``centers, sigmas`` (..., R); ``coef`` (..., R, n_in+1); one shared ``offset, scale``.
    """

    @classmethod
    def stack(cls, models: list[TakagiSugeno]) -> StackedTS:
        first = models[0]
        for m in models:
            if not (np.array_equal(m.offset, first.offset) and np.array_equal(m.scale, first.scale)
                    and m.premise == first.premise and m.n_rules == first.n_rules):
                raise ValueError("stacked models must share normalisation, premise and R")
        return cls(centers=np.stack([m.centers for m in models]),
                   sigmas=np.stack([m.sigmas for m in models]),
                   coef=np.stack([m.coef for m in models]), offset=first.offset,
                   scale=first.scale, premise=first.premise)

    def take(self, index: int | slice | Sequence[int] | NDArray[np.intp]) -> StackedTS:
        """The stacked systems at ``index`` of the first batch axis."""
        return StackedTS(centers=self.centers[index], sigmas=self.sigmas[index],
                         coef=self.coef[index], offset=self.offset, scale=self.scale,
                         premise=self.premise)

    def __call__(self, x: Array) -> Array:
        """Evaluate every stacked model at inputs x broadcastable to (..., n_in)."""
        z: Array = (np.asarray(x, dtype=float) - self.offset) / self.scale
        return _evaluate(z, self.premise, self.centers, self.sigmas, self.coef)[0]
