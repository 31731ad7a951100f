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
           "load_thresholds", "moving_average", "rate_status", "symptom_name"]


# What a residual model's quasi-stationarity gate makes of a transient segment.
TRANSIENT_RULES = ("not_valid", "regime")
TRANSIENT_SUFFIX = "/transient"
# status word of a segment whose inputs change beyond the invalid_rates limits
TOO_FAST = "changing too fast"


def rate_status(values: Mapping[str, float], limits: Mapping[str, float],
                kind: str = "transient") -> str:
    """The gate's status for features beyond their ``max_rates`` limits ("" if none; a
    non-finite value counts as within)."""
    big = {k: v for k, v in values.items() if np.isfinite(v) and abs(v) > limits[k]}
    if not big:
        return ""
    what = ", ".join(f"|{k}| = {abs(v):.1f} > {limits[k]:g}" for k, v in big.items())
    return f"not valid here: {kind} ({what})"


def effect_values(g: np.ndarray, thr: np.ndarray) -> np.ndarray:
    """An effect ``g`` in units of the symptom thresholds back in the residuals' units; 0
    where a residual is not judged (an infinite threshold, and no effect estimated there)."""
    g, thr = np.asarray(g, dtype=float), np.asarray(thr, dtype=float)
    out = np.zeros(np.broadcast_shapes(g.shape, thr.shape))
    np.multiply(g, thr, out=out, where=g != 0.0)
    return out


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


