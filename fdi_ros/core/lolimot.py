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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["Lolimot", "LolimotResult"]

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


def _as_2d(X, n_inputs: int | None = None) -> np.ndarray:
    X = np.asarray(X, dtype=float)
    if X.ndim == 1:
        X = X[:, None] if n_inputs in (None, 1) else X[None, :]
    if X.ndim != 2:
        raise ValueError(f"X must be 2-D (samples, inputs), got shape {X.shape}")
    if n_inputs is not None and X.shape[1] != n_inputs:
        raise ValueError(f"X has {X.shape[1]} inputs, the model has {n_inputs}")
    return X


def _shifted(grid: np.ndarray, fill: bool) -> list[np.ndarray]:
    """The grid shifted by one bin along every axis and both directions (edges filled)."""
    out = []
    for ax in range(grid.ndim):
        for step in (1, -1):
            g = np.roll(grid, step, axis=ax)
            edge = [slice(None)] * grid.ndim
            edge[ax] = 0 if step == 1 else -1
            g[tuple(edge)] = fill
            out.append(g)
    return out


def _closing(grid: np.ndarray) -> np.ndarray:
    """Morphological closing (dilate, then erode) with the axis neighbours: fills one-bin
    holes between the sweeps of an identification cycle without growing its outline."""
    dil = grid | np.logical_or.reduce(_shifted(grid, False))
    return dil & np.logical_and.reduce(_shifted(dil, True)) | grid


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
    compress_bins : 0 fits on the samples themselves; ``B > 0`` first pools the samples into
        a ``B**p`` grid over the scaled input box (bin means of x and y, weighted by counts).
        Quasi-stationary identification data repeat the same operating points many times, so
        this shrinks the problem by one or two orders of magnitude at a negligible loss (the
        within-bin spread of x is 1/B of the range).
    """

    def __init__(self, *, max_models: int = 20, k_sigma: float = 0.35, ridge: float = 1e-6,
                 min_samples_per_model: int = 10, patience: int = 4, coverage_bins: int = 16,
                 coverage_min_count: int = 1, compress_bins: int = 0) -> None:
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
        self.compress_bins = int(compress_bins)
        self.max_models = int(max_models)
        self.k_sigma = float(k_sigma)
        self.ridge = float(ridge)
        self.min_samples_per_model = int(min_samples_per_model)
        self.patience = int(patience)
        self.coverage_bins = int(coverage_bins)
        self.coverage_min_count = int(coverage_min_count)
        # Fitted state (scaled coordinates z = (x - x_min) / x_scale).
        self._x_min: np.ndarray | None = None
        self._x_scale: np.ndarray | None = None
        self._lo: np.ndarray | None = None      # (M, p) cell lower bounds, scaled
        self._hi: np.ndarray | None = None      # (M, p) cell upper bounds, scaled
        self._theta: np.ndarray | None = None   # (M, p + 1) [intercept, slopes] in z
        self._coverage: np.ndarray | None = None
        self.input_names: tuple[str, ...] = ()
        self.output_name: str = "y"

    # ------------------------------------------------------------------ fitting
    def fit(self, X, y, *, X_val=None, y_val=None, progress: bool = False,
            input_names: tuple[str, ...] | None = None, output_name: str = "y") -> LolimotResult:
        """Grow the tree on ``(X, y)``; choose the model count by validation RMSE or AICc.

        Parameters
        ----------
        X : (N, p) inputs; y : (N,) outputs. Rows with a non-finite value are rejected.
        X_val, y_val : optional validation data for the choice of the number of models.
        progress : show a tqdm bar over the splits.
        """
        X = _as_2d(X)
        y = np.asarray(y, dtype=float).ravel()
        if y.shape[0] != X.shape[0]:
            raise ValueError(f"X has {X.shape[0]} rows but y has {y.shape[0]}")
        if not (np.all(np.isfinite(X)) and np.all(np.isfinite(y))):
            raise ValueError("X and y must be finite (drop NaN/inf rows first)")
        n, p = X.shape
        if n < p + 1:
            raise ValueError(f"need at least {p + 1} samples for {p} inputs, got {n}")
        have_val = X_val is not None and y_val is not None
        if have_val:
            X_val = _as_2d(X_val, p)
            y_val = np.asarray(y_val, dtype=float).ravel()
            if y_val.shape[0] != X_val.shape[0] or not (
                    np.all(np.isfinite(X_val)) and np.all(np.isfinite(y_val))):
                raise ValueError("X_val and y_val must be finite and of matching length")
        self.input_names = tuple(input_names) if input_names else tuple(
            f"x{d}" for d in range(p))
        if len(self.input_names) != p:
            raise ValueError("one input name per input column is required")
        self.output_name = output_name

        x_min = X.min(axis=0)
        x_scale = X.max(axis=0) - x_min
        x_scale[x_scale <= 0] = 1.0
        self._x_min, self._x_scale = x_min, x_scale
        Z = (X - x_min) / x_scale
        Zv = (X_val - x_min) / x_scale if have_val else None
        self._coverage = self._coverage_grid(Z)
        w = np.ones(n)
        wv = np.ones(Zv.shape[0]) if have_val else None
        if self.compress_bins:
            Z, y, w = self._pool(Z, y)
            if have_val:
                Zv, y_val, wv = self._pool(Zv, y_val)

        def rmse(e, wt):
            return float(np.sqrt(np.sum(wt * e ** 2) / np.sum(wt)))

        lo = np.zeros((1, p))
        hi = np.ones((1, p))
        theta, phi = self._estimate(Z, y, w, lo, hi)
        err = y - self._blend(Z, phi, theta)
        snapshots = [(lo, hi, theta)]
        loss = [rmse(err, w)]
        val_loss: list[float] = []
        if have_val:
            val_loss.append(rmse(y_val - self._blend(Zv, self._validity(Zv, lo, hi), theta), wv))
        crit = [val_loss[-1] if have_val else self._aicc(err, w, 1, p)]
        splits: list[tuple[int, int]] = []
        frozen = np.zeros(1, dtype=bool)  # cells that cannot be split further
        message = f"reached max_models={self.max_models}"
        bar = None
        if progress:
            from tqdm import tqdm
            bar = tqdm(total=self.max_models - 1, desc=f"LOLIMOT {output_name}", leave=False)
        nit = 0
        while lo.shape[0] < self.max_models:
            local_loss = phi.T @ (w * err ** 2)
            local_loss[frozen] = -np.inf
            if not np.isfinite(local_loss).any():
                message = "no cell can be split (min_samples_per_model)"
                break
            worst = int(np.argmax(local_loss))
            best = None
            for d in range(p):
                cand = self._split(Z, w, lo, hi, worst, d)
                if cand is None:
                    continue
                c_lo, c_hi = cand
                c_theta, c_phi = self._estimate(Z, y, w, c_lo, c_hi)
                c_err = y - self._blend(Z, c_phi, c_theta)
                sse = float(np.sum(w * c_err ** 2))
                if best is None or sse < best[0]:
                    best = (sse, d, c_lo, c_hi, c_theta, c_phi, c_err)
            if best is None:
                frozen[worst] = True
                continue
            nit += 1
            _, d, lo, hi, theta, phi, err = best
            frozen = np.append(np.delete(frozen, worst), [False, False])
            splits.append((worst, d))
            snapshots.append((lo, hi, theta))
            loss.append(rmse(err, w))
            if have_val:
                val_loss.append(rmse(y_val - self._blend(Zv, self._validity(Zv, lo, hi), theta),
                                     wv))
            crit.append(val_loss[-1] if have_val else self._aicc(err, w, lo.shape[0], p))
            if bar is not None:
                bar.update(1)
            if len(crit) - 1 - int(np.argmin(crit)) >= self.patience:
                message = f"criterion did not improve for {self.patience} splits"
                break
            if loss[-1] <= 1e-12 * (1.0 + float(np.abs(y).max())):
                message = "training error vanished"
                break
        if bar is not None:
            bar.close()
        k = int(np.argmin(crit))
        self._lo, self._hi, self._theta = snapshots[k]
        return LolimotResult(
            n_models=k + 1, loss=np.asarray(loss), val_loss=np.asarray(val_loss),
            criterion=np.asarray(crit), criterion_name="val_rmse" if have_val else "aicc",
            nit=nit, success=True, message=message, train_rmse=loss[k],
            val_rmse=val_loss[k] if have_val else float("nan"), splits=tuple(splits[:k]))

    def _pool(self, Z, y):
        """Bin means of (Z, y) on a compress_bins**p grid, weighted by the sample counts."""
        B = self.compress_bins
        idx = np.clip((Z * B).astype(np.int64), 0, B - 1)
        flat = np.ravel_multi_index(tuple(idx.T), (B,) * Z.shape[1])
        uniq, inv = np.unique(flat, return_inverse=True)
        w = np.bincount(inv).astype(float)
        Zp = np.column_stack([np.bincount(inv, weights=Z[:, d]) for d in range(Z.shape[1])])
        return Zp / w[:, None], np.bincount(inv, weights=y) / w, w

    def _split(self, Z, w, lo, hi, i, d):
        """Halve cell ``i`` along input ``d``; None if a half holds too few samples."""
        mid = 0.5 * (lo[i, d] + hi[i, d])
        inside = np.all((lo[i] <= Z) & (hi[i] >= Z), axis=1)
        n_left = float(np.sum(w[inside & (Z[:, d] < mid)]))
        if min(n_left, float(np.sum(w[inside])) - n_left) < self.min_samples_per_model:
            return None
        lo_a, hi_a = lo[i].copy(), hi[i].copy()
        hi_a[d] = mid
        lo_b, hi_b = lo[i].copy(), hi[i].copy()
        lo_b[d] = mid
        keep = np.arange(lo.shape[0]) != i
        return (np.vstack([lo[keep], lo_a, lo_b]), np.vstack([hi[keep], hi_a, hi_b]))

    def _validity(self, Z, lo, hi) -> np.ndarray:
        """Normalised validity functions Phi (N, M); log-sum-exp keeps far points finite."""
        centre = 0.5 * (lo + hi)
        sigma = self.k_sigma * (hi - lo)
        q = ((Z[:, None, :] - centre[None]) / sigma[None]) ** 2
        logmu = -0.5 * q.sum(axis=2)
        logmu -= logmu.max(axis=1, keepdims=True)
        mu = np.exp(logmu)
        return mu / mu.sum(axis=1, keepdims=True)

    def _estimate(self, Z, y, w, lo, hi):
        """Local weighted least squares for all cells at once (ridge on the slopes); ``w`` are
        sample weights (counts of pooled samples)."""
        phi = self._validity(Z, lo, hi)
        A = np.hstack([np.ones((Z.shape[0], 1)), Z])
        q = A.shape[1]
        # Outer products once, then one matrix product for all cells (BLAS, not einsum loops).
        AA = (A[:, :, None] * A[:, None, :]).reshape(A.shape[0], q * q)
        pw = phi * w[:, None]
        G = (pw.T @ AA).reshape(-1, q, q)
        b = pw.T @ (A * y[:, None])
        reg = np.eye(q)
        reg[0, 0] = 0.0
        wsum = pw.sum(axis=0)
        # A tiny absolute term keeps cells with no weight at all solvable.
        G = G + (self.ridge * wsum[:, None, None] + 1e-12) * reg[None]
        G[:, 0, 0] += 1e-12
        theta = np.linalg.solve(G, b[..., None])[..., 0]
        return theta, phi

    @staticmethod
    def _blend(Z, phi, theta) -> np.ndarray:
        local = theta[:, 0][None, :] + Z @ theta[:, 1:].T
        return (phi * local).sum(axis=1)

    @staticmethod
    def _aicc(err, w, m, p) -> float:
        n = float(np.sum(w))
        k = m * (p + 1)
        sse = max(float(np.sum(w * err ** 2)), 1e-300)
        corr = 2.0 * k * (k + 1) / (n - k - 1) if n - k - 1 > 0 else np.inf
        return n * np.log(sse / n) + 2.0 * k + corr

    def _coverage_grid(self, Z) -> np.ndarray:
        p = Z.shape[1]
        bins = self.coverage_bins
        if bins ** p > _MAX_GRID_CELLS:
            return np.ones((1,) * p, dtype=bool)
        idx = np.clip((Z * bins).astype(int), 0, bins - 1)
        counts = np.zeros((bins,) * p, dtype=int)
        np.add.at(counts, tuple(idx.T), 1)
        return _closing(counts >= self.coverage_min_count)

    # ------------------------------------------------------------------ using
    def _require_fitted(self) -> None:
        if self._theta is None:
            raise RuntimeError("model is not fitted: call fit() or load() first")

    def _scaled(self, X) -> np.ndarray:
        self._require_fitted()
        X = _as_2d(X, self._x_min.shape[0])
        return (X - self._x_min) / self._x_scale

    def predict(self, X) -> np.ndarray:
        """Model output for (N, p) inputs; NaN rows give NaN. Extrapolates the outer models."""
        Z = self._scaled(X)
        ok = np.all(np.isfinite(Z), axis=1)
        out = np.full(Z.shape[0], np.nan)
        if ok.any():
            Zk = Z[ok]
            out[ok] = self._blend(Zk, self._validity(Zk, self._lo, self._hi), self._theta)
        return out

    def validity(self, X) -> np.ndarray:
        """Normalised validity functions Phi_i(x), shape (N, M); rows sum to one."""
        Z = self._scaled(X)
        return self._validity(Z, self._lo, self._hi)

    def in_region(self, X) -> np.ndarray:
        """True where x lies inside the training data's bounding box and in a coverage bin
        that held training data (the identified region)."""
        Z = self._scaled(X)
        ok = np.all(np.isfinite(Z), axis=1) & np.all((Z >= 0.0) & (Z <= 1.0), axis=1)
        grid = self._coverage
        bins = grid.shape[0]
        if grid.size == 1:
            return ok
        idx = np.clip((np.nan_to_num(Z) * bins).astype(int), 0, bins - 1)
        return ok & grid[tuple(idx.T)]

    # ------------------------------------------------------------------ inspection
    @property
    def n_models(self) -> int:
        self._require_fitted()
        return int(self._theta.shape[0])

    @property
    def centres(self) -> np.ndarray:
        """Cell centres in input units, shape (M, p)."""
        self._require_fitted()
        return self._x_min + 0.5 * (self._lo + self._hi) * self._x_scale

    @property
    def cell_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper cell bounds in input units, each (M, p)."""
        self._require_fitted()
        return (self._x_min + self._lo * self._x_scale, self._x_min + self._hi * self._x_scale)

    @property
    def sigmas(self) -> np.ndarray:
        """Widths of the Gaussian validity functions in input units, (M, p)."""
        self._require_fitted()
        return self.k_sigma * (self._hi - self._lo) * self._x_scale

    @property
    def coverage(self) -> np.ndarray:
        """Boolean coverage grid (coverage_bins per input) over the training bounding box."""
        self._require_fitted()
        return self._coverage.copy()

    @property
    def input_range(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounding box of the training inputs (min, max)."""
        self._require_fitted()
        return self._x_min.copy(), self._x_min + self._x_scale

    def local_parameters(self) -> tuple[np.ndarray, np.ndarray]:
        """Local models as ``y_i = offset_i + slopes_i . (x - centre_i)`` in input units.

        Returns
        -------
        offset : (M,) value of each local model at its centre.
        slopes : (M, p) partial derivatives in output units per input unit.
        """
        self._require_fitted()
        zc = 0.5 * (self._lo + self._hi)
        offset = self._theta[:, 0] + np.einsum("mj,mj->m", self._theta[:, 1:], zc)
        return offset, self._theta[:, 1:] / self._x_scale

    # ------------------------------------------------------------------ persistence
    def to_arrays(self) -> dict[str, np.ndarray]:
        """All state as arrays (for npz); inverse of :meth:`from_arrays`."""
        self._require_fitted()
        meta = {"max_models": self.max_models, "k_sigma": self.k_sigma, "ridge": self.ridge,
                "min_samples_per_model": self.min_samples_per_model,
                "patience": self.patience, "coverage_bins": self.coverage_bins,
                "coverage_min_count": self.coverage_min_count,
                "compress_bins": self.compress_bins,
                "input_names": list(self.input_names), "output_name": self.output_name}
        return {"x_min": self._x_min, "x_scale": self._x_scale, "lo": self._lo, "hi": self._hi,
                "theta": self._theta, "coverage": self._coverage,
                "meta": np.array(json.dumps(meta))}

    @classmethod
    def from_arrays(cls, arrays) -> Lolimot:
        try:
            meta = json.loads(str(arrays["meta"]))
            names = meta.pop("input_names")
            out_name = meta.pop("output_name")
            model = cls(**meta)
            model._x_min = np.asarray(arrays["x_min"], dtype=float)
            model._x_scale = np.asarray(arrays["x_scale"], dtype=float)
            model._lo = np.asarray(arrays["lo"], dtype=float)
            model._hi = np.asarray(arrays["hi"], dtype=float)
            model._theta = np.asarray(arrays["theta"], dtype=float)
            model._coverage = np.asarray(arrays["coverage"], dtype=bool)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"not a LOLIMOT model file: {exc}") from exc
        p = model._x_min.shape[0]
        if model._lo.shape != model._hi.shape or model._lo.shape[1] != p or \
                model._theta.shape != (model._lo.shape[0], p + 1):
            raise ValueError("inconsistent LOLIMOT model arrays")
        model.input_names = tuple(names)
        model.output_name = out_name
        return model

    def save(self, path) -> Path:
        """Write the model to an ``.npz`` file (no pickles)."""
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_suffix(".npz")
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, **self.to_arrays())
        return path

    @classmethod
    def load(cls, path) -> Lolimot:
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"no LOLIMOT model at {path}")
        with np.load(path, allow_pickle=False) as data:
            return cls.from_arrays({k: data[k] for k in data.files})
