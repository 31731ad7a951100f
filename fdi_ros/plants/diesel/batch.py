"""The diesel bank models over a whole recorded stream at once (offline diagnosis).

:class:`BatchedModel` answers ``residuals(fv)`` for the feature vectors of one recorded stream
exactly as the wrapped :class:`~fdi_ros.plants.diesel.symptoms.ReferenceResidualModel` or
:class:`~fdi_ros.plants.diesel.symptoms.FaultHypothesisResidualModel` would segment by
segment, but computes each *run* (the segments from a reset to the end of the stream) in one
go with array operations:

- the parity residuals and the fault-effect maps ``g(x)`` of every segment (stateless);
- the quasi-stationarity gate (backward differences over ``rate_lag`` segments, input ranges
  over the last ``settle_s``) from the positions of the resets it makes (invalid segments);
- the window statistics of the norms (size estimate ``s``, block RMS) from running sums.

The diagnoser still calls the models segment by segment (the on-line set changes as faults
get isolated); a model taken on line again is reset, which starts a new run. The step-wise
classes stay the reference: ``tests/test_offline_batch.py`` checks that both give the same
diagnosis events.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fdi_ros.core.sliding import window_ranges, window_reduce
from fdi_ros.core.symptoms import TOO_FAST, effect_values, rate_status
from fdi_ros.core.types import FeatureVector, ResidualVector
from fdi_ros.plants.diesel.ecu import (
    ACTUATOR_MOVE,
    ACTUATOR_SETTLE_S,
    GATED_ACTUATORS,
    actuator_status,
)
from fdi_ros.plants.diesel.plant import TOO_FAST_HOLD
from fdi_ros.plants.diesel.reference import transient_regime


@dataclass(frozen=True)
class Parity:
    """The stateless part of the bank models, given by :mod:`fdi_ros.plants.diesel.symptoms`:
    parity residuals of many segments and of one, their names and units, the features they
    read and why a segment is outside the models' region."""

    many: Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray]]   # R, valid, regime
    one: Callable[..., ResidualVector]
    names: tuple[str, ...]
    units: tuple[str, ...]
    required: tuple[str, ...]                   # features every segment must have
    features: Callable[..., tuple[str, ...]]    # features the models read
    region_status: Callable[..., list[str]]     # why segments are outside the region


_new = object.__new__
# per segment of a run: residuals (N, m), validity, status, operating regime
_Rows = tuple[np.ndarray, np.ndarray, list[str], list[str]]
# a model's answers for a run: validity, status, values, norm, regime per segment
_Run = tuple[list[bool], list[str], list[np.ndarray], list[float], list[str]]
_SETTLING = "not valid here: settling (too little history after a gap)"


def _column(feats: Sequence[FeatureVector], name: str) -> tuple[np.ndarray, np.ndarray]:
    """Values of one feature over the stream (NaN where absent) and where it is present."""
    idx: dict[tuple[str, ...], int] = {}
    out = np.full(len(feats), np.nan)
    have = np.zeros(len(feats), dtype=bool)
    for k, fv in enumerate(feats):
        j = idx.get(fv.names)
        if j is None:
            j = idx[fv.names] = fv.names.index(name) if name in fv.names else -1
        if j >= 0:
            out[k] = fv.values[j]
            have[k] = True
    return out, have


