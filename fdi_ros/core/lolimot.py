"""LOLIMOT: the local linear model tree of Nelles (1999, 2001).

A static nonlinear map ``y = f(x)`` is approximated by ``M`` local affine models blended by
normalised Gaussian validity functions,

.. math::

    \\hat y(x) = \\sum_{i=1}^{M} \\Phi_i(x)\\,\\bigl(w_{i0} + w_i^T z\\bigr), \\qquad
    \\Phi_i(x) = \\frac{\\mu_i(x)}{\\sum_j \\mu_j(x)}, \\qquad
    \\mu_i(x) = \\exp\\Bigl(-\\tfrac12 \\sum_d
        \\bigl(\\tfrac{z_d - c_{id}}{\\sigma_{id}}\\bigr)^2\\Bigr),

where ``z`` are the inputs scaled to the unit hypercube of the training data, ``c_i`` the centre
of hyper-rectangle ``i`` and ``sigma_i = k_sigma * (cell extent)``. Construction: start with one
cell (the data's bounding box); repeat: take the local model with the largest local loss
``I_i = sum_n Phi_i(x_n) e_n^2``, try halving its cell along every input dimension, re-estimate
the local models by weighted least squares (small ridge term), keep the best split. The number
of models is chosen by the validation error (or AICc without validation data).

The fitted tree is inspectable (:attr:`Lolimot.centres`, :attr:`Lolimot.cell_bounds`,
:meth:`Lolimot.local_parameters`) and carries a coarse coverage grid of its training data so that
:meth:`Lolimot.in_region` can say "not identified here" (e.g. low engine speed with high boost).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["Lolimot", "LolimotResult", "LolimotStack"]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

# Inputs beyond this many dimensions get no coverage grid (bins**p cells would be too many).
_MAX_GRID_CELLS = 1_000_000


@dataclass(frozen=True)
class LolimotResult:
    """Outcome of :meth:`Lolimot.fit`.

    Attributes
    ----------
    n_models : number of local models kept (the best by the selection criterion).
    loss : training RMSE after each split, index ``k`` for ``k + 1`` models.
    val_loss : validation RMSE per model count (empty without validation data).
    criterion : values of the selection criterion per model count (validation RMSE or AICc).
    criterion_name : ``"val_rmse"`` or ``"aicc"``.
    nit : number of split iterations performed.
    success : True when a model was fitted (False only for degenerate data).
    message : why the growth stopped.
    train_rmse, val_rmse : errors of the kept model (val_rmse NaN without validation data).
    """

    n_models: int
    loss: np.ndarray
    val_loss: np.ndarray
    criterion: np.ndarray
    criterion_name: str
    nit: int
    success: bool
    message: str
    train_rmse: float
    val_rmse: float
    splits: tuple[tuple[int, int], ...] = field(default=())


def _as_2d(X: ArrayLike, n_inputs: int | None = None) -> FloatArray:
    A: FloatArray = np.asarray(X, dtype=float)
    if A.ndim == 1:
        A = A[:, None] if n_inputs in (None, 1) else A[None, :]
    if A.ndim != 2:
        raise ValueError(f"X must be 2-D (samples, inputs), got shape {A.shape}")
    if n_inputs is not None and A.shape[1] != n_inputs:
        raise ValueError(f"X has {A.shape[1]} inputs, the model has {n_inputs}")
    return A


def _shifted(grid: BoolArray, fill: bool) -> list[BoolArray]:
    """The grid shifted by one bin along every axis and both directions (edges filled)."""
    out = []
    for ax in range(grid.ndim):
        for step in (1, -1):
            g = np.roll(grid, step, axis=ax)
            edge: list[int | slice] = [slice(None)] * grid.ndim
            edge[ax] = 0 if step == 1 else -1
            g[tuple(edge)] = fill
            out.append(g)
    return out


def _closing(grid: BoolArray) -> BoolArray:
    """Morphological closing (dilate, then erode) with the axis neighbours: fills one-bin
    holes between the sweeps of an identification cycle without growing its outline."""
    dil = grid | np.logical_or.reduce(_shifted(grid, False))
    closed: BoolArray = dil & np.logical_and.reduce(_shifted(dil, True)) | grid
    return closed


class _Fitted(NamedTuple):
    """The fitted state, in scaled coordinates ``z = (x - x_min) / x_scale``."""

    x_min: FloatArray
    x_scale: FloatArray
    lo: FloatArray        # (M, p) cell lower bounds
    hi: FloatArray        # (M, p) cell upper bounds
    theta: FloatArray     # (M, p + 1) [intercept, slopes] in z
    coverage: BoolArray
    # the identified region's box in z (None: the training box [0, 1]); the coverage grid
    # spans it (see Lolimot.set_region)
    region_lo: FloatArray | None = None
    region_hi: FloatArray | None = None


def _log_mu(Z: FloatArray, lo: FloatArray, hi: FloatArray, k_sigma: float) -> FloatArray:
    """Unnormalised log validity of every cell, (N, M): -1/2 sum_d ((z_d - c_d) / sigma_d)^2.
    Each column depends on its own cell only (a split recomputes two columns)."""
    scale = np.sqrt(0.5) / (k_sigma * (hi - lo))   # 1 / (sqrt(2) sigma)
    shift = 0.5 * (lo + hi) * scale
    out: FloatArray = np.zeros((Z.shape[0], lo.shape[0]))
    for d in range(Z.shape[1]):   # a few inputs: one (N, M) pass each, no 3-D temporary
        u = np.multiply.outer(Z[:, d], scale[:, d])
        u -= shift[:, d]
        u *= u
        out -= u
    return out


def _normalised(logmu: FloatArray) -> FloatArray:
    """Phi (N, M) from the log validities; subtracting the row maximum keeps far points finite."""
    logmu = logmu - logmu.max(axis=-1, keepdims=True)
    mu = np.exp(logmu)
    phi: FloatArray = mu / mu.sum(axis=-1, keepdims=True)
    return phi


def _bin_index(Z: FloatArray, bins: int) -> NDArray[np.int64]:
    """Row-major index of each sample's bin on a ``bins**p`` grid over the unit box (one
    input at a time: reductions and casts along rows of (N, p) are slow)."""
    flat = np.zeros(Z.shape[0], dtype=np.int64)
    for d in range(Z.shape[1]):
        flat = flat * bins + np.clip((Z[:, d] * bins).astype(np.int64), 0, bins - 1)
    return flat


def _normalised_fit(logmu: FloatArray) -> FloatArray:
    """:func:`_normalised` for the training samples, with fewer passes: a sample inside the
    training box lies within ~1.4 sigma per input of its own cell's centre, so the largest
    validity does not underflow and the row maximum need not be subtracted (if a row's sum
    is ever that small, :func:`_normalised` is used); the row sums as a matrix-vector product."""
    mu = np.exp(logmu)
    s = mu @ np.ones(mu.shape[-1])
    if not np.all(s > 1e-200):
        return _normalised(logmu)
    phi: FloatArray = mu / s[..., None]
    return phi


class Lolimot:
    """Local linear model tree (LOLIMOT) regressor for static maps ``R^p -> R``.

    Parameters
    ----------
    max_models : upper bound on the number of local models.
    k_sigma : width of the validity functions relative to the cell extent (Nelles: 1/3..0.4).
    ridge : ridge factor on the local slopes, relative to the local sum of weights, in scaled
        input units (keeps almost-empty cells well posed; 0 gives plain weighted LS).
    min_samples_per_model : a split is admitted only if both halves contain at least this many
        training samples (counted inside the hyper-rectangles).
    patience : growth stops when the criterion has not improved for this many splits.
    coverage_bins : bins per input of the coverage grid used by :meth:`in_region`.
    coverage_min_count : training samples a coverage bin needs to count as identified.
    coverage_inputs : the coverage grid spans the first this many inputs (0: all); with many
        inputs a full grid is too sparse (or too large) to tell, while the leading ones (e.g.
        an engine's operating point) still bound where the model was identified.
    compress_bins : 0 fits on the samples themselves; ``B > 0`` first pools the samples into
        a ``B**p`` grid over the scaled input box (bin means of x and y, weighted by counts).
        Quasi-stationary identification data repeat the same operating points many times, so
        this shrinks the problem by one or two orders of magnitude at a negligible loss (the
        within-bin spread of x is 1/B of the range).
    """

    # Candidate splits reuse the log validity of the cells they do not touch and the regressor
    # products of the data (same numbers); False: the reference that recomputes everything.
    _fast_splits = True

    def __init__(self, *, max_models: int = 20, k_sigma: float = 0.35, ridge: float = 1e-6,
                 min_samples_per_model: int = 10, patience: int = 4, coverage_bins: int = 16,
                 coverage_min_count: int = 1, compress_bins: int = 0,
                 coverage_inputs: int = 0) -> None:
        if int(max_models) < 1:
            raise ValueError("max_models must be >= 1")
        if not 0.05 <= float(k_sigma) <= 2.0:
            raise ValueError("k_sigma must be within [0.05, 2]")
        if float(ridge) < 0:
            raise ValueError("ridge must be >= 0")
        if int(min_samples_per_model) < 1:
            raise ValueError("min_samples_per_model must be >= 1")
        if int(patience) < 1:
            raise ValueError("patience must be >= 1")
        if int(coverage_bins) < 1 or int(coverage_min_count) < 1:
            raise ValueError("coverage_bins and coverage_min_count must be >= 1")
        if int(compress_bins) < 0:
            raise ValueError("compress_bins must be >= 0")
        if int(coverage_inputs) < 0:
            raise ValueError("coverage_inputs must be >= 0")
        self.compress_bins = int(compress_bins)
        self.coverage_inputs = int(coverage_inputs)
        self.max_models = int(max_models)
        self.k_sigma = float(k_sigma)
        self.ridge = float(ridge)
        self.min_samples_per_model = int(min_samples_per_model)
        self.patience = int(patience)
        self.coverage_bins = int(coverage_bins)
        self.coverage_min_count = int(coverage_min_count)
        self._state: _Fitted | None = None
        self.input_names: tuple[str, ...] = ()
        self.output_name: str = "y"

    # ------------------------------------------------------------------ fitting
    def fit(self, X: ArrayLike, y: ArrayLike, *, X_val: ArrayLike | None = None,
            y_val: ArrayLike | None = None, progress: bool = False,
            input_names: tuple[str, ...] | None = None, output_name: str = "y") -> LolimotResult:
        """Grow the tree on ``(X, y)``; choose the model count by validation RMSE or AICc.

        Parameters
        ----------
        X : (N, p) inputs; y : (N,) outputs. Rows with a non-finite value are rejected.
        X_val, y_val : optional validation data for the choice of the number of models.
        progress : show a tqdm bar over the splits.
        """
        Xa = _as_2d(X)
        ya: FloatArray = np.asarray(y, dtype=float).ravel()
        if ya.shape[0] != Xa.shape[0]:
            raise ValueError(f"X has {Xa.shape[0]} rows but y has {ya.shape[0]}")
        if not (np.all(np.isfinite(Xa)) and np.all(np.isfinite(ya))):
            raise ValueError("X and y must be finite (drop NaN/inf rows first)")
        n, p = Xa.shape
        if n < p + 1:
            raise ValueError(f"need at least {p + 1} samples for {p} inputs, got {n}")
        val: tuple[FloatArray, FloatArray] | None = None
        if X_val is not None and y_val is not None:
            Xv = _as_2d(X_val, p)
            yv: FloatArray = np.asarray(y_val, dtype=float).ravel()
            if yv.shape[0] != Xv.shape[0] or not (
                    np.all(np.isfinite(Xv)) and np.all(np.isfinite(yv))):
                raise ValueError("X_val and y_val must be finite and of matching length")
            val = (Xv, yv)
        self.input_names = tuple(input_names) if input_names else tuple(
            f"x{d}" for d in range(p))
        if len(self.input_names) != p:
            raise ValueError("one input name per input column is required")
        self.output_name = output_name

        Xt = np.ascontiguousarray(Xa.T)   # reductions along rows of (N, p) are slow
        x_min = Xt.min(axis=1)
        x_scale = Xt.max(axis=1) - x_min
        x_scale[x_scale <= 0] = 1.0
        Z = ((Xt - x_min[:, None]) / x_scale[:, None]).T   # columns contiguous
        coverage = self._coverage_grid(Z)
        w: FloatArray = np.ones(n)
        if self.compress_bins:
            Z, ya, w = self._pool(Z, ya)
        vdata: tuple[FloatArray, FloatArray, FloatArray] | None = None
        if val is not None:
            Zv = ((val[0].T - x_min[:, None]) / x_scale[:, None]).T
            vdata = self._pool(Zv, val[1]) if self.compress_bins else \
                (Zv, val[1], np.ones(Zv.shape[0]))
        stats = self._stats(Z, ya)

        def rmse(e: FloatArray, wt: FloatArray) -> float:
            return float(np.sqrt(np.sum(wt * e ** 2) / np.sum(wt)))

        Lv: FloatArray | None = None   # the validation samples' log validities

        def val_rmse(lo: FloatArray, hi: FloatArray, theta: FloatArray,
                     worst: int | None = None) -> float:
            """Validation RMSE; after a split of cell ``worst`` (fast path) only the two new
            cells' log validities are computed."""
            nonlocal Lv
            assert vdata is not None
            Zq, yq, wq = vdata
            if worst is None or Lv is None or not self._fast_splits:
                Lv = _log_mu(Zq, lo, hi, self.k_sigma)
            else:
                Lv = np.concatenate([np.delete(Lv, worst, axis=1),
                                     _log_mu(Zq, lo[-2:], hi[-2:], self.k_sigma)], axis=1)
            return rmse(yq - self._blend(Zq, _normalised(Lv), theta), wq)

        lo: FloatArray = np.zeros((1, p))
        hi: FloatArray = np.ones((1, p))
        L = _log_mu(Z, lo, hi, self.k_sigma)
        phi = _normalised_fit(L)
        theta = self._solve(stats, w, phi)
        err = ya - self._blend(Z, phi, theta)
        snapshots = [(lo, hi, theta)]
        loss = [rmse(err, w)]
        val_loss: list[float] = []
        if vdata is not None:
            val_loss.append(val_rmse(lo, hi, theta))
        crit = [val_loss[-1] if vdata is not None else self._aicc(err, w, 1, p)]
        splits: list[tuple[int, int]] = []
        frozen = np.zeros(1, dtype=bool)  # cells that cannot be split further
        message = f"reached max_models={self.max_models}"
        bar = None
        if progress:
            from tqdm import tqdm
            bar = tqdm(total=self.max_models - 1, desc=f"LOLIMOT {output_name}", leave=False)
        nit = 0
        vanished = 1e-12 * (1.0 + float(np.abs(ya).max()))
        while lo.shape[0] < self.max_models:
            local_loss = phi.T @ (w * err ** 2)
            local_loss[frozen] = -np.inf
            if not np.isfinite(local_loss).any():
                message = "no cell can be split (min_samples_per_model)"
                break
            worst = int(np.argmax(local_loss))
            keep = np.arange(lo.shape[0]) != worst
            w_in = w.copy()   # the sample weights inside the cell, zero outside
            for d in range(p):   # per input: reductions along rows of (N, p) are slow
                w_in[(Z[:, d] < lo[worst, d]) | (Z[:, d] > hi[worst, d])] = 0.0
            cands = [(d, c) for d in range(p)
                     if (c := self._split(Z, w_in, lo, hi, worst, d)) is not None]
            best: tuple[int, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray,
                        FloatArray] | None = None
            if cands:
                # every admissible split of the cell evaluated in one batch (K, N, M)
                if self._fast_splits:   # two new columns each; the others as they were
                    c_L = np.empty((len(cands), Z.shape[0], lo.shape[0] + 1))
                    c_L[:, :, :-2] = L[:, keep]
                    new = _log_mu(Z, np.vstack([c[0][-2:] for _, c in cands]),
                                  np.vstack([c[1][-2:] for _, c in cands]), self.k_sigma)
                    c_L[:, :, -2:] = new.reshape(Z.shape[0], len(cands), 2).transpose(1, 0, 2)
                else:
                    c_L = np.stack([_log_mu(Z, c_lo, c_hi, self.k_sigma)
                                    for _, (c_lo, c_hi) in cands])
                c_phi = _normalised_fit(c_L)
                c_theta = self._solve(stats, w, c_phi)
                c_err = ya - self._blend(Z, c_phi, c_theta)
                j = int(np.argmin(c_err ** 2 @ w))
                d, (c_lo, c_hi) = cands[j]
                best = (d, c_lo, c_hi, c_theta[j], c_phi[j], c_err[j], c_L[j])
            if best is None:
                frozen[worst] = True
                continue
            nit += 1
            d, lo, hi, theta, phi, err, L = best
            frozen = np.append(np.delete(frozen, worst), [False, False])
            splits.append((worst, d))
            snapshots.append((lo, hi, theta))
            loss.append(rmse(err, w))
            if vdata is not None:
                val_loss.append(val_rmse(lo, hi, theta, worst))
            crit.append(val_loss[-1] if vdata is not None else
                        self._aicc(err, w, lo.shape[0], p))
            if bar is not None:
                bar.update(1)
            if len(crit) - 1 - int(np.argmin(crit)) >= self.patience:
                message = f"criterion did not improve for {self.patience} splits"
                break
            if loss[-1] <= vanished:
                message = "training error vanished"
                break
        if bar is not None:
            bar.close()
        k = int(np.argmin(crit))
        self._state = _Fitted(x_min, x_scale, *snapshots[k], coverage)
        return LolimotResult(
            n_models=k + 1, loss=np.asarray(loss), val_loss=np.asarray(val_loss),
            criterion=np.asarray(crit), criterion_name="val_rmse" if vdata is not None
            else "aicc", nit=nit, success=True, message=message, train_rmse=loss[k],
            val_rmse=val_loss[k] if vdata is not None else float("nan"),
            splits=tuple(splits[:k]))

    def _pool(self, Z: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Bin means of (Z, y) on a compress_bins**p grid, weighted by the sample counts."""
        B = self.compress_bins
        flat = _bin_index(Z, B)
        # the occupied bins in ascending order (np.unique's, by counting: no sort)
        counts = np.bincount(flat, minlength=B ** Z.shape[1]) if B ** Z.shape[1] <= 4 * \
            flat.size + 65536 else None
        if counts is None:
            _, inv = np.unique(flat, return_inverse=True)
        else:
            inv = (np.cumsum(counts > 0) - 1)[flat]
        w = np.bincount(inv).astype(float)
        Zp = np.column_stack([np.bincount(inv, weights=Z[:, d]) for d in range(Z.shape[1])])
        return Zp / w[:, None], np.bincount(inv, weights=y) / w, w

    def _split(self, Z: FloatArray, w_in: FloatArray, lo: FloatArray, hi: FloatArray, i: int,
               d: int) -> tuple[FloatArray, FloatArray] | None:
        """Halve cell ``i`` along input ``d``; None if a half holds too few samples. The two
        halves come last (the other cells keep their order); ``w_in``: the sample weights in
        cell ``i``, zero outside."""
        mid = 0.5 * (lo[i, d] + hi[i, d])
        n_left = float(w_in @ (Z[:, d] < mid))
        if min(n_left, float(w_in.sum()) - n_left) < self.min_samples_per_model:
            return None
        lo_a, hi_a = lo[i].copy(), hi[i].copy()
        hi_a[d] = mid
        lo_b, hi_b = lo[i].copy(), hi[i].copy()
        lo_b[d] = mid
        keep = np.arange(lo.shape[0]) != i
        return (np.vstack([lo[keep], lo_a, lo_b]), np.vstack([hi[keep], hi_a, hi_b]))

    def _validity(self, Z: FloatArray, lo: FloatArray, hi: FloatArray) -> FloatArray:
        """Normalised validity functions Phi (N, M); log-sum-exp keeps far points finite."""
        return _normalised(_log_mu(Z, lo, hi, self.k_sigma))

    @staticmethod
    def _stats(Z: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Regressor products of the data, the same for every tree: the outer products of
        ``a = [1, z]`` flattened (N, q*q) and ``a y`` (N, q)."""
        A = np.hstack([np.ones((Z.shape[0], 1)), Z])
        q = A.shape[1]
        # Outer products once, then one matrix product for all cells (BLAS, not einsum loops).
        AA = (A[:, :, None] * A[:, None, :]).reshape(A.shape[0], q * q)
        return AA, A * y[:, None]

    def _solve(self, stats: tuple[FloatArray, FloatArray], w: FloatArray,
               phi: FloatArray) -> FloatArray:
        """Local weighted least squares for all cells at once (ridge on the slopes); ``w`` are
        sample weights (counts of pooled samples)."""
        AA, Ay = stats
        q = Ay.shape[1]
        pw = phi * w[:, None]
        pwT = np.swapaxes(pw, -1, -2)
        G = (pwT @ AA).reshape(*pwT.shape[:-1], q, q)
        b = pwT @ Ay
        reg = np.eye(q)
        reg[0, 0] = 0.0
        wsum = pw.sum(axis=-2)
        # A tiny absolute term keeps cells with no weight at all solvable.
        G = G + (self.ridge * wsum[..., None, None] + 1e-12) * reg
        G[..., 0, 0] += 1e-12
        theta: FloatArray = np.linalg.solve(G, b[..., None])[..., 0]
        return theta

    @staticmethod
    def _blend(Z: FloatArray, phi: FloatArray, theta: FloatArray) -> FloatArray:
        # sum_m phi_m (theta_m0 + z . theta_m1:) as phi @ theta, then one input at a time
        pt = phi @ theta
        out: FloatArray = pt[..., 0]
        for d in range(Z.shape[1]):
            out = out + Z[:, d] * pt[..., d + 1]
        return out

    @staticmethod
    def _aicc(err: FloatArray, w: FloatArray, m: int, p: int) -> float:
        n = float(np.sum(w))
        k = m * (p + 1)
        sse = max(float(np.sum(w * err ** 2)), 1e-300)
        corr = 2.0 * k * (k + 1) / (n - k - 1) if n - k - 1 > 0 else np.inf
        return float(n * np.log(sse / n) + 2.0 * k + corr)

    def _coverage_grid(self, Z: FloatArray) -> BoolArray:
        p = min(self.coverage_inputs, Z.shape[1]) if self.coverage_inputs else Z.shape[1]
        Z = Z[:, :p]
        bins = self.coverage_bins
        if bins ** p > _MAX_GRID_CELLS:
            return np.ones((1,) * p, dtype=bool)
        counts = np.bincount(_bin_index(Z, bins), minlength=bins ** p).reshape((bins,) * p)
        return _closing(counts >= self.coverage_min_count)

    # ------------------------------------------------------------------ using
    def _fitted(self) -> _Fitted:
        if self._state is None:
            raise RuntimeError("model is not fitted: call fit() or load() first")
        return self._state

    def _scaled(self, X: ArrayLike) -> FloatArray:
        st = self._fitted()
        Xa = _as_2d(X, st.x_min.shape[0])
        Z: FloatArray = (Xa - st.x_min) / st.x_scale
        return Z

    def predict(self, X: ArrayLike) -> FloatArray:
        """Model output for (N, p) inputs; NaN rows give NaN. Extrapolates the outer models."""
        st = self._fitted()
        Z = self._scaled(X)
        ok = np.all(np.isfinite(Z), axis=1)
        out = np.full(Z.shape[0], np.nan)
        if ok.any():
            Zk = Z[ok]
            out[ok] = self._blend(Zk, self._validity(Zk, st.lo, st.hi), st.theta)
        return out

    def validity(self, X: ArrayLike) -> FloatArray:
        """Normalised validity functions Phi_i(x), shape (N, M); rows sum to one."""
        st = self._fitted()
        return self._validity(self._scaled(X), st.lo, st.hi)

    def set_region(self, X: ArrayLike) -> None:
        """The identified region from all of the identification data ``X`` (training,
        validation and test rows: the model was fitted on some and scored on the others): its
        bounding box joined with the training box, and the coverage grid over that box from
        every row. Without it the region is the training data's."""
        st = self._fitted()
        Z = self._scaled(X)
        Z = Z[np.all(np.isfinite(Z), axis=1)]
        if Z.shape[0] == 0:
            raise ValueError("set_region needs finite rows")
        lo = np.minimum(Z.min(axis=0), 0.0)
        hi = np.maximum(Z.max(axis=0), 1.0)
        self._state = st._replace(coverage=self._coverage_grid((Z - lo) / (hi - lo)),
                                  region_lo=lo, region_hi=hi)

    def in_region(self, X: ArrayLike) -> BoolArray:
        """True where x lies inside the identification data's bounding box and in a coverage
        bin that held identification data (the identified region; :meth:`set_region`)."""
        st = self._fitted()
        Z = self._scaled(X)
        if st.region_lo is not None and st.region_hi is not None:
            Z = (Z - st.region_lo) / (st.region_hi - st.region_lo)
        ok: BoolArray = np.all(np.isfinite(Z), axis=1) & np.all((Z >= 0.0) & (Z <= 1.0), axis=1)
        grid = st.coverage
        bins = grid.shape[0]
        if grid.size == 1:
            return ok
        idx = np.clip((np.nan_to_num(Z[:, :grid.ndim]) * bins).astype(int), 0, bins - 1)
        inside: BoolArray = ok & grid[tuple(idx.T)]
        return inside

    # ------------------------------------------------------------------ inspection
    @property
    def n_models(self) -> int:
        return int(self._fitted().theta.shape[0])

    @property
    def centres(self) -> FloatArray:
        """Cell centres in input units, shape (M, p)."""
        st = self._fitted()
        return st.x_min + 0.5 * (st.lo + st.hi) * st.x_scale

    @property
    def cell_bounds(self) -> tuple[FloatArray, FloatArray]:
        """Lower and upper cell bounds in input units, each (M, p)."""
        st = self._fitted()
        return (st.x_min + st.lo * st.x_scale, st.x_min + st.hi * st.x_scale)

    @property
    def sigmas(self) -> FloatArray:
        """Widths of the Gaussian validity functions in input units, (M, p)."""
        st = self._fitted()
        sig: FloatArray = self.k_sigma * (st.hi - st.lo) * st.x_scale
        return sig

    @property
    def coverage(self) -> BoolArray:
        """Boolean coverage grid (coverage_bins per input) over the identified region's box
        (the training data's, or all identification data's after :meth:`set_region`)."""
        return self._fitted().coverage.copy()

    @property
    def input_range(self) -> tuple[FloatArray, FloatArray]:
        """Bounding box of the training inputs (min, max)."""
        st = self._fitted()
        return st.x_min.copy(), st.x_min + st.x_scale

    def local_parameters(self) -> tuple[FloatArray, FloatArray]:
        """Local models as ``y_i = offset_i + slopes_i . (x - centre_i)`` in input units.

        Returns
        -------
        offset : (M,) value of each local model at its centre.
        slopes : (M, p) partial derivatives in output units per input unit.
        """
        st = self._fitted()
        zc = 0.5 * (st.lo + st.hi)
        offset: FloatArray = st.theta[:, 0] + np.einsum("mj,mj->m", st.theta[:, 1:], zc)
        return offset, st.theta[:, 1:] / st.x_scale

    # ------------------------------------------------------------------ persistence
    def to_arrays(self) -> dict[str, NDArray[Any]]:
        """All state as arrays (for npz); inverse of :meth:`from_arrays`."""
        st = self._fitted()
        meta = {"max_models": self.max_models, "k_sigma": self.k_sigma, "ridge": self.ridge,
                "min_samples_per_model": self.min_samples_per_model,
                "patience": self.patience, "coverage_bins": self.coverage_bins,
                "coverage_min_count": self.coverage_min_count,
                "compress_bins": self.compress_bins, "coverage_inputs": self.coverage_inputs,
                "input_names": list(self.input_names), "output_name": self.output_name}
        region = {} if st.region_lo is None or st.region_hi is None else {
            "region_lo": st.region_lo, "region_hi": st.region_hi}
        return {"x_min": st.x_min, "x_scale": st.x_scale, "lo": st.lo, "hi": st.hi,
                "theta": st.theta, "coverage": st.coverage, **region,
                "meta": np.array(json.dumps(meta))}

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, Any]) -> Lolimot:
        try:
            meta = json.loads(str(arrays["meta"]))
            names = meta.pop("input_names")
            out_name = meta.pop("output_name")
            model = cls(**meta)
            st = _Fitted(x_min=np.asarray(arrays["x_min"], dtype=float),
                         x_scale=np.asarray(arrays["x_scale"], dtype=float),
                         lo=np.asarray(arrays["lo"], dtype=float),
                         hi=np.asarray(arrays["hi"], dtype=float),
                         theta=np.asarray(arrays["theta"], dtype=float),
                         coverage=np.asarray(arrays["coverage"], dtype=bool),
                         region_lo=(np.asarray(arrays["region_lo"], dtype=float)
                                    if "region_lo" in arrays else None),
                         region_hi=(np.asarray(arrays["region_hi"], dtype=float)
                                    if "region_hi" in arrays else None))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"not a LOLIMOT model file: {exc}") from exc
        p = st.x_min.shape[0]
        if st.lo.shape != st.hi.shape or st.lo.shape[1] != p or \
                st.theta.shape != (st.lo.shape[0], p + 1):
            raise ValueError("inconsistent LOLIMOT model arrays")
        model._state = st
        model.input_names = tuple(names)
        model.output_name = out_name
        return model

    def save(self, path: str | Path) -> Path:
        """Write the model to an ``.npz`` file (no pickles)."""
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_suffix(".npz")
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays: dict[str, Any] = self.to_arrays()
        np.savez_compressed(path, allow_pickle=False, **arrays)
        return path

    @classmethod
    def load(cls, path: str | Path) -> Lolimot:
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"no LOLIMOT model at {path}")
        with np.load(path, allow_pickle=False) as data:
            return cls.from_arrays({k: data[k] for k in data.files})


