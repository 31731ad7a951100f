"""Validity regions of identified models: where their identification data lay, per input.

A data-driven model holds where it was identified, and nowhere else. Its regressors' joint
coverage (e.g. :meth:`fdi_ros.core.lolimot.Lolimot.in_region`) is one bound; every other input
that the identification data held fixed or spanned is another: a commanded actuator (a valve
that stayed closed, a flap that stayed open), an operating mode, a regressor's range. A
:class:`ValidityRegion` is learned from the identification data (the range of each such input,
widened by a tolerance), stored with the model, and checked per segment. Outside it the model
says "not valid here" and why, never a residual that a symptom could be made of.

The region names no plant: the wing chooses which inputs bound its models and the tolerances
of the ones that the identification held fixed.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["InputRange", "NOT_VALID", "ValidityRegion"]

NOT_VALID = "not valid here"


@dataclass(frozen=True)
class InputRange:
    """The identified range of one input, ``lo .. hi`` (data), accepted within ``+-tol``."""

    name: str
    lo: float
    hi: float
    tol: float = 0.0
    unit: str = ""

    def __post_init__(self) -> None:
        if not self.name:
            raise ValueError("an input range needs a name")
        vals = (float(self.lo), float(self.hi), float(self.tol))
        if not all(math.isfinite(v) for v in vals) or vals[0] > vals[1] or vals[2] < 0:
            raise ValueError(f"input range {self.name}: need finite lo <= hi and tol >= 0, "
                             f"got {vals}")
        object.__setattr__(self, "lo", vals[0])
        object.__setattr__(self, "hi", vals[1])
        object.__setattr__(self, "tol", vals[2])

    @property
    def held(self) -> bool:
        """The identification held this input fixed (no span)."""
        return self.hi == self.lo

    @property
    def _unit(self) -> str:
        """The unit as a suffix (" kg/m^3"); empty for a ratio or no unit."""
        return f" {self.unit}" if self.unit and self.unit != "1" else ""

    def describe(self) -> str:
        span = f"{self.lo:.4g}" if self.held else f"{self.lo:.4g}..{self.hi:.4g}"
        return f"{span}{self._unit}"

    def contains(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        with np.errstate(invalid="ignore"):
            inside = np.isfinite(x) & (x >= self.lo - self.tol) & (x <= self.hi + self.tol)
        return np.asarray(inside, dtype=bool)

    def reason(self, x: float) -> str:
        """Why ``x`` is outside ("" when inside)."""
        if not math.isfinite(x):
            return f"{self.name} not finite (identified at {self.describe()})"
        if x < self.lo - self.tol or x > self.hi + self.tol:
            where = "held at" if self.held else "over"
            return f"{self.name} = {x:.4g}{self._unit} outside the identified region ({where} " \
                   f"{self.describe()})"
        return ""


@dataclass(frozen=True)
class ValidityRegion:
    """Per-input identified ranges of a model (a box; the joint coverage of the regressors is
    the model's own check). Missing inputs are "not valid here": the model cannot tell."""

    ranges: tuple[InputRange, ...]

    def __post_init__(self) -> None:
        rs = tuple(r if isinstance(r, InputRange) else InputRange(**r) for r in self.ranges)
        names = [r.name for r in rs]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate inputs in a validity region: {names}")
        object.__setattr__(self, "ranges", rs)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(r.name for r in self.ranges)

    def __getitem__(self, name: str) -> InputRange:
        for r in self.ranges:
            if r.name == name:
                return r
        raise KeyError(name)

    @classmethod
    def learn(cls, data: Mapping[str, Any], names: Sequence[str], *,
              tolerance: Mapping[str, float] | None = None, rel_tolerance: float = 0.02,
              units: Mapping[str, str] | None = None) -> ValidityRegion:
        """Ranges of ``names`` in the identification data (finite values only).

        Each range is widened by ``tolerance[name]`` (absolute, e.g. a command's resolution for
        an input the identification held fixed) plus ``rel_tolerance`` times its span. Inputs
        absent from ``data`` are left out (the data cannot bound them)."""
        if rel_tolerance < 0:
            raise ValueError("rel_tolerance must be >= 0")
        tolerance = dict(tolerance or {})
        units = dict(units or {})
        out = []
        for k in names:
            if k not in data:
                continue
            x = np.asarray(data[k], dtype=float).ravel()
            x = x[np.isfinite(x)]
            if x.size == 0:
                raise ValueError(f"no finite values of {k} to learn its identified range from")
            lo, hi = float(x.min()), float(x.max())
            tol = float(tolerance.get(k, 0.0)) + rel_tolerance * (hi - lo)
            out.append(InputRange(k, lo, hi, tol, units.get(k, "")))
        return cls(tuple(out))

    def check(self, values: Mapping[str, float]) -> str:
        """"" when every input of the region is present and inside, else the reason (all
        inputs outside, named)."""
        why = []
        for r in self.ranges:
            if r.name not in values:
                why.append(f"{r.name} not in the data (identified at {r.describe()})")
                continue
            w = r.reason(float(values[r.name]))
            if w:
                why.append(w)
        return f"{NOT_VALID}: " + "; ".join(why) if why else ""

    def contains(self, data: Mapping[str, Any], n: int) -> np.ndarray:
        """Vectorised: True per row (of ``n``) inside every range; a missing input -> False."""
        ok = np.ones(n, dtype=bool)
        for r in self.ranges:
            if r.name not in data:
                return np.zeros(n, dtype=bool)
            ok &= r.contains(np.broadcast_to(np.asarray(data[r.name], dtype=float), (n,)))
        return ok

    def reasons(self, data: Mapping[str, Any], n: int) -> list[str]:
        """Vectorised :meth:`check`: one reason per row ("" inside)."""
        ok = self.contains(data, n)
        out = [""] * n
        cols = {r.name: np.broadcast_to(np.asarray(data[r.name], dtype=float), (n,))
                for r in self.ranges if r.name in data}
        for i in np.flatnonzero(~ok):
            out[i] = self.check({k: float(v[i]) for k, v in cols.items()})
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"ranges": [{"name": r.name, "lo": r.lo, "hi": r.hi, "tol": r.tol,
                            "unit": r.unit} for r in self.ranges]}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ValidityRegion:
        try:
            return cls(tuple(InputRange(**dict(r)) for r in d["ranges"]))
        except (KeyError, TypeError) as exc:
            raise ValueError(f"malformed validity region: {exc}") from None
