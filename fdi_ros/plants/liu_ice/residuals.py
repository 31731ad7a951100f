"""Structured parity residuals of the LiU-ICE air path, LOLIMOT models identified fault-free.

Six residual generators, each leaving out sensors so that the set isolates the four fault
classes (see :data:`RESIDUALS`; the fault-symptom table follows from ``uses`` with
:func:`fdi_ros.core.structure.derive_fst`). All are written in logarithms: a sensor gain
``g`` then shifts a residual by ``ln g`` at every operating point, whatever the flow.

=========  =========================================  ==========================  ==========
residual   output                                     inputs (lag in samples)     uses
=========  =========================================  ==========================  ==========
``r_pic``  ln(p_ic / p_amb)                           n, throttle, wastegate,     p_ic
                                                      wastegate(-2), throttle(-2)
``r_sd``   ln(maf T_im / (n p_im)) (speed-density)    n, ln p_im, dln p_im        maf, p_im,
                                                                                  manifold
``r_pim``  ln(p_im / p_amb)                           n, throttle(0,-1,-2,-4),    p_im,
                                                      n(-2)                       manifold
``r_maf``  ln(maf sqrt(T_amb) / p_amb)                n, throttle(0,-1,-2)        maf,
                                                                                  manifold
``r_th``   ln(maf sqrt(T_im) / p_ic) (throttle)       throttle(0,-1,-2),          maf, p_im,
                                                      ln(p_im/p_ic), dln p_im     p_ic
``r_fuel`` ln(fuel / maf) (lambda control)            n, throttle(0,-2,-6), n(-4) maf,
                                                                                  manifold
=========  =========================================  ==========================  ==========

Static models use the present sample only; the dynamic ones (lagged inputs and differences)
are Schwarte & Isermann's dynamic parity equations: the manifold fills and empties after a
throttle step, which a static map would report as a fault. The leak acts on the manifold's
mass balance (``manifold``): air enters behind the throttle, so the speed-density flow, the
manifold pressure for a given throttle and the metered flow for a given throttle move, while
the throttle's own flow relation (``r_th``) does not.

Each raw residual ``y - f(x)`` is averaged over the last ``filter_len`` valid samples and
divided by its threshold, which depends on the speed band (idle or driving: the models are
better at idle, where the benchmark's faults start). A
sample is *not valid here* (no symptom; the filter restarts) outside the identified region of
any model, or while the driver's inputs move (throttle or speed changed by more than the
gate within ``gate_samples``): there the models are not identified well enough to judge.
"""

from __future__ import annotations

import json
import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fdi_ros.core.lolimot import Lolimot
from fdi_ros.core.structure import derive_fst, hypothesis_norm
from fdi_ros.core.types import FeatureVector, ResidualVector
from fdi_ros.plants.liu_ice import FAULT_ACTS_ON, FAULT_CLASSES

MODEL_FILE = "structured.json"
# Directions a process fault drives the residuals it acts on (sensor gains: either way).
# The leak lets air into the manifold behind the throttle: the manifold pressure rises, the
# metered flow falls short of the speed-density flow and of the throttle-position flow.
FAULT_SIGNS = {"f_iml": {"r_sd": -1, "r_pim": 1, "r_maf": -1, "r_fuel": 1}}
FORMAT = "fdi_ros.liu_ice.structured/1"


@dataclass(frozen=True)
class ResidualSpec:
    """One parity equation: ``target - f(inputs)``; inputs are (derived signal, lag)."""

    name: str
    target: str
    inputs: tuple[tuple[str, int], ...]
    uses: tuple[str, ...]

    @property
    def dynamic(self) -> bool:
        return any(lag > 0 for _, lag in self.inputs) or any(
            s.startswith("d") for s, _ in self.inputs)

    @property
    def input_names(self) -> tuple[str, ...]:
        return tuple(s if lag == 0 else f"{s}(-{lag})" for s, lag in self.inputs)


