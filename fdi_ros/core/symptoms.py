"""Symptoms from residuals: threshold, sign, debounce, validity.

Each residual is centred by its fault-free mean, smoothed by a causal moving average over
``filter_len`` steps and compared with thresholds derived from fault-free statistics
(:func:`calibrate_thresholds`): level ``-`` below ``-thr``, ``+`` above ``thr``, ``++`` above
``intense_factor * thr``, else ``o``. A level must persist ``debounce_on`` steps to be asserted
and ``debounce_off`` steps to be cleared. An invalid residual vector ("not valid here") gives
no symptom and restarts the filter. Isolation by a fault-symptom table: :mod:`fdi_ros.core.fst`.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fdi_ros.core.files import read_document
from fdi_ros.core.fst import signature_string
from fdi_ros.core.types import ResidualVector

__all__ = ["SymptomConfig", "SymptomGenerator", "SymptomState", "calibrate_thresholds",
           "load_thresholds", "moving_average", "symptom_name"]


def symptom_name(residual: str) -> str:
    """``r_x`` -> ``s_x`` (other names: ``s_`` prefixed)."""
    return "s_" + residual.removeprefix("r_")


def moving_average(R: np.ndarray, length: int) -> np.ndarray:
    """Causal moving average over the last ``length`` rows (fewer at the start)."""
    c = np.cumsum(np.vstack([np.zeros((1,) + R.shape[1:]), R]), axis=0)
    k = np.arange(1, R.shape[0] + 1)
    lo = np.maximum(k - length, 0)
    cnt = (k - lo).reshape((-1,) + (1,) * (R.ndim - 1))
    out: np.ndarray = (c[k] - c[lo]) / cnt
    return out


@dataclass(frozen=True)
class SymptomConfig:
    """Thresholds and debouncing of the symptoms of one residual vector (the threshold file).

    Attributes
    ----------
    names : the residuals, in the order of the other tuples.
    centre : fault-free mean of each residual (subtracted first).
    threshold : symptom threshold on the centred, filtered residual (units as the residual).
    scale : fault-free (robust) standard deviation of the filtered residual, for reports.
        Bank-model norms divide by ``threshold`` instead, so that a fault-free residual stays
        below one whatever its distribution.
    intense_factor : ``++`` when the residual exceeds this multiple of the threshold.
    filter_len : moving-average length [segments]; debounce_on/off : persistence [segments].
    The remaining settings belong to the residual model that produced the residuals and are
    kept in the same file (the generator ignores them):

    storage_coeff : dynamic correction of eta_V for the air stored in the boost volume while
        p2 changes: ``r_eta += storage_coeff * (dp2/dt) / (n p2)`` (identified from fault-free
        transients by :func:`calibrate_from_fault_free`; 0 = static residual as in the paper).
    settle_s, max_speed_change, max_fuel_change : quasi-stationarity gate on the ECU's inputs:
        a segment is "not valid here" while engine speed [rpm] or injected fuel [mg/stroke]
        has moved more than these within the last ``settle_s`` seconds (the static reference
        models do not hold in transients; the gate looks at inputs, not at p2 or the MAF,
        so that a fault's own transient does not switch its detection off).
    rate_lag : dp2/dt of the storage correction is a backward difference over this many
        segments.
    """

    centre: tuple[float, ...]
    threshold: tuple[float, ...]
    scale: tuple[float, ...]
    intense_factor: float = 4.0
    filter_len: int = 4
    debounce_on: int = 2
    debounce_off: int = 4
    names: tuple[str, ...] = ()
    storage_coeff: float = 0.0
    settle_s: float = 0.0
    max_speed_change: float = float("inf")
    max_fuel_change: float = float("inf")
    rate_lag: int = 2

    def __post_init__(self) -> None:
        m = len(self.names)
        if m == 0:
            raise ValueError("a symptom configuration needs the names of its residuals")
        if not (self.max_speed_change > 0 and self.max_fuel_change > 0 and self.settle_s >= 0
                and self.rate_lag >= 1 and np.isfinite(self.storage_coeff)):
            raise ValueError("gate limits must be > 0, settle_s >= 0, rate_lag >= 1, "
                             "storage_coeff finite")
        for name in ("centre", "threshold", "scale"):
            v = tuple(float(x) for x in getattr(self, name))
            if len(v) != m or not np.all(np.isfinite(v)):
                raise ValueError(f"{name} needs {m} finite values")
            object.__setattr__(self, name, v)
        if min(self.threshold) <= 0 or min(self.scale) <= 0:
            raise ValueError("thresholds and scales must be positive")
        if self.intense_factor <= 1.0:
            raise ValueError("intense_factor must be > 1")
        if self.filter_len < 1 or self.debounce_on < 1 or self.debounce_off < 1:
            raise ValueError("filter_len, debounce_on and debounce_off must be >= 1")
        object.__setattr__(self, "names", tuple(self.names))

    def to_dict(self) -> dict[str, Any]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SymptomConfig:
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown symptom settings: {sorted(unknown)}")
        kw: dict[str, Any] = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()}
        return cls(**kw)


def load_thresholds(path: str | Path) -> SymptomConfig:
    """The one loader of threshold files (JSON or YAML; the settings may sit under a
    ``symptoms:`` key)."""
    doc = read_document(path, "threshold file")
    if isinstance(doc, Mapping) and isinstance(doc.get("symptoms"), Mapping):
        doc = doc["symptoms"]
    if not isinstance(doc, Mapping):
        raise ValueError(f"{path}: thresholds must be a mapping")
    try:
        return SymptomConfig.from_dict(doc)
    except TypeError as exc:
        raise ValueError(f"{path}: malformed thresholds: {exc}") from None


def calibrate_thresholds(R: np.ndarray, valid: np.ndarray | None = None, *,
                         k_sigma: float = 5.0, margin: float = 1.25, filter_len: int = 4,
                         min_threshold: Sequence[float] | None = None,
                         names: Sequence[str], **settings: Any) -> SymptomConfig:
    """Thresholds from fault-free residuals (N, m), not tuned on any fault.

    ``threshold = max(k_sigma * s, margin * max|f - c|, min_threshold)`` where ``f`` is the
    filtered residual, ``c`` its median and ``s`` its robust standard deviation (1.4826 MAD):
    a Gaussian-tail bound that also covers every fault-free excursion seen, with margin.
    """
    R = np.asarray(R, dtype=float)
    if valid is not None:
        R = R[np.asarray(valid, dtype=bool)]
    R = R[np.all(np.isfinite(R), axis=1)]
    if R.shape[0] < 20:
        raise ValueError(f"need >= 20 valid fault-free residual rows, got {R.shape[0]}")
    c = np.median(R, axis=0)
    F = moving_average(R - c, filter_len)
    s = 1.4826 * np.median(np.abs(F - np.median(F, axis=0)), axis=0)
    s = np.where(s > 0, s, np.std(F, axis=0) + 1e-12)
    thr = np.maximum(k_sigma * s, margin * np.abs(F).max(axis=0))
    if min_threshold is not None:
        thr = np.maximum(thr, np.asarray(min_threshold, dtype=float))
    return SymptomConfig(centre=tuple(c), threshold=tuple(thr), scale=tuple(s),
                         filter_len=filter_len, names=tuple(names), **settings)


@dataclass(frozen=True)
class SymptomState:
    """Debounced symptoms after one residual vector (mirrors ``fdi_msgs/Symptoms``)."""

    index: int
    t: float
    valid: bool
    status: str
    names: tuple[str, ...]
    levels: tuple[int, ...]
    residuals: tuple[float, ...]
    threshold_low: tuple[float, ...]
    threshold_high: tuple[float, ...]
    threshold_intense: tuple[float, ...]

    @property
    def signature(self) -> str:
        return signature_string(self.levels)

    def by_name(self) -> dict[str, int]:
        return dict(zip(self.names, self.levels))

    def in_order(self, columns: Sequence[str]) -> tuple[int, ...]:
        """Levels in the order ``columns`` (e.g. a fault-symptom table's); absent ones 0."""
        d = self.by_name()
        return tuple(d.get(s, 0) for s in columns)


@dataclass
class SymptomGenerator:
    """Thresholds + debouncing, stateful per stream of ResidualVectors of the nominal model.

    ``update`` returns levels in the order of the config's residual names; residual
    ``r_<x>`` gives symptom ``s_<x>``.
    """

    config: SymptomConfig
    _buf: deque[np.ndarray] = field(init=False, repr=False)
    _level: np.ndarray = field(init=False, repr=False)
    _cand: np.ndarray = field(init=False, repr=False)
    _count: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.config, SymptomConfig):
            self.config = SymptomConfig.from_dict(self.config)
        self.reset()

    def reset(self) -> None:
        m = len(self.config.names)
        self._buf = deque(maxlen=self.config.filter_len)
        self._level = np.zeros(m, dtype=int)
        self._cand = np.zeros(m, dtype=int)
        self._count = np.zeros(m, dtype=int)

    @property
    def symptom_names(self) -> tuple[str, ...]:
        return tuple(symptom_name(r) for r in self.config.names)

    def _values(self, rv: ResidualVector) -> np.ndarray:
        if tuple(rv.names) == self.config.names:
            return np.asarray(rv.values, dtype=float)
        try:
            return np.array([rv.values[list(rv.names).index(k)] for k in self.config.names],
                            dtype=float)
        except ValueError:
            raise ValueError(f"residual vector {rv.names} lacks {self.config.names}") from None

    def update(self, rv: ResidualVector) -> SymptomState:
        cfg = self.config
        thr = np.asarray(cfg.threshold)
        c = np.asarray(cfg.centre)
        m = len(cfg.names)
        thr_t = (tuple(c - thr), tuple(c + thr), tuple(c + cfg.intense_factor * thr))
        v = self._values(rv)
        if not rv.valid or not np.all(np.isfinite(v)):
            # Not valid here: no symptom, and the filter restarts when data is valid again.
            self.reset()
            return SymptomState(rv.index, rv.t, False, rv.status or "residuals not valid",
                                self.symptom_names, (0,) * m, tuple(np.full(m, np.nan)),
                                *thr_t)
        self._buf.append(v - c)
        f = np.mean(self._buf, axis=0)
        raw = np.where(f < -thr, -1, np.where(f > cfg.intense_factor * thr, 2,
                                              np.where(f > thr, 1, 0)))
        same = raw == self._cand
        self._count = np.where(same, self._count + 1, 1)
        self._cand = raw
        need = np.where(raw == 0, cfg.debounce_off, cfg.debounce_on)
        switch = (raw != self._level) & (self._count >= need)
        # "+" -> "++" (and back) is a change of intensity, not of sign: no extra delay.
        grow = (self._level != 0) & (raw != 0) & (np.sign(raw) == np.sign(self._level))
        self._level = np.where(switch | grow, raw, self._level)
        return SymptomState(rv.index, rv.t, True, "", self.symptom_names,
                            tuple(int(x) for x in self._level), tuple(f + c), *thr_t)

    def run(self, rvs: Sequence[ResidualVector]) -> list[SymptomState]:
        """:meth:`update` over a stream (from a reset), the moving average with array
        operations and the debounce as a lean loop: the same states, many times faster."""
        cfg = self.config
        m, n_rows, L = len(cfg.names), len(rvs), max(int(cfg.filter_len), 1)
        self.reset()
        if not n_rows:
            return []
        c, thr = np.asarray(cfg.centre, dtype=float), np.asarray(cfg.threshold, dtype=float)
        thr_t = (tuple(c - thr), tuple(c + thr), tuple(c + cfg.intense_factor * thr))
        V = np.array([self._values(rv) for rv in rvs], dtype=float).reshape(n_rows, m)
        ok = np.array([bool(rv.valid) for rv in rvs]) & np.all(np.isfinite(V), axis=1)
        X = np.where(ok[:, None], V - c, 0.0)
        k = np.arange(n_rows)
        count = np.minimum(k - np.maximum.accumulate(np.where(ok, -1, k)), L)
        # the filter's sum, oldest sample first (as np.mean adds the buffer's rows)
        acc = np.zeros((n_rows, m))
        for back in range(L - 1, -1, -1):
            take = ok & (back < count)
            acc = acc + np.where(take[:, None], X[np.maximum(k - back, 0)], 0.0)
        filt = acc / np.maximum(count, 1)[:, None]
        raw = np.where(filt < -thr, -1, np.where(filt > cfg.intense_factor * thr, 2,
                                              np.where(filt > thr, 1, 0))).tolist()
        FC = filt + c
        names = self.symptom_names
        nan_t = tuple(np.full(m, np.nan))
        on, off = int(cfg.debounce_on), int(cfg.debounce_off)
        level, cand, cnt = [0] * m, [0] * m, [0] * m
        out = []
        for j, rv in enumerate(rvs):
            if not ok[j]:
                level, cand, cnt = [0] * m, [0] * m, [0] * m
                out.append(SymptomState(rv.index, rv.t, False, rv.status or "residuals not valid",
                                        names, (0,) * m, nan_t, *thr_t))
                continue
            r = raw[j]
            for i in range(m):
                ri, li = r[i], level[i]
                cnt[i] = cnt[i] + 1 if ri == cand[i] else 1
                cand[i] = ri
                if (ri != li and cnt[i] >= (off if ri == 0 else on)) or \
                        (li != 0 and ri != 0 and (ri > 0) == (li > 0)):
                    level[i] = ri
            out.append(SymptomState(rv.index, rv.t, True, "", names, tuple(level),
                                    tuple(FC[j]), *thr_t))
        # leave the generator as update() would have
        self._level, self._cand = np.array(level, dtype=int), np.array(cand, dtype=int)
        self._count = np.array(cnt, dtype=int)
        for j in range(n_rows - int(count[-1]) if ok[-1] else n_rows, n_rows):
            self._buf.append(V[j] - c)
        return out
