"""ECU look-up tables sampled from an identified model.

A table holds the model's values at the nodes of a user grid (one strictly increasing
breakpoint vector per input) and is evaluated the way an engine ECU evaluates its maps:
multilinear interpolation between the 2**p surrounding nodes (bilinear for two inputs), inputs
clamped to the outermost breakpoints. Each node also carries an "identified" flag (from the
model's coverage of its training data); a query is valid when the interpolated flag is at least
one half and the query lies within the breakpoint range. Outside, the clamped value is still
returned, flagged invalid, so that a caller can say "not valid here" instead of trusting it.
"""

from __future__ import annotations

import bisect
import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = ["LookupTable", "table_error"]


@dataclass(frozen=True)
class LookupTable:
    """A p-dimensional map on a rectilinear grid.

    Attributes
    ----------
    breakpoints : one strictly increasing vector per input, in input units.
    values : table values, shape ``tuple(len(b) for b in breakpoints)``.
    identified : boolean flags of the same shape (True: node inside the identified region).
    input_names, output_name : names for inspection and plots.
    """

    breakpoints: tuple[np.ndarray, ...]
    values: np.ndarray
    identified: np.ndarray
    input_names: tuple[str, ...] = ()
    output_name: str = "y"

    def __post_init__(self) -> None:
        bps = tuple(np.asarray(b, dtype=float) for b in self.breakpoints)
        object.__setattr__(self, "breakpoints", bps)
        shape = tuple(b.size for b in bps)
        for d, b in enumerate(bps):
            if b.ndim != 1 or b.size < 2:
                raise ValueError(f"breakpoints of input {d} need at least two entries")
            if not np.all(np.isfinite(b)) or np.any(np.diff(b) <= 0):
                raise ValueError(f"breakpoints of input {d} must be finite, strictly increasing")
        vals = np.asarray(self.values, dtype=float)
        ident = np.asarray(self.identified, dtype=bool)
        if vals.shape != shape or ident.shape != shape:
            raise ValueError(f"values {vals.shape} and identified {ident.shape} must be {shape}")
        # Unidentified nodes may hold NaN (nothing to sample); replace for interpolation.
        if np.any(~np.isfinite(vals) & ident):
            raise ValueError("identified table nodes must hold finite values")
        object.__setattr__(self, "values", np.where(np.isfinite(vals), vals, 0.0))
        object.__setattr__(self, "identified", ident)
        if self.input_names and len(self.input_names) != len(bps):
            raise ValueError("one input name per breakpoint vector is required")

    @classmethod
    def from_model(cls, model: Callable[[np.ndarray], np.ndarray],
                   breakpoints: Sequence[ArrayLike], *,
                   region: Callable[[np.ndarray], np.ndarray] | None = None,
                   input_names: tuple[str, ...] = (), output_name: str = "y") -> LookupTable:
        """Sample ``model`` (a vectorised callable of (N, p) inputs) on the grid.

        ``region`` (e.g. :meth:`Lolimot.in_region`) flags the identified nodes; without it all
        nodes count as identified.
        """
        bps = tuple(np.asarray(b, dtype=float) for b in breakpoints)
        mesh = np.meshgrid(*bps, indexing="ij")
        pts = np.column_stack([m.ravel() for m in mesh])
        vals = np.asarray(model(pts), dtype=float).reshape(mesh[0].shape)
        ident = (np.ones(vals.shape, dtype=bool) if region is None
                 else np.asarray(region(pts), dtype=bool).reshape(vals.shape))
        return cls(breakpoints=bps, values=vals, identified=ident & np.isfinite(vals),
                   input_names=tuple(input_names), output_name=output_name)

    @property
    def n_inputs(self) -> int:
        return len(self.breakpoints)

    def _corners(self, points: ArrayLike
                 ) -> tuple[list[NDArray[np.intp]], list[FloatArray], BoolArray, BoolArray]:
        """Lower node index and fractional position per input, after clamping."""
        X: FloatArray = np.asarray(points, dtype=float)
        if X.ndim == 1:
            X = X[None, :]
        if X.ndim != 2 or X.shape[1] != self.n_inputs:
            raise ValueError(f"expected (N, {self.n_inputs}) inputs, got shape {X.shape}")
        idx: list[NDArray[np.intp]] = []
        frac: list[FloatArray] = []
        inside: BoolArray = np.all(np.isfinite(X), axis=1)
        for d, b in enumerate(self.breakpoints):
            x = np.nan_to_num(X[:, d], nan=b[0])
            inside &= (x >= b[0]) & (x <= b[-1])
            xc = np.clip(x, b[0], b[-1])
            i = np.clip(np.searchsorted(b, xc, side="right") - 1, 0, b.size - 2)
            idx.append(i)
            frac.append((xc - b[i]) / (b[i + 1] - b[i]))
        return idx, frac, inside, np.all(np.isfinite(X), axis=1)

    def _interp(self, table: FloatArray, idx: list[NDArray[np.intp]], frac: list[FloatArray]
                ) -> FloatArray:
        out = np.zeros(idx[0].shape[0])
        for corner in range(2 ** self.n_inputs):
            w = np.ones_like(out)
            node = []
            for d in range(self.n_inputs):
                up = (corner >> d) & 1
                w = w * (frac[d] if up else 1.0 - frac[d])
                node.append(idx[d] + up)
            out += w * table[tuple(node)]
        return out

    def __call__(self, X: ArrayLike) -> FloatArray:
        """Interpolated values at (N, p) inputs (clamped at the edges; NaN rows give NaN)."""
        idx, frac, _, finite = self._corners(X)
        out = self._interp(self.values, idx, frac)
        out[~finite] = np.nan
        return out

    def evaluate(self, points: ArrayLike) -> tuple[FloatArray, BoolArray]:
        """Values and validity flags: valid = within the breakpoints and the interpolated
        identified flag >= 0.5."""
        X: FloatArray = np.asarray(points, dtype=float)
        if X.size == self.n_inputs and X.ndim <= 2 and self.n_inputs == 2:
            v, ok = self.evaluate_point(float(X.flat[0]), float(X.flat[1]))
            return np.array([v]), np.array([ok])
        idx, frac, inside, finite = self._corners(X)
        vals = self._interp(self.values, idx, frac)
        vals[~finite] = np.nan
        valid = inside & (self._interp(self.identified.astype(float), idx, frac) >= 0.5)
        return vals, valid

    def evaluate_point(self, x0: float, x1: float) -> tuple[float, bool]:
        """One 2-D operating point, the way an ECU evaluates a map: two interval searches and
        one bilinear blend in scalar arithmetic (the per-segment path of the live graph; the
        same result as :meth:`evaluate`, ~50 x faster for a single point)."""
        if self.n_inputs != 2:
            raise ValueError("evaluate_point is for 2-D tables")
        cache = self.__dict__.get("_scalar")
        if cache is None:
            cache = ([b.tolist() for b in self.breakpoints], self.values.tolist(),
                     self.identified.astype(float).tolist())
            object.__setattr__(self, "_scalar", cache)
        (b0, b1), vals, ident = cache
        if not (math.isfinite(x0) and math.isfinite(x1)):
            return math.nan, False
        inside = b0[0] <= x0 <= b0[-1] and b1[0] <= x1 <= b1[-1]
        c0 = min(max(x0, b0[0]), b0[-1])
        c1 = min(max(x1, b1[0]), b1[-1])
        i = min(max(bisect.bisect_right(b0, c0) - 1, 0), len(b0) - 2)
        j = min(max(bisect.bisect_right(b1, c1) - 1, 0), len(b1) - 2)
        f = (c0 - b0[i]) / (b0[i + 1] - b0[i])
        g = (c1 - b1[j]) / (b1[j + 1] - b1[j])
        w00, w10, w01, w11 = (1 - f) * (1 - g), f * (1 - g), (1 - f) * g, f * g
        v = (w00 * vals[i][j] + w10 * vals[i + 1][j] + w01 * vals[i][j + 1]
             + w11 * vals[i + 1][j + 1])
        idf = (w00 * ident[i][j] + w10 * ident[i + 1][j] + w01 * ident[i][j + 1]
               + w11 * ident[i + 1][j + 1])
        return v, bool(inside and idf >= 0.5)

    # ------------------------------------------------------------------ persistence
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready representation (the form an ECU calibration tool would import)."""
        return {"input_names": list(self.input_names), "output_name": self.output_name,
                "breakpoints": [b.tolist() for b in self.breakpoints],
                "values": self.values.tolist(), "identified": self.identified.tolist()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> LookupTable:
        try:
            return cls(breakpoints=tuple(np.asarray(b, dtype=float) for b in d["breakpoints"]),
                       values=np.asarray(d["values"], dtype=float),
                       identified=np.asarray(d["identified"], dtype=bool),
                       input_names=tuple(d.get("input_names", ())),
                       output_name=d.get("output_name", "y"))
        except (KeyError, TypeError) as exc:
            raise ValueError(f"not a look-up table: {exc}") from exc

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_dict()))
        return path

    @classmethod
    def load(cls, path: str | Path) -> LookupTable:
        from fdi_ros.core.files import read_document

        doc = read_document(path, "look-up table", fmt="json")
        if not isinstance(doc, Mapping):
            raise ValueError(f"{path}: not a look-up table (a JSON object is expected)")
        return cls.from_dict(doc)


def table_error(model: Callable[[FloatArray], ArrayLike], table: LookupTable, points: ArrayLike
                ) -> dict[str, float | int]:
    """Table-versus-model error on points X (only where the table is valid).

    Returns
    -------
    dict with ``rmse``, ``max_abs`` (output units), ``n_points`` used and ``nodes``.
    """
    X: FloatArray = np.asarray(points, dtype=float)
    vals, valid = table.evaluate(X)
    if not valid.any():
        return {"rmse": float("nan"), "max_abs": float("nan"), "n_points": 0,
                "nodes": int(table.values.size)}
    e = vals[valid] - np.asarray(model(X[valid]), dtype=float)
    return {"rmse": float(np.sqrt(np.mean(e ** 2))), "max_abs": float(np.abs(e).max()),
            "n_points": int(valid.sum()), "nodes": int(table.values.size)}