RESIDUALS: tuple[ResidualSpec, ...] = (
    ResidualSpec("r_pic", "l_pic_amb",
                 (("n", 0), ("throttle", 0), ("wastegate", 0), ("wastegate", 2),
                  ("throttle", 2)), ("p_ic",)),
    ResidualSpec("r_sd", "l_eta", (("n", 0), ("l_pim", 0), ("dl_pim", 0)),
                 ("maf", "p_im", "manifold")),
    ResidualSpec("r_pim", "l_pim_amb",
                 (("n", 0), ("throttle", 0), ("throttle", 1), ("throttle", 2),
                  ("throttle", 4), ("n", 2)), ("p_im", "manifold")),
    ResidualSpec("r_maf", "l_maf_amb",
                 (("n", 0), ("throttle", 0), ("throttle", 1), ("throttle", 2)),
                 ("maf", "manifold")),
    ResidualSpec("r_th", "l_maf_ic",
                 (("throttle", 0), ("throttle", 1), ("throttle", 2), ("l_pr", 0),
                  ("dl_pim", 0)), ("maf", "p_im", "p_ic")),
    ResidualSpec("r_fuel", "l_fuel_maf",
                 (("n", 0), ("throttle", 0), ("throttle", 2), ("throttle", 6), ("n", 4)),
                 ("maf", "manifold")),
)
RESIDUAL_NAMES = tuple(s.name for s in RESIDUALS)
RAW_SIGNALS = ("n", "p_im", "p_ic", "maf", "throttle", "wastegate", "T_im", "p_amb", "T_amb",
               "fuel")
# Samples of history the residuals need (lags, differences and the gate).
DIFF_LAG = 2


def fault_symptom_table(specs: Sequence[ResidualSpec] = RESIDUALS) -> dict[str, tuple[int, ...]]:
    """The FST derived from what each residual uses (columns: :data:`FAULT_CLASSES`)."""
    return derive_fst({s.name: s.uses for s in specs},
                      {f: FAULT_ACTS_ON[f] for f in FAULT_CLASSES})


def _lag(x: np.ndarray, k: int) -> np.ndarray:
    if k == 0:
        return x
    out = np.full_like(x, np.nan)
    out[k:] = x[:-k]
    return out