class LolimotStack:
    """Several fitted LOLIMOT maps of the same inputs evaluated in one pass: the cells of
    all maps side by side, each map's validity functions normalised over its own cells.

    Equal to calling :meth:`Lolimot.predict` map by map (to rounding: the blend is summed as
    ``sum(mu y) / sum(mu)`` instead of ``sum((mu / sum(mu)) y)``), with a fixed number of
    array operations instead of one set per map: a bank model that needs its five effect
    maps at one operating point per segment pays the array overhead once.
    """

    def __init__(self, models: Sequence[Lolimot]) -> None:
        states = [m._fitted() for m in models]
        if not states:
            raise ValueError("a stack needs at least one fitted map")
        p = states[0].x_min.shape[0]
        if any(st.x_min.shape[0] != p for st in states):
            raise ValueError("the maps of a stack must take the same number of inputs")
        counts = [st.lo.shape[0] for st in states]
        self.n_inputs = p
        self._starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.intp)
        self._map = np.repeat(np.arange(len(states)), counts)
        self._x_min = np.stack([st.x_min for st in states])
        self._x_scale = np.stack([st.x_scale for st in states])
        lo = np.vstack([st.lo for st in states])
        hi = np.vstack([st.hi for st in states])
        k_sigma = np.repeat([m.k_sigma for m in models], counts)[:, None]
        self._centre = 0.5 * (lo + hi)
        self._sigma = k_sigma * (hi - lo)
        theta = np.vstack([st.theta for st in states])
        self._theta0, self._theta1 = theta[:, 0], theta[:, 1:]

    def predict(self, X: ArrayLike) -> FloatArray:
        """Outputs of every map for (N, p) inputs, shape (N, maps); NaN rows give NaN."""
        A = _as_2d(X, self.n_inputs)
        with np.errstate(invalid="ignore", over="ignore"):
            Z = ((A[:, None, :] - self._x_min[None]) / self._x_scale[None])[:, self._map, :]
            L = -0.5 * (((Z - self._centre[None]) / self._sigma[None]) ** 2).sum(axis=2)
            mu = np.exp(L - np.maximum.reduceat(L, self._starts, axis=1)[:, self._map])
            local = self._theta0[None] + (Z * self._theta1[None]).sum(axis=2)
            out: FloatArray = (np.add.reduceat(mu * local, self._starts, axis=1)
                               / np.add.reduceat(mu, self._starts, axis=1))
        out[~np.all(np.isfinite(A), axis=1)] = np.nan
        return out