class _Stream:
    """Stateless per-segment quantities of one stream, shared by the models of a bank."""

    def __init__(self, feats: Sequence[FeatureVector], parity: Parity) -> None:
        self.parity = parity
        self.feats = list(feats)
        self.N = len(self.feats)
        self.t = np.array([fv.t_end for fv in self.feats], dtype=float)
        self.fv_valid = np.array([bool(fv.valid) for fv in self.feats])
        self.cols: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._matrix: np.ndarray | None = None
        self._base: dict[int, _Rows] = {}
        self.gated: dict[Any, _Rows] = {}
        self.pos = {id(fv): k for k, fv in enumerate(self.feats)}

    def col(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        if name not in self.cols:
            names = self.uniform()
            if self._matrix is not None and names is not None:   # one layout for the stream
                have = name in names
                self.cols[name] = (self._matrix[:, names.index(name)] if have
                                   else np.full(self.N, np.nan), np.full(self.N, have))
            else:
                self.cols[name] = _column(self.feats, name)
        return self.cols[name]

    def uniform(self) -> tuple[str, ...] | None:
        """The feature names when every vector of the stream has the same, else None."""
        names = self.feats[0].names if self.feats else ()
        if self._matrix is None and all(fv.names == names for fv in self.feats):
            self._matrix = np.array([fv.values for fv in self.feats], dtype=float)
        return names if self._matrix is not None else None

    def base(self, models: Any) -> _Rows:
        """Parity residuals (N, 5), validity, status and regime of every segment, as
        :func:`~fdi_ros.plants.diesel.symptoms.residual_vector` gives them one by one."""
        key = id(models)
        if key in self._base:
            return self._base[key]
        P, names = self.parity, self.uniform()
        if names is None or not all(k in names for k in P.required):
            # mixed or incomplete layouts (rare): segment by segment
            rvs = [P.one(models, fv) for fv in self.feats]
            R = np.array([rv.values for rv in rvs], dtype=float).reshape(self.N, len(P.names))
            self._base[key] = (R, np.array([rv.valid for rv in rvs], dtype=bool),
                               [rv.status for rv in rvs], [rv.regime for rv in rvs])
            return self._base[key]
        data = {k: self.col(k)[0] for k in P.features(models) if k in names}
        R, ok, regime = P.many(models, data)
        valid = self.fv_valid & ok
        why = P.region_status(models, data, ok) if not ok.all() else None
        status = [""] * self.N
        for k in np.flatnonzero(~valid):
            fv = self.feats[k]
            if not fv.valid:
                status[k] = fv.status or "features not valid"
            else:
                status[k] = (why[k] if why is not None else "") or "residuals not finite"
        self._base[key] = (R, valid, status, [str(r) for r in regime])
        return self._base[key]


def _window_sums(X: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Sums of the last ``count[j]`` rows of X up to row j (inclusive), for every j."""
    C = np.concatenate([np.zeros((1,) + X.shape[1:]), np.cumsum(X, axis=0)])
    j = np.arange(X.shape[0])
    return C[j + 1] - C[j + 1 - count]


def _window_norms(Z: np.ndarray, G: np.ndarray | None, *, window: int, block: int = 10,
                  min_effect: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(size estimate s, block RMS of ``Z - s G`` (or Z)) over the last ``window`` rows of a
    run, for every row: the statistics the step-wise models keep in their buffers."""
    m = Z.shape[0]
    count = np.minimum(np.arange(m) + 1, window)
    s = np.zeros(m)
    use = np.zeros(m, dtype=bool)
    if G is not None:
        num = _window_sums(np.sum(G * Z, axis=1), count)
        den = _window_sums(np.sum(G * G, axis=1), count)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(den > 0, np.maximum(0.0, num / np.where(den > 0, den, 1.0)), 0.0)
        gmean = _window_sums(G, count) / count[:, None]
        use = np.max(np.abs(s[:, None] * gmean), axis=1) >= min_effect
    CZ = np.concatenate([np.zeros((1, Z.shape[1])), np.cumsum(Z, axis=0)])
    CG = np.concatenate([np.zeros((1, Z.shape[1])), np.cumsum(G, axis=0)]) \
        if G is not None else None
    j1 = np.arange(m) + 1
    first = j1 - count
    sq = np.zeros(m)
    nb = np.zeros(m)
    for b in range(-(-window // block)):
        end = j1 - b * block
        have = end > first
        start = np.maximum(first, end - block)
        e, a = np.where(have, end, 0), np.where(have, start, 0)
        size = np.where(have, e - a, 1)
        mean = CZ[e] - CZ[a]
        if CG is not None:
            mean = mean - np.where(use, s, 0.0)[:, None] * (CG[e] - CG[a])
        mean = mean / size[:, None]
        sq += np.where(have, np.sum(mean ** 2, axis=1), 0.0)
        nb += have
    return s, np.sqrt(sq / (nb * Z.shape[1]))


class BatchedModel:
    """A diesel bank model answering for the segments of one recorded stream (see module)."""

    def __init__(self, model: Any, stream: _Stream) -> None:
        self.model = model
        self.model_id = model.model_id
        self.stream = stream
        self._pos = stream.pos
        self._names, self._units = stream.parity.names, stream.parity.units
        self._run: _Run | None = None
        self._k0 = 0
        self._next = 0

    def reset(self) -> None:
        self.model.reset()
        self._run = None

    def residuals(self, fv: FeatureVector) -> ResidualVector:
        k = self._pos.get(id(fv))
        if k is None:
            raise ValueError("BatchedModel answers only for the feature vectors it was "
                             "prepared with")
        if self._run is None:
            self._k0, self._run = k, self._compute(k)
        elif k != self._next:
            raise ValueError(f"{self.model_id}: segment {k} out of turn (expected "
                             f"{self._next}); reset() first")
        self._next = k + 1
        valid, status, values, norm, regime = self._run
        i = k - self._k0
        # a frozen record's fields set at once (the per-field __setattr__ of the dataclass's
        # __init__ is most of the cost of a step here)
        rv = _new(ResidualVector)
        rv.__dict__.update(model_id=self.model_id, index=fv.index, t=fv.t_end, valid=valid[i],
                           status=status[i], names=self._names, units=self._units,
                           values=values[i], norm=norm[i], regime=regime[i])
        return rv

    # -- one run, from a reset at segment k0 to the end of the stream ----------------------
    def _gate(self, k0: int, R: np.ndarray, valid: np.ndarray, status: list[str],
              regime: list[str]) -> _Rows:
        """QuasiStationarity.apply over the run (correction of r_eta, transient gate or
        transient regime)."""
        c = self.model.config
        if c is None or not (c.storage_coeff != 0.0 or c.settle_s > 0):
            return R, valid, status, regime
        st = self.stream
        t = st.t[k0:]
        n, has_n = (a[k0:] for a in st.col("n"))
        p2, has_p2 = (a[k0:] for a in st.col("p2"))
        fuel = st.col("fuel")[0][k0:]
        m = t.size
        k = np.arange(m)
        elig = st.fv_valid[k0:] & has_n & has_p2 & np.isfinite(n) & np.isfinite(p2)
        rs = np.maximum.accumulate(np.where(elig, -1, k)) + 1   # start of the current run
        lag = c.rate_lag
        back = np.maximum(k - lag, 0)
        dt = t - t[back]
        with np.errstate(divide="ignore", invalid="ignore"):
            dp = np.where(elig & (k - rs >= lag) & (dt > 0), (p2 - p2[back]) / dt, np.nan)
        if c.settle_s > 0:
            lo = np.maximum(rs, np.searchsorted(t, t - c.settle_s, side="left"))
            lo = np.minimum(lo, k)
            cnt = k - lo + 1
            span_ok = elig & (cnt >= 2) & (t - t[lo] >= 0.8 * c.settle_s)
            dn = window_reduce(np.maximum, n, lo) - window_reduce(np.minimum, n, lo)
            bad = np.concatenate([[0], np.cumsum(~np.isfinite(fuel))])
            f_ok = bad[k + 1] - bad[lo] == 0
            with np.errstate(invalid="ignore"):
                df = np.where(f_ok, window_reduce(np.maximum, fuel, lo)
                              - window_reduce(np.minimum, fuel, lo), 0.0)
            dn = np.where(span_ok, dn, np.nan)
            df = np.where(span_ok, df, np.nan)
            settled = span_ok & (dn <= c.max_speed_change) & (df <= c.max_fuel_change)
        else:
            dn, df = np.zeros(m), np.zeros(m)
            settled = np.ones(m, dtype=bool)
        for i in np.flatnonzero(valid & ~(np.isfinite(dp) & np.isfinite(dn))):
            valid[i], status[i] = False, _SETTLING
        # the largest magnitude over the last TOO_FAST_HOLD segments of the run
        held = np.maximum(rs, k - TOO_FAST_HOLD + 1)
        too_fast = {key: window_reduce(np.maximum, np.abs(np.nan_to_num(
            self.stream.col(key)[0][k0:], nan=0.0)), held) for key in c.invalid_rates}
        for k, v in too_fast.items():
            with np.errstate(invalid="ignore"):
                rows = np.flatnonzero(valid & (np.abs(v) > c.invalid_rates[k]))
            for i in rows:
                valid[i] = False
                status[i] = rate_status({a: float(x[i]) for a, x in too_fast.items()},
                                        c.invalid_rates, TOO_FAST)
        transient = valid & ~settled
        moved = self._actuators_moved(k0, t, rs)
        big = np.zeros(m, dtype=bool)
        for v in moved.values():
            with np.errstate(invalid="ignore"):
                big |= v > (c.actuator_move or ACTUATOR_MOVE)
        for i in np.flatnonzero(valid & settled & big):   # the others have no status to give
            transient[i] = bool(actuator_status({a: float(v[i]) for a, v in moved.items()},
                                                c.actuator_move))
        rates = {k: self.stream.col(k)[0][k0:] for k in c.max_rates}
        fast = np.zeros(m, dtype=bool)
        for k, v in rates.items():
            with np.errstate(invalid="ignore"):
                fast |= np.abs(v) > c.max_rates[k]
        still = valid & ~transient
        for i in np.flatnonzero(still & fast):
            transient[i] = True
        if c.transients == "regime":
            for i in np.flatnonzero(transient):
                regime[i] = transient_regime(regime[i])
        else:
            for i in np.flatnonzero(transient):
                valid[i] = False
                status[i] = (f"not valid here: transient inputs (speed moved {dn[i]:.0f} "
                             f"rpm, fuel {df[i]:.1f} mg within {c.settle_s:g} s)"
                             if not settled[i] else
                             actuator_status({a: float(v[i]) for a, v in moved.items()},
                                             c.actuator_move)
                             or rate_status({k: float(v[i]) for k, v in rates.items()},
                                            c.max_rates))
        if "r_eta" in c.names and c.storage_coeff:
            j = c.names.index("r_eta")
            rows = np.flatnonzero(valid)
            R[rows, j] += c.storage_coeff * dp[rows] / (n[rows] * p2[rows])
        return R, valid, status, regime

    def _actuators_moved(self, k0: int, t: np.ndarray,
                         rs: np.ndarray) -> dict[str, np.ndarray]:
        """Per actuator command, its range over the last ACTUATOR_SETTLE_S of the run (NaN:
        not in the data), as QuasiStationarity.actuators_moved."""
        out = {}
        for a in GATED_ACTUATORS:
            v, has = (x[k0:] for x in self.stream.col(a))
            v = np.where(has & np.isfinite(v), v, np.nan)
            if np.isfinite(v).any():
                out[a] = window_ranges(t, v, ACTUATOR_SETTLE_S, start=rs)
        return out

    def _compute(self, k0: int) -> _Run:
        models, cfg = self.model.models, self.model.config
        try:   # the bank's models share their reference set and thresholds: gate once
            key: Any = (k0, id(models), cfg)
            hash(key)
        except TypeError:
            key = None
        gated = self.stream.gated.get(key) if key is not None else None
        if gated is None:
            R0, valid0, status0, regime0 = self.stream.base(models)
            gated = self._gate(k0, R0[k0:].copy(), valid0[k0:].copy(), status0[k0:],
                               regime0[k0:])
            if key is not None:
                self.stream.gated[key] = gated
        R, valid, status, regime = (gated[0].copy(), gated[1].copy(), list(gated[2]),
                                    list(gated[3]))
        norm = np.full(R.shape[0], np.nan)
        values = R
        C, T = self._statistics(cfg, valid, status, regime)
        if not hasattr(self.model, "directions"):   # the nominal (reference) model
            if cfg is not None:
                rows = np.flatnonzero(valid)
                Z = (R[rows] - C[rows]) / T[rows]
                if self.model.window == 1:
                    norm[rows] = np.sqrt(np.mean(Z ** 2, axis=1))
                else:
                    norm[rows] = _window_norms(Z, None, window=self.model.window)[1]
        else:
            values, norm = self._hypothesis(k0, R, valid, status, regime, C, T)
        return (valid.tolist(), status, list(values), norm.tolist(), regime)

    @staticmethod
    def _statistics(cfg: Any, valid: np.ndarray, status: list[str],
                    regime: list[str]) -> tuple[np.ndarray, np.ndarray]:
        """Per segment, the centre and thresholds of its regime (rows (N, m)); a valid segment
        of a regime without thresholds is made "not valid here", as _finish does."""
        N = len(regime)
        if cfg is None:
            return np.zeros((N, 1)), np.ones((N, 1))
        stats = {}
        for r in set(regime):
            stats[r] = cfg.statistics(r) if cfg.knows(r) else None
        for i in np.flatnonzero(valid):
            if stats[regime[i]] is None:
                valid[i] = False
                status[i] = f"not valid here: no thresholds for regime {regime[i]!r}"
        base = cfg.statistics()
        C = np.array([(stats[r] or base)[0] for r in regime], dtype=float).reshape(N, -1)
        T = np.array([(stats[r] or base)[1] for r in regime], dtype=float).reshape(N, -1)
        return C, T

    def _hypothesis(self, k0: int, R: np.ndarray, valid: np.ndarray, status: list[str],
                    regime: list[str], C: np.ndarray, T: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
        h = self.model   # a fault-hypothesis model
        cfg = h.config
        for i in np.flatnonzero(valid):
            if not h.covers(regime[i]):
                valid[i] = False
                status[i] = (f"not valid here: the {h.fault} effect maps are not identified "
                             f"in regime {regime[i]!r}")
        at_all = np.flatnonzero(valid)
        whys = h.look_alike_here([self.stream.feats[k0 + i] for i in at_all],
                                 [regime[i] for i in at_all])
        for i, why in zip(at_all, whys):
            if why:
                valid[i], status[i] = False, why
        rows = np.flatnonzero(valid)
        G = np.full((rows.size, len(cfg.names)), np.nan)
        reg = np.array(regime, dtype=object)[rows]
        for name in set(reg.tolist()):
            # each regime's effect maps over their own inputs
            at = np.flatnonzero(reg == name)   # positions in rows (and G)
            sub = rows[at]
            inputs = h.inputs_for(name)
            cols = [self.stream.col(k) for k in inputs]
            if all(have[k0:][sub].all() for _, have in cols):
                keep_a = np.arange(sub.size)
            else:   # rare: ask the features one by one for the step-wise message
                keep = []
                for r, i in enumerate(sub):
                    try:
                        [self.stream.feats[k0 + i].get(k) for k in inputs]
                        keep.append(r)
                    except KeyError as exc:
                        valid[i], status[i] = False, f"feature missing: {exc}"
                keep_a = np.asarray(keep, dtype=np.intp)
            if keep_a.size:
                X = np.column_stack([c[0][k0:][sub[keep_a]] for c in cols])
                G[at[keep_a]] = h.direction(X, name)
                leak = h.leak_effect([self.stream.feats[k0 + i] for i in sub[keep_a]], name)
                if leak is not None:   # the exhaust side's, not the map's
                    G[at[keep_a], cfg.names.index("r_eta")] = leak
        fin = np.all(np.isfinite(G), axis=1)
        for bad in rows[~fin]:
            if valid[bad]:
                valid[bad], status[bad] = False, "fault effect map not defined here"
        rows, G = rows[fin], G[fin]
        norm = np.full(R.shape[0], np.nan)
        values = R.copy()
        if rows.size:
            Z = (R[rows] - C[rows]) / T[rows]
            s, rms = _window_norms(Z, G, window=h.window, min_effect=h.min_effect)
            norm[rows] = rms + h.penalty
            values[rows] = R[rows] - s[:, None] * effect_values(G, T[rows])
        return values, norm


def batched(model: Any, features: Sequence[FeatureVector], shared: dict[str, Any],
            parity: Parity) -> Any:
    """``model`` over one recorded stream (``shared``: per-stream data the bank's models
    share); the model itself when the stream's times do not increase (no batching)."""
    stream = shared.get("diesel")
    if stream is None or stream.feats is not features and list(features) != stream.feats:
        stream = shared["diesel"] = _Stream(features, parity)
    if stream.N > 1 and not np.all(np.diff(stream.t) >= 0):
        return model
    return BatchedModel(model, stream)