def derived_signals(sig: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Logarithmic outputs and inputs of the residuals from raw signals (SI units, maf in
    kg/h, n in rpm). Non-positive pressures or flows give NaN (not valid)."""
    def ln(x):
        x = np.asarray(x, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(x > 0, np.log(np.where(x > 0, x, 1.0)), np.nan)

    n = np.asarray(sig["n"], dtype=float)
    l_maf, l_pim, l_pic = ln(sig["maf"]), ln(sig["p_im"]), ln(sig["p_ic"])
    l_pamb, l_tim, l_tamb = ln(sig["p_amb"]), ln(sig["T_im"]), ln(sig["T_amb"])
    return {
        "n": n, "throttle": np.asarray(sig["throttle"], dtype=float),
        "wastegate": np.asarray(sig["wastegate"], dtype=float),
        "l_pim": l_pim,
        "dl_pim": l_pim - _lag(l_pim, DIFF_LAG),
        "l_pr": l_pim - l_pic,
        "l_pic_amb": l_pic - l_pamb,
        "l_eta": l_maf + l_tim - ln(n) - l_pim,
        "l_pim_amb": l_pim - l_pamb,
        "l_maf_amb": l_maf + 0.5 * l_tamb - l_pamb,
        "l_maf_ic": l_maf + 0.5 * l_tim - l_pic,
        "l_fuel_maf": ln(sig["fuel"]) - l_maf,
    }


def regressors(d: Mapping[str, np.ndarray], spec: ResidualSpec) -> tuple[np.ndarray, np.ndarray]:
    """(X (N, p), y (N,)) of one residual; rows without full history hold NaN."""
    X = np.column_stack([_lag(d[s], lag) for s, lag in spec.inputs])
    return X, d[spec.target]


@dataclass(frozen=True)
class Gate:
    """Quasi-stationarity gate: the inputs moved less than these within ``samples``."""

    samples: int = 10
    max_throttle: float = 1.0      # [%]
    max_speed: float = 150.0       # [rpm]

    def mask(self, sig: Mapping[str, np.ndarray]) -> np.ndarray:
        """True where settled (vectorised over a record; the first samples are unsettled)."""
        ok = np.ones(np.asarray(sig["n"]).shape[0], dtype=bool)
        for name, lim in (("throttle", self.max_throttle), ("n", self.max_speed)):
            x = np.asarray(sig[name], dtype=float)
            hi = x.copy()
            lo = x.copy()
            for k in range(1, self.samples + 1):
                xk = _lag(x, k)
                hi = np.fmax(hi, xk)
                lo = np.fmin(lo, xk)
            ok &= (hi - lo) <= lim
        ok[: self.samples] = False
        return ok


class MovingAverage:
    """Mean of the last ``length`` valid rows; an invalid row restarts it."""

    def __init__(self, length: int, width: int) -> None:
        if length < 1:
            raise ValueError("filter length must be >= 1")
        self.length = int(length)
        self.width = int(width)
        self._buf: deque = deque(maxlen=self.length)

    def reset(self) -> None:
        self._buf.clear()

    def step(self, r: np.ndarray, valid: bool) -> np.ndarray:
        if not valid:
            self._buf.clear()
            return np.full(self.width, np.nan)
        self._buf.append(np.asarray(r, dtype=float))
        return np.mean(self._buf, axis=0)


@dataclass
class StructuredResiduals:
    """The identified residual set: LOLIMOT models, centres, thresholds, filter and gate."""

    models: dict[str, Lolimot]
    centre: tuple[float, ...]
    threshold: tuple[tuple[float, ...], ...]   # one row per speed band
    filter_len: int = 20
    bands_rpm: tuple[float, ...] = (1100.0,)    # band edges of engine speed
    gate: Gate = field(default_factory=Gate)
    specs: tuple[ResidualSpec, ...] = RESIDUALS
    info: dict = field(default_factory=dict)
    # Thresholds while the inputs move (one row per speed band) and the filter length there;
    # None: transients are "not valid here".
    threshold_transient: tuple[tuple[float, ...], ...] | None = None
    transient_len: int = 10

    def __post_init__(self) -> None:
        missing = [s.name for s in self.specs if s.name not in self.models]
        if missing:
            raise ValueError(f"no model for residuals {missing}")
        m = len(self.specs)
        self.threshold = tuple(tuple(float(x) for x in row) for row in self.threshold)
        self.bands_rpm = tuple(float(x) for x in self.bands_rpm)
        if len(self.centre) != m or len(self.threshold) != len(self.bands_rpm) + 1 or any(
                len(row) != m for row in self.threshold):
            raise ValueError(f"centre needs {m} values, threshold {len(self.bands_rpm) + 1} "
                             f"rows (speed bands) of {m}")
        if not np.all(np.asarray(self.threshold) > 0):
            raise ValueError("thresholds must be positive")
        if self.threshold_transient is not None:
            self.threshold_transient = tuple(tuple(float(x) for x in row)
                                             for row in self.threshold_transient)
            if np.asarray(self.threshold_transient).shape != np.asarray(self.threshold).shape \
                    or not np.all(np.asarray(self.threshold_transient) > 0):
                raise ValueError("transient thresholds need the shape of the thresholds, > 0")
        if self.transient_len < 1:
            raise ValueError("transient_len must be >= 1")

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.specs)

    @property
    def history(self) -> int:
        """Samples of history one step needs."""
        lags = [lag for s in self.specs for _, lag in s.inputs]
        return max(lags + [DIFF_LAG, self.gate.samples]) + 1

    @property
    def table(self) -> dict[str, tuple[int, ...]]:
        return fault_symptom_table(self.specs)

    # -- batch (identification, offline checks) ----------------------------------------------
    def raw(self, sig: Mapping[str, np.ndarray], *,
            last_only: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Unfiltered residuals (N, m) and validity (N,: settled and inside the identified
        region) of a whole record (with ``last_only``: of its last sample)."""
        R, settled, inside = self.raw_parts(sig, last_only=last_only)
        return R, settled & inside

    def raw_parts(self, sig: Mapping[str, np.ndarray], *,
                  last_only: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unfiltered residuals (N, m), inputs settled (N,), inside the region (N,)."""
        d = derived_signals(sig)
        cols, settled = [], self.gate.mask(sig)
        if last_only:
            settled = settled[-1:]
        for s in self.specs:
            X, y = regressors(d, s)
            if last_only:
                X, y = X[-1:], y[-1:]
            ok = np.all(np.isfinite(X), axis=1) & np.isfinite(y)
            r = np.full(y.shape, np.nan)
            if ok.any():
                inside = self.models[s.name].in_region(X[ok])
                pred = self.models[s.name].predict(X[ok])
                r[np.flatnonzero(ok)[inside]] = (y[ok] - pred)[inside]
            cols.append(r)
        R = np.column_stack(cols)
        # A residual outside its model's identified region says nothing (0, no evidence);
        # the sample is judged when most residuals are inside theirs.
        each = np.isfinite(R)
        inside = each.sum(axis=1) >= len(self.specs) - 1
        return np.where(each, R, 0.0), settled, inside

    def filtered(self, sig: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Filtered residuals (N, m) (NaN where not valid) and validity (N,)."""
        R, valid = self.raw(sig)
        f = MovingAverage(self.filter_len, len(self.specs))
        return np.array([f.step(r, v) for r, v in zip(R, valid)]), valid

    def band(self, n: np.ndarray | float) -> np.ndarray:
        """Speed band index of each engine speed [rpm]."""
        return np.searchsorted(np.asarray(self.bands_rpm), np.asarray(n, dtype=float),
                               side="right")

    def thresholds_at(self, n: np.ndarray | float, *, transient: bool = False) -> np.ndarray:
        """Thresholds (..., m) at engine speed(s) n (``transient``: while the inputs move)."""
        rows = self.threshold_transient if transient and self.threshold_transient is not None \
            else self.threshold
        return np.asarray(rows)[self.band(n)]

    def z(self, filtered: np.ndarray, n: np.ndarray | float) -> np.ndarray:
        """Filtered residuals in threshold units (fault-free within +-1)."""
        return (filtered - np.asarray(self.centre)) / self.thresholds_at(n)

    def transient_filtered(self, sig: Mapping[str, np.ndarray]
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Residuals averaged over ``transient_len`` samples regardless of the gate (NaN
        outside the region), and the settled and inside masks."""
        R, settled, inside = self.raw_parts(sig)
        f = MovingAverage(self.transient_len, len(self.specs))
        return np.array([f.step(r, v) for r, v in zip(R, inside)]), settled, inside

    def scores(self, sig: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Residuals in threshold units (N, m) and validity (N,) of a whole record."""
        R, settled, inside = self.raw_parts(sig)
        inside[: self.history - 1] = False   # as a stream: the history is not full yet
        sc = Scorer(self)
        out = [sc.step(r, st, ins, n) for r, st, ins, n in zip(R, settled, inside, sig["n"])]
        return np.array([o[0] for o in out]), np.array([o[1] for o in out])

    # -- persistence ---------------------------------------------------------------------------
    def save(self, directory: str | Path) -> Path:
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        for name, m in self.models.items():
            m.save(d / f"{name}.npz")
        doc = {"format": FORMAT, "residuals": [
            {"name": s.name, "target": s.target, "inputs": [list(x) for x in s.inputs],
             "uses": list(s.uses)} for s in self.specs],
            "centre": list(self.centre), "threshold": [list(r) for r in self.threshold],
            "threshold_transient": None if self.threshold_transient is None else
            [list(r) for r in self.threshold_transient], "transient_len": self.transient_len,
            "bands_rpm": list(self.bands_rpm),
            "filter_len": self.filter_len, "gate": self.gate.__dict__,
            "fault_symptom_table": {f: list(c) for f, c in self.table.items()},
            "info": self.info}
        (d / MODEL_FILE).write_text(json.dumps(doc, indent=1))
        return d

    @classmethod
    def load(cls, directory: str | Path) -> StructuredResiduals:
        d = Path(directory)
        path = d / MODEL_FILE
        if not path.is_file():
            raise FileNotFoundError(f"no LiU-ICE residual set in {d} (missing {MODEL_FILE}); "
                                    f"run `fdi-ros benchmark liu-ice` or identify first")
        try:
            doc = json.loads(path.read_text())
            if doc.get("format") != FORMAT:
                raise ValueError(f"format {doc.get('format')!r}, expected {FORMAT!r}")
            specs = tuple(ResidualSpec(r["name"], r["target"],
                                       tuple((str(a), int(b)) for a, b in r["inputs"]),
                                       tuple(r["uses"])) for r in doc["residuals"])
            models = {s.name: Lolimot.load(d / f"{s.name}.npz") for s in specs}
            return cls(models=models, centre=tuple(doc["centre"]),
                       threshold=tuple(tuple(r) for r in doc["threshold"]),
                       bands_rpm=tuple(doc["bands_rpm"]), filter_len=int(doc["filter_len"]),
                       threshold_transient=None if doc.get("threshold_transient") is None
                       else tuple(tuple(r) for r in doc["threshold_transient"]),
                       transient_len=int(doc.get("transient_len", 10)),
                       gate=Gate(**doc["gate"]), specs=specs, info=doc.get("info", {}))
        except (KeyError, TypeError, ValueError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path}: malformed residual set: {exc}") from exc


TRANSIENT = "transient inputs: transient thresholds"


class Scorer:
    """One sample's residuals in threshold units, from its raw residuals.

    Settled inputs: the average over the last ``filter_len`` settled samples against the
    settled thresholds. Moving inputs: the average over the last ``transient_len`` samples
    against the (wider) transient thresholds, or "not valid here" without them. Outside the
    identified region: not valid, both filters restart.
    """

    def __init__(self, rs: StructuredResiduals) -> None:
        self.rs = rs
        m = len(rs.specs)
        self._settled = MovingAverage(rs.filter_len, m)
        self._moving = MovingAverage(rs.transient_len, m)

    def reset(self) -> None:
        self._settled.reset()
        self._moving.reset()

    def step(self, r: np.ndarray, settled: bool, inside: bool,
             n: float) -> tuple[np.ndarray, bool, str]:
        m = len(self.rs.specs)
        if not inside:
            self.reset()
            return np.full(m, np.nan), False, "not valid here: outside the identified region"
        moving = self._moving.step(r, True)
        c = np.asarray(self.rs.centre)
        if settled:
            f = self._settled.step(r, True)
            return (f - c) / self.rs.thresholds_at(n), True, ""
        self._settled.reset()
        if self.rs.threshold_transient is None:
            return np.full(m, np.nan), False, "not valid here: transient inputs"
        return (moving - c) / self.rs.thresholds_at(n, transient=True), True, TRANSIENT


_FILLING = "not valid here: filling the history"


def _key(fv: FeatureVector) -> tuple[int, float]:
    """A sample's identity in a stream (the same vector again is answered from memory)."""
    return int(fv.index), float(fv.t_end)


def _admitted(fv: FeatureVector, last_t: float) -> tuple[list[float] | None, str]:
    """(the sample's raw signals, "") when it continues the history, else (None, why not): a
    missing feature, a gap, a bad sample or time going back (the history is no longer
    contiguous and starts again)."""
    try:
        row = [fv.get(k) for k in RAW_SIGNALS]
    except KeyError as exc:
        return None, f"feature missing: {exc}"
    if not fv.valid or not np.all(np.isfinite(row)) or fv.t_end <= last_t:
        return None, fv.status or "sample not valid"
    return row, ""


class ResidualStream:
    """Per-stream state of a residual set: history of raw samples, filter, last result.

    ``step`` takes one feature vector (one sample) and returns (residuals in threshold units,
    valid, status); the same feature vector (index and time) again returns the memoised result, so
    every bank model of one process shares one computation.

    Offline, :meth:`prime` computes a whole recorded stream at once (the raw residuals of each
    contiguous run with array operations, the same filters sample by sample), and ``step`` then
    answers from it; a reset (a model taken on line again) computes the rest of the stream
    again from an empty history, as the sample-by-sample path would go on.
    """

    def __init__(self, rs: StructuredResiduals) -> None:
        self.rs = rs
        self._hist: deque[list[float]] = deque(maxlen=rs.history)
        self._history = rs.history
        self._scorer = Scorer(rs)
        self._last_key: tuple[int, float] | None = None
        self._last: tuple[np.ndarray, bool, str] = (np.full(len(rs.specs), np.nan), False, "")
        self._last_t = -math.inf
        # the primed stream, its results by position, where each sample first is, the last
        # position answered
        self._primed: list[tuple[np.ndarray, bool, str]] | None = None
        self._feats: list[FeatureVector] = []
        self._pos: dict[tuple[int, float], int] = {}
        self._cursor, self._answered = -1, False

    def reset(self) -> None:
        self._hist.clear()
        self._scorer.reset()
        self._last_key = None
        self._last_t = -math.inf
        if self._primed is not None and self._answered:
            # the samples after the last one answered, from an empty history
            k = self._cursor + 1
            self._primed[k:] = self._compute(self._feats[k:])
            self._answered = False

    def prime(self, feats: Sequence[FeatureVector]) -> None:
        """The results of ``feats`` (one recorded stream, in order) computed at once, equal to
        stepping them one by one from an empty history (see the class docstring)."""
        self._primed = None
        self.reset()
        self._feats = list(feats)
        self._pos = {}
        for i, fv in enumerate(self._feats):
            self._pos.setdefault(_key(fv), i)
        self._cursor, self._answered = -1, False
        self._primed = list(self._compute(self._feats))

    def _compute(self, feats: Sequence[FeatureVector]) -> list[tuple[np.ndarray, bool, str]]:
        """The results of ``feats`` stepped one by one from an empty history, by position."""
        m = len(self.rs.specs)
        plan: list[tuple[tuple[int, float], Any]] = []  # per sample: a result, or a run row
        runs: list[list[list[float]]] = [[]]
        hist, last_t = 0, -math.inf
        for fv in feats:
            key = _key(fv)
            if plan and key == plan[-1][0]:  # the same sample again: the same answer
                plan.append((key, ("again", None)))
                continue
            row, why = _admitted(fv, last_t)
            if row is None:
                hist, last_t = 0, -math.inf
                runs.append([])
                plan.append((key, ("reset", (np.full(m, np.nan), False, why))))
                continue
            last_t = fv.t_end
            runs[-1].append(row)
            hist = min(hist + 1, self._history)
            if hist < self._history:
                plan.append((key, ("fill", (np.full(m, np.nan), False, _FILLING))))
            else:
                plan.append((key, ("row", (len(runs) - 1, len(runs[-1]) - 1, row[0]))))
        parts = {}
        for i, rows in enumerate(runs):
            if len(rows) >= self._history:
                H = np.array(rows)
                parts[i] = self.rs.raw_parts({k: H[:, j] for j, k in enumerate(RAW_SIGNALS)})
        scorer = Scorer(self.rs)
        out: list[tuple[np.ndarray, bool, str]] = []
        for _, (kind, v) in plan:
            if kind == "row":
                i, j, n = v
                R, settled, inside = parts[i]
                out.append(scorer.step(R[j], bool(settled[j]), bool(inside[j]), n))
            elif kind == "again":
                out.append(out[-1])
            else:
                scorer.reset()
                out.append(v)
        return out

    def step(self, fv: FeatureVector) -> tuple[np.ndarray, bool, str]:
        key = _key(fv)
        if key == self._last_key:
            return self._last
        if self._primed is not None:
            k = self._cursor + 1  # the next sample of the stream, else where this one first is
            if not (k < len(self._feats) and _key(self._feats[k]) == key):
                k = self._pos.get(key, -1)
            if k >= 0:
                self._cursor, self._answered = k, True
                self._last_key, self._last = key, self._primed[k]
                return self._last
            # not a sample of the primed stream: sample by sample from here
            self._primed = None
            self.reset()
        self._last_key = key
        m = len(self.rs.specs)
        row, why = _admitted(fv, self._last_t)
        if row is None:
            self.reset()
            self._last_key = key
            self._last = (np.full(m, np.nan), False, why)
            return self._last
        self._last_t = fv.t_end
        self._hist.append(row)
        if len(self._hist) < self._history:
            self._scorer.reset()
            self._last = (np.full(m, np.nan), False, _FILLING)
            return self._last
        H = np.array(self._hist)
        sig = {k: H[:, i] for i, k in enumerate(RAW_SIGNALS)}
        R, settled, inside = self.rs.raw_parts(sig, last_only=True)
        self._last = self._scorer.step(R[-1], bool(settled[-1]), bool(inside[-1]), row[0])
        return self._last


# ----------------------------------------------------------------------------- bank models
# Largest sensor gain error a sensor-fault hypothesis may explain (ln 1.2: +-20 %).
MAX_GAIN_LOG = math.log(1.2)


class StructuredResidualModel:
    """A bank model over the structured residual set: the fault-free hypothesis (``fault``
    empty) or one fault class. ``values`` are the filtered residuals in threshold units
    (fault-free within +-1); ``norm`` is :func:`~fdi_ros.core.structure.hypothesis_norm`
    with this hypothesis' FST column. A sensor gain hypothesis explains at most a gain of
    ``max_gain_log`` (log units) in each residual; the leak is not bounded."""

    def __init__(self, *, stream: ResidualStream, model_id: str, fault: str = "",
                 quiet_penalty: float = 0.45, max_gain_log: float = MAX_GAIN_LOG) -> None:
        table = stream.rs.table
        if fault and fault not in table:
            raise ValueError(f"unknown fault class {fault!r}; known: {sorted(table)}")
        self.stream = stream
        self.model_id = model_id
        self.fault = fault
        self.column = table[fault] if fault else None
        self.quiet_penalty = float(quiet_penalty)
        self.bounded = bool(fault) and FAULT_ACTS_ON[fault] in RAW_SIGNALS
        signs = FAULT_SIGNS.get(fault, {})
        self.sign = tuple(signs.get(n, 0) for n in stream.rs.names) if signs else None
        self.max_gain_log = float(max_gain_log)

    def reset(self) -> None:
        self.stream.reset()

    def batch(self, features: Sequence[FeatureVector], shared: dict[str, Any]
              ) -> StructuredResidualModel:
        """Offline (:func:`fdi_ros.core.diagnoser.diagnose_offline`): the shared stream primed
        with the whole recorded stream once; the model itself answers from it."""
        key = f"liu_ice_stream_{id(self.stream)}"
        if key not in shared:
            self.stream.prime(features)
            shared[key] = self.stream
        return self

    def residuals(self, fv: FeatureVector) -> ResidualVector:
        vals, valid, status = self.stream.step(fv)
        rs = self.stream.rs
        norm = float("nan")
        if valid:
            bound = None
            if self.bounded:
                # the bound in the units of the thresholds in effect for this sample
                bound = self.max_gain_log / rs.thresholds_at(fv.get("n"),
                                                             transient=status == TRANSIENT)
            norm = hypothesis_norm(vals, self.column, quiet_penalty=self.quiet_penalty,
                                   bound=bound, sign=self.sign)
        return ResidualVector(model_id=self.model_id, index=fv.index, t=fv.t_end, valid=valid,
                              status=status, names=rs.names,
                              units=("threshold",) * len(rs.names),
                              values=np.asarray(vals, dtype=float), norm=norm)


_STREAMS: dict[str, ResidualStream] = {}


def shared_stream(directory: str | Path) -> ResidualStream:
    """One residual stream per model directory and process (the bank's models share it)."""
    key = str(Path(directory).resolve())
    if key not in _STREAMS:
        _STREAMS[key] = ResidualStream(StructuredResiduals.load(directory))
    return _STREAMS[key]


def _register() -> None:
    from fdi_ros.core.residual_models import register_residual_model

    @register_residual_model("liu_ice_structured")
    def _make(spec: dict, *, base_dir: Path, model_id: str) -> StructuredResidualModel:
        unknown = set(spec) - {"path", "fault", "quiet_penalty", "shared", "max_gain_log"}
        if unknown:
            raise ValueError(f"liu_ice_structured: unknown keys {sorted(unknown)}")
        d = base_dir / spec.get("path", ".")
        stream = shared_stream(d) if spec.get("shared", True) else \
            ResidualStream(StructuredResiduals.load(d))
        return StructuredResidualModel(stream=stream, model_id=model_id,
                                       fault=str(spec.get("fault", "") or ""),
                                       quiet_penalty=float(spec.get("quiet_penalty", 0.45)),
                                       max_gain_log=float(spec.get("max_gain_log",
                                                                   MAX_GAIN_LOG)))


_register()