def _unscaled(z: np.ndarray, thr: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Filtered residuals back in their units; NaN where not judged (infinite threshold)."""
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(thr), z * thr + centre, np.nan)


# (centre, threshold) arrays of a SymptomConfig's regimes, made once per configuration (read
# per segment and bank model): id -> (the configuration, {regime: arrays}); a few
# configurations live at a time, so the bound only keeps the dict from growing in a long run
_STATISTICS: dict[int, tuple[Any, dict[str, tuple[np.ndarray, np.ndarray]]]] = {}


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
    max_rates : further gate limits: a segment is transient while the magnitude of one of
        these features (e.g. a temperature's rate of change) exceeds its limit.
    actuator_move : the change of a commanded actuator that makes the following seconds
        transient (None: the residual model's own default).
    invalid_rates : like ``max_rates``, but beyond these limits a segment is "not valid
        here" whatever ``transients`` says (too fast for any threshold).
    transients : what the gate makes of a transient segment: "not_valid" (no diagnosis), or
        "regime" (a regime of its own, ``<regime>/transient``, judged by the thresholds of the
        fault-free transients: diagnosed, less sensitively).
    regimes : operating regimes of their own (name -> ``{"centre", "threshold", "scale"}``,
        tuples as above): a model that covers several regimes (e.g. an engine's EGR valve
        closed or open) with models of different accuracy says in each residual vector which
        regime produced it, and the residuals are judged against that regime's statistics.
        The top-level ``centre``, ``threshold`` and ``scale`` are those of ``base_regime``
        (and of vectors that name no regime). A vector of a regime the file does not hold is
        "not valid here". A regime may also carry ``"judged"`` (a flag per residual): a
        residual not judged there never gives a symptom in it (its threshold counts as
        infinite; its calibrated one is kept for the record), for a regime whose maps of that
        residual do not carry over (e.g. crank pulsations with the EGR valve open).
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
    regimes: Mapping[str, Mapping[str, tuple[float, ...]]] = field(default_factory=dict)
    base_regime: str = ""
    transients: str = "not_valid"
    max_rates: Mapping[str, float] = field(default_factory=dict)
    actuator_move: float | None = None
    invalid_rates: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        m = len(self.names)
        if m == 0:
            raise ValueError("a symptom configuration needs the names of its residuals")
        regimes = {}
        for rname, st in dict(self.regimes).items():
            keys = {"centre", "threshold", "scale"}
            if not isinstance(st, Mapping) or not keys <= set(st) <= keys | {"judged"}:
                raise ValueError(f"regime {rname!r}: needs exactly centre, threshold, scale "
                                 "(and judged, optional)")
            vals: dict[str, tuple[Any, ...]] = {
                k: tuple(float(x) for x in st[k]) for k in sorted(keys)}
            if any(len(v) != m or not np.all(np.isfinite(v)) for v in vals.values()):
                raise ValueError(f"regime {rname!r}: needs {m} finite values each")
            if min(vals["threshold"]) <= 0 or min(vals["scale"]) <= 0:
                raise ValueError(f"regime {rname!r}: thresholds and scales must be positive")
            if "judged" in st:
                judged = tuple(st["judged"])
                if len(judged) != m or not all(isinstance(j, bool) for j in judged):
                    raise ValueError(f"regime {rname!r}: judged needs {m} true/false flags")
                if not all(judged):
                    vals["judged"] = judged
            regimes[str(rname)] = vals
        object.__setattr__(self, "regimes", regimes)
        object.__setattr__(self, "base_regime", str(self.base_regime))
        if self.transients not in TRANSIENT_RULES:
            raise ValueError(f"transients must be one of {TRANSIENT_RULES}")
        for name in ("max_rates", "invalid_rates"):
            rates = {str(k): float(v) for k, v in dict(getattr(self, name)).items()}
            if any(not v > 0 for v in rates.values()):
                raise ValueError(f"{name} limits must be > 0")
            object.__setattr__(self, name, rates)
        if self.actuator_move is not None and not self.actuator_move > 0:
            raise ValueError("actuator_move must be > 0")
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
        d = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}
        d["regimes"] = {r: {k: list(v) for k, v in st.items()} for r, st in self.regimes.items()}
        d["max_rates"] = dict(self.max_rates)
        d["invalid_rates"] = dict(self.invalid_rates)
        return d

    def knows(self, regime: str) -> bool:
        """Whether the file holds statistics for ``regime`` ("" and the base regime: yes)."""
        return regime in ("", self.base_regime) or regime in self.regimes

    def judged(self, regime: str = "") -> tuple[bool, ...]:
        """Per residual, whether ``regime`` judges it (all, unless the regime says)."""
        flags = self.regimes.get(regime, {}).get("judged")
        return tuple(bool(j) for j in flags) if flags else (True,) * len(self.names)

    def judges_all(self, regime: str = "") -> bool:
        """Whether every residual is judged in ``regime`` (a fault-symptom table's signatures
        span them all: with some not judged there, they are compared on the judged ones)."""
        return all(self.judged(regime))

    def statistics(self, regime: str = "") -> tuple[np.ndarray, np.ndarray]:
        """(centre, threshold) of a regime ("" or the base regime: the top-level ones), as
        read-only arrays."""
        mine = _STATISTICS.get(id(self))
        if mine is None or mine[0] is not self:
            if len(_STATISTICS) >= 64:
                _STATISTICS.clear()
            mine = _STATISTICS[id(self)] = (self, {})
        hit = mine[1].get(regime)
        if hit is not None:
            return hit
        if regime in ("", self.base_regime):
            c, thr = np.array(self.centre), np.array(self.threshold)
        else:
            st = self.regimes.get(regime)
            if st is None:
                raise KeyError(f"no thresholds for regime {regime!r}")
            c, thr = np.array(st["centre"]), np.array(st["threshold"])
            if "judged" in st:  # not judged there: never a symptom
                thr = np.where(np.asarray(st["judged"]), thr, np.inf)
        for a in (c, thr):
            a.flags.writeable = False
        mine[1][regime] = (c, thr)
        return c, thr

    def normalise(self, values: np.ndarray, regime: str = "") -> np.ndarray:
        """Residuals centred and divided by their regime's thresholds: fault-free they stay
        within +-1 once filtered, whatever the regime."""
        c, thr = self.statistics(regime)
        out: np.ndarray = (np.asarray(values, dtype=float) - c) / thr
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SymptomConfig:
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown symptom settings: {sorted(unknown)}")
        kw: dict[str, Any] = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()
                              if k != "regimes"}
        regimes = d.get("regimes") or {}
        if not isinstance(regimes, Mapping):
            raise ValueError("regimes must map regime names to their statistics")
        return cls(**kw, regimes=regimes)


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


def _statistics(R: np.ndarray, *, k_sigma: float, margin: float, filter_len: int,
                min_threshold: Sequence[float] | None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centre, threshold, scale) of fault-free residual rows (see calibrate_thresholds)."""
    if R.shape[0] < 20:
        raise ValueError(f"need >= 20 valid fault-free residual rows, got {R.shape[0]}")
    c = np.median(R, axis=0)
    F = moving_average(R - c, filter_len)
    s = 1.4826 * np.median(np.abs(F - np.median(F, axis=0)), axis=0)
    s = np.where(s > 0, s, np.std(F, axis=0) + 1e-12)
    thr = np.maximum(k_sigma * s, margin * np.abs(F).max(axis=0))
    if min_threshold is not None:
        thr = np.maximum(thr, np.asarray(min_threshold, dtype=float))
    return c, thr, s


def calibrate_thresholds(R: np.ndarray, valid: np.ndarray | None = None, *,
                         k_sigma: float = 5.0, margin: float = 1.25, filter_len: int = 4,
                         min_threshold: Sequence[float] | None = None,
                         names: Sequence[str], regimes: Sequence[str] | None = None,
                         base_regime: str = "", min_rows: int = 20,
                         margins: Mapping[str, float] | None = None,
                         **settings: Any) -> SymptomConfig:
    """Thresholds from fault-free residuals (N, m), not tuned on any fault.

    ``threshold = max(k_sigma * s, margin * max|f - c|, min_threshold)`` where ``f`` is the
    filtered residual, ``c`` its median and ``s`` its robust standard deviation (1.4826 MAD):
    a Gaussian-tail bound that also covers every fault-free excursion seen, with margin.

    ``regimes``: the operating regime of each row (see :class:`SymptomConfig`); each regime
    gets statistics of its own rows (``base_regime``'s, or "" rows', are the top-level ones).
    A regime with fewer than ``min_rows`` valid rows gets none: its residuals stay "not valid
    here" rather than be judged by another regime's thresholds. ``margins``: a regime's own
    margin on its largest fault-free excursion (e.g. a regime whose models rest on fewer data
    and generalise less).
    """
    R = np.asarray(R, dtype=float)
    keep = np.all(np.isfinite(R), axis=1)
    if valid is not None:
        keep &= np.asarray(valid, dtype=bool)
    labels = np.array([""] * R.shape[0] if regimes is None else
                      ["" if r == base_regime else str(r) for r in regimes], dtype=object)
    margins = dict(margins or {})

    def stats(rows: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return _statistics(rows, k_sigma=k_sigma, margin=margins.get(name, margin),
                           filter_len=filter_len, min_threshold=min_threshold)

    c, thr, s = stats(R[keep & (labels == "")], base_regime)
    extra = {}
    for name in sorted(set(labels[keep]) - {""}):
        rows = R[keep & (labels == name)]
        if rows.shape[0] >= max(min_rows, 20):
            rc, rt, rs = stats(rows, name)
            extra[name] = {"centre": tuple(rc), "threshold": tuple(rt), "scale": tuple(rs)}
    return SymptomConfig(centre=tuple(c), threshold=tuple(thr), scale=tuple(s),
                         filter_len=filter_len, names=tuple(names), regimes=extra,
                         base_regime=base_regime, **settings)


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
    regime: str = ""   # the operating regime of the residuals (see SymptomConfig.regimes)

    @property
    def signature(self) -> str:
        return signature_string(self.levels)

    def by_name(self) -> dict[str, int]:
        return dict(zip(self.names, self.levels))

    def in_order(self, columns: Sequence[str]) -> tuple[int, ...]:
        """Levels in the order ``columns`` (e.g. a fault-symptom table's); absent ones 0."""
        d = self.by_name()
        return tuple(d.get(s, 0) for s in columns)


# the reported thresholds (low, high, intense) of one regime
_Bounds = tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]


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

    def _regime(self, rv: ResidualVector) -> tuple[np.ndarray, np.ndarray, _Bounds, str]:
        """(centre, threshold, reported thresholds, why not valid) of the vector's regime."""
        cfg = self.config
        if not cfg.knows(rv.regime):
            c, thr = cfg.statistics()
            why = f"not valid here: no thresholds for regime {rv.regime!r}"
        else:
            (c, thr), why = cfg.statistics(rv.regime), ""
        return c, thr, (tuple(c - thr), tuple(c + thr), tuple(c + cfg.intense_factor * thr)), why

    def update(self, rv: ResidualVector) -> SymptomState:
        cfg = self.config
        m = len(cfg.names)
        c, thr, thr_t, why = self._regime(rv)
        v = self._values(rv)
        if why or not rv.valid or not np.all(np.isfinite(v)):
            # Not valid here: no symptom, and the filter restarts when data is valid again.
            self.reset()
            return SymptomState(rv.index, rv.t, False,
                                (rv.status if not rv.valid else why) or why
                                or "residuals not valid",
                                self.symptom_names, (0,) * m, tuple(np.full(m, np.nan)),
                                *thr_t, regime=rv.regime)
        # the filter runs on residuals in units of their regime's thresholds, so that a
        # change of regime neither jumps nor mixes units
        self._buf.append((v - c) / thr)
        f = np.mean(self._buf, axis=0)
        raw = np.where(f < -1.0, -1, np.where(f > cfg.intense_factor, 2,
                                              np.where(f > 1.0, 1, 0)))
        same = raw == self._cand
        self._count = np.where(same, self._count + 1, 1)
        self._cand = raw
        need = np.where(raw == 0, cfg.debounce_off, cfg.debounce_on)
        switch = (raw != self._level) & (self._count >= need)
        # "+" -> "++" (and back) is a change of intensity, not of sign: no extra delay.
        grow = (self._level != 0) & (raw != 0) & (np.sign(raw) == np.sign(self._level))
        self._level = np.where(switch | grow, raw, self._level)
        return SymptomState(rv.index, rv.t, True, "", self.symptom_names,
                            tuple(int(x) for x in self._level), tuple(_unscaled(f, thr, c)),
                            *thr_t, regime=rv.regime)

    def run(self, rvs: Sequence[ResidualVector]) -> list[SymptomState]:
        """:meth:`update` over a stream (from a reset), the moving average with array
        operations and the debounce as a lean loop: the same states, many times faster."""
        cfg = self.config
        m, n_rows, L = len(cfg.names), len(rvs), max(int(cfg.filter_len), 1)
        self.reset()
        if not n_rows:
            return []
        per = {r: self._regime(rv) for r, rv in {rv.regime: rv for rv in rvs}.items()}
        C = np.array([per[rv.regime][0] for rv in rvs], dtype=float).reshape(n_rows, m)
        T = np.array([per[rv.regime][1] for rv in rvs], dtype=float).reshape(n_rows, m)
        V = np.array([self._values(rv) for rv in rvs], dtype=float).reshape(n_rows, m)
        ok = np.array([bool(rv.valid) and not per[rv.regime][3] for rv in rvs]) \
            & np.all(np.isfinite(V), axis=1)
        X = np.where(ok[:, None], (V - C) / T, 0.0)
        k = np.arange(n_rows)
        count = np.minimum(k - np.maximum.accumulate(np.where(ok, -1, k)), L)
        # the filter's sum, oldest sample first (as np.mean adds the buffer's rows)
        acc = np.zeros((n_rows, m))
        for back in range(L - 1, -1, -1):
            take = ok & (back < count)
            acc = acc + np.where(take[:, None], X[np.maximum(k - back, 0)], 0.0)
        filt = acc / np.maximum(count, 1)[:, None]
        raw = np.where(filt < -1.0, -1, np.where(filt > cfg.intense_factor, 2,
                                                 np.where(filt > 1.0, 1, 0))).tolist()
        FC = _unscaled(filt, T, C)
        names = self.symptom_names
        nan_t = tuple(np.full(m, np.nan))
        on, off = int(cfg.debounce_on), int(cfg.debounce_off)
        level, cand, cnt = [0] * m, [0] * m, [0] * m
        out = []
        for j, rv in enumerate(rvs):
            thr_t = per[rv.regime][2]
            if not ok[j]:
                level, cand, cnt = [0] * m, [0] * m, [0] * m
                why = rv.status if not rv.valid else per[rv.regime][3]
                out.append(SymptomState(rv.index, rv.t, False, why or "residuals not valid",
                                        names, (0,) * m, nan_t, *thr_t, regime=rv.regime))
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
                                    tuple(FC[j]), *thr_t, regime=rv.regime))
        # leave the generator as update() would have
        self._level, self._cand = np.array(level, dtype=int), np.array(cand, dtype=int)
        self._count = np.array(cnt, dtype=int)
        for j in range(n_rows - int(count[-1]) if ok[-1] else n_rows, n_rows):
            self._buf.append(X[j])
        return out
