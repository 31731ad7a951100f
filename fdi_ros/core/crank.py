"""Crank-synchronous front end: one feature set per crank-angle segment of ``segment_deg``
(one firing: 180 deg CA for a four-cylinder four-stroke engine; the engine's wing says).

Signal model per segment (Schwarte & Isermann 2002, eqs. 4 and 7), alpha in deg CA::

    x(alpha) = mean + A cos(2 pi alpha / D + phi)  (+ higher orders)

Segments are aligned to multiples of ``segment_deg`` of the unwrapped crank angle:
segment j covers ``[j D, (j + 1) D]``, ``D = segment_deg``.

Phase convention
----------------
``phi`` is returned in deg CA (D deg CA = one period = 2 pi), wrapped to ``[-D/2, D/2)``. A
signal whose maximum is at ``alpha = j D + a`` has ``phi = -a`` (wrapped). Consumers that need
another branch re-wrap with a centre (e.g. a wing's ``wrap_phase``).

Method
------
Each sample ``i`` owns the crank-angle cell between the midpoints to its neighbours. Its
weight in segment j is the length of (cell_i intersected with segment j), so a cell that
straddles a boundary is split between two segments. The mean and the harmonics 1..K (K =
``n_harmonics``, default 3) are the weighted least-squares fit of
``x = b0 + sum_k (a_k cos(k w alpha) + b_k sin(k w alpha))``, ``w = 2 pi / D``, i.e. the
normal equations ``G beta = g`` with ``G = sum w_i phi_i phi_i^T``, ``g = sum w_i phi_i x_i``.
For uniform sampling these weights are the trapezoid (boundaries on samples) or the rectangle
rule (boundaries between samples); both integrate trigonometric polynomials over a whole
period exactly, and ``G`` is diagonal. For any other sampling (non-uniform in crank angle,
e.g. samples equidistant in time during a speed ramp) a signal made of the mean and harmonics
up to K is still recovered exactly, because the least-squares fit reproduces any function in
its span; components above K leak in as O(h^2) errors.

Then ``A = hypot(a_1, b_1)``, ``phi = atan2(-b_1, a_1)`` (rad) -> deg CA by ``* 90 / pi``.

Features (names fixed for the project)
--------------------------------------
``n`` rpm, ``rho2 = p2 / (R T2)`` kg/m^3, ``p2`` Pa, ``T2`` K, ``maf`` kg/h (crank-angle
means), ``maf_amp`` kg/h, ``maf_phase`` deg CA, ``p2_amp`` Pa, ``p2_phase`` deg CA,
``eta_v = maf / (1/2 n/60 V_D rho2)`` (maf in kg/s), then the means of ``fuel``,
``egr_cmd``, ``swirl_cmd``, ``vgt`` when the block has them.

Validity
--------
A segment is invalid (``valid=False``, all values NaN, ``status`` says why) when a sample in
it is NaN/inf ("nan"), when a crank-angle step touching it is a gap ("gap": larger than
``max_gap_deg``, or by default more than 1.5 x the smaller neighbouring step, so one missing
sample is enough), or when the samples do not cover it ("incomplete"). Crank angles that are not
strictly increasing (unsorted, duplicates) and decreasing times raise ``ValueError``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fdi_ros.core.types import FeatureVector, SampleBlock

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
StrArray = NDArray[np.str_]

FEATURE_NAMES = ("n", "rho2", "p2", "T2", "maf", "maf_amp", "maf_phase", "p2_amp", "p2_phase",
                 "eta_v")
FEATURE_UNITS = ("rpm", "kg/m^3", "Pa", "K", "kg/h", "kg/h", "deg CA", "Pa", "deg CA", "1")
ACTUATOR_CHANNELS = ("fuel", "egr_cmd", "swirl_cmd", "vgt")
ACTUATOR_UNITS = {"fuel": "mg/stroke", "egr_cmd": "1", "swirl_cmd": "1", "vgt": "1"}
REQUIRED = {"n": "rpm", "p2": "Pa", "T2": "K", "maf": "kg/h"}


@dataclass(frozen=True)
class CrankHarmonics:
    """Per-segment least-squares coefficients of several channels.

    Attributes
    ----------
    index : (S,) segment numbers j (segment j starts at ``j * segment_deg``).
    alpha_start : (S,) [deg CA]; t_start, t_end : (S,) [s] (interpolated at the boundaries).
    coef : (C, S, 1 + 2K) ``[b0, a_1, b_1, ..., a_K, b_K]`` per channel and segment.
    valid : (S,) bool; status : (S,) str ("ok", "nan", "gap", "incomplete").
    """

    index: np.ndarray
    alpha_start: np.ndarray
    t_start: np.ndarray
    t_end: np.ndarray
    coef: np.ndarray
    valid: np.ndarray
    status: np.ndarray

    def amplitude(self, k: int = 1) -> FloatArray:
        """(C, S) amplitude of harmonic k."""
        amp: FloatArray = np.hypot(self.coef[..., 2 * k - 1], self.coef[..., 2 * k])
        return amp

    def phase_deg(self, k: int, segment_deg: float) -> FloatArray:
        """(C, S) phase of harmonic k in deg CA of that harmonic's period, in [-P/2, P/2)."""
        period = segment_deg / k
        ph: FloatArray = np.arctan2(-self.coef[..., 2 * k], self.coef[..., 2 * k - 1])
        ph = ph * period / (2 * np.pi)
        return (ph + period / 2.0) % period - period / 2.0


def _basis(alpha: np.ndarray, D: float, K: int) -> np.ndarray:
    """(len(alpha), 1 + 2K) basis [1, cos(k w a), sin(k w a)] with w = 2 pi / D."""
    th = (2.0 * np.pi / D) * np.mod(alpha, D)
    out = np.empty((alpha.size, 1 + 2 * K))
    out[:, 0] = 1.0
    for k in range(1, K + 1):
        out[:, 2 * k - 1] = np.cos(k * th)
        out[:, 2 * k] = np.sin(k * th)
    return out


def _check_order(alpha: np.ndarray, t: np.ndarray | None) -> np.ndarray:
    if alpha.ndim != 1:
        raise ValueError("alpha must be one-dimensional")
    d = np.diff(alpha)
    if (d.size == 0 and not np.all(np.isfinite(alpha))) or (d.size and not np.all(d > 0)):
        if not np.all(np.isfinite(alpha)):
            raise ValueError("crank angles must be finite (a NaN crank angle cannot be placed)")
        bad = int(np.argmax(~(d > 0)))
        kind = "duplicate" if d[bad] == 0 else "decreasing"
        raise ValueError(f"crank angles must be strictly increasing: {kind} at sample {bad + 1} "
                         f"({alpha[bad]} -> {alpha[bad + 1]} deg CA)")
    if t is not None and t.size > 1:
        dt = np.diff(t)
        if not np.all(dt > 0) and np.all(np.isfinite(t)):
            bad = int(np.argmax(~(dt > 0)))
            raise ValueError(f"sample times must be strictly increasing (sample {bad + 1})")
    return d


def crank_harmonics(alpha: np.ndarray, t: np.ndarray | None, values: np.ndarray, *,
                    segment_deg: float, n_harmonics: int = 3,
                    max_gap_deg: float | None = None, alpha_prev: float | None = None,
                    first_segment: int | None = None) -> tuple[CrankHarmonics, int]:
    """Fit mean and harmonics per complete segment (vectorised; see the module docstring).

    Parameters
    ----------
    alpha : (N,) strictly increasing crank angles [deg CA]; t : (N,) times [s] or None.
    values : (C, N) samples.
    alpha_prev : crank angle of the sample just before ``alpha[0]`` (streaming context), or
        None at the start of a record (the first cell then starts at ``alpha[0]``).
    first_segment : first segment to report (default: the first boundary >= alpha[0]).
    max_gap_deg : largest allowed crank-angle step (default: a step more than 1.5 x the
        smaller of its neighbours is a gap, see :func:`_gap_steps`).

    Returns
    -------
    (harmonics, next_segment): the complete segments, and the number of the first segment
    that is not complete yet (for streaming).
    """
    D = float(segment_deg)
    K = int(n_harmonics)
    alpha = np.asarray(alpha, dtype=float)
    values = np.atleast_2d(np.asarray(values, dtype=float))
    tt = None if t is None else np.asarray(t, dtype=float)
    d = _check_order(alpha, tt)
    N = alpha.size
    C = values.shape[0]
    P = 1 + 2 * K
    if values.shape[1] != N:
        raise ValueError("values must have one column per crank angle")
    j0 = int(math.ceil(alpha[0] / D - 1e-12)) if first_segment is None else int(first_segment)
    empty = CrankHarmonics(np.zeros(0, int), np.zeros(0), np.zeros(0), np.zeros(0),
                           np.zeros((C, 0, P)), np.zeros(0, bool), np.zeros(0, dtype="<U10"))
    if N < 2:
        return empty, j0
    # complete segments: a sample at or beyond the segment end exists
    j_end = int(math.floor(alpha[-1] / D + 1e-12))          # segments j0 .. j_end-1
    S = j_end - j0
    if S <= 0:
        return empty, j0
    h = float(d[0])
    uniform = bool(d.max() - d.min() <= 1e-9 * max(h, 1.0))
    uniform = (uniform and abs(D / h - round(D / h)) < 1e-9 and
               (alpha_prev is None or abs(alpha[0] - alpha_prev - h) <= 1e-9 * max(h, 1.0)))
    seg_start = (j0 + np.arange(S)) * D
    i_first = int(np.searchsorted(alpha, j0 * D - 1e-9 * D))
    if uniform and i_first == 0 and alpha_prev is None and abs(alpha[0] - j0 * D) > 1e-9:
        uniform = False          # record starts inside a cell: let the general path clip it
    if uniform:
        coef, status = _uniform(alpha, values, j0, S, D, K, h, i_first)
    else:
        coef, status = _general(alpha, values, j0, S, D, K, alpha_prev)
    m = int(round(D / h)) if uniform else 0
    if tt is None:
        t_start = t_end = np.full(S, np.nan)
    elif uniform and abs(alpha[i_first] - j0 * D) <= 1e-9 * D and \
            i_first + S * m < N:
        tb = tt[i_first:i_first + S * m + 1:m]          # boundaries fall on samples
        t_start, t_end = tb[:-1], tb[1:]
    else:
        t_start = np.interp(seg_start, alpha, tt)
        t_end = np.interp(seg_start + D, alpha, tt)
    # crank-angle gaps (the step from the context sample counts too)
    a_all = alpha if alpha_prev is None else np.concatenate([[alpha_prev], alpha])
    d_all = d if alpha_prev is None else np.concatenate([[alpha[0] - alpha_prev], d])
    if not uniform or max_gap_deg is not None:
        for i in np.nonzero(_gap_steps(d_all, max_gap_deg))[0]:
            a_lo, a_hi = a_all[i], a_all[i + 1]
            js = np.arange(int(math.floor(a_lo / D)), int(math.floor(a_hi / D)) + 1) - j0
            status[js[(js >= 0) & (js < S)]] = "gap"
    bad_num = ~np.all(np.isfinite(coef), axis=(0, 2))
    status[(status == "ok") & bad_num] = "nan"
    valid = status == "ok"
    coef[:, ~valid, :] = np.nan
    out = CrankHarmonics(index=j0 + np.arange(S), alpha_start=seg_start, t_start=t_start,
                         t_end=t_end, coef=coef, valid=valid, status=status)
    return out, j_end


# (samples per segment, D, K, first offset, step, half first weight) -> (w phi, G^-1)
_CacheKey = tuple[int, float, int, float, float, bool]
_UNIFORM_CACHE: dict[_CacheKey, tuple[FloatArray, FloatArray]] = {}


def _gap_steps(d: FloatArray, max_gap_deg: float | None) -> BoolArray:
    """Mask of crank-angle steps that are gaps.

    With ``max_gap_deg`` the rule is absolute. Otherwise a step is a gap when it is more than
    1.5 times the smaller of its two neighbouring steps: one missing sample of a uniform grid
    doubles a step, while sampling that is only smoothly non-uniform (equidistant in time
    during a speed ramp) changes from step to step by far less.
    """
    gap: BoolArray
    if max_gap_deg is not None:
        gap = d > float(max_gap_deg)
    elif d.size < 2:
        gap = np.zeros(d.size, bool)
    else:
        left = np.concatenate([[np.inf], d[:-1]])
        right = np.concatenate([d[1:], [np.inf]])
        gap = d > 1.5 * np.minimum(left, right)
    return gap


def _uniform(alpha: FloatArray, values: FloatArray, j0: int, S: int, D: float, K: int, h: float,
             i_first: int) -> tuple[FloatArray, StrArray]:
    """Uniform grid: one weight vector and one (diagonal-ish) Gram matrix for all segments."""
    m = int(round(D / h))
    s0 = j0 * D
    a_loc = alpha[i_first:i_first + m + 1]
    lo = np.maximum(np.concatenate([[a_loc[0] - h / 2], (a_loc[:-1] + a_loc[1:]) / 2]), s0)
    hi = np.minimum(np.concatenate([(a_loc[:-1] + a_loc[1:]) / 2, [a_loc[-1] + h / 2]]), s0 + D)
    w = np.maximum(hi - lo, 0.0)
    if i_first == 0 and abs(alpha[0] - s0) <= 1e-9 * D:
        w[0] = h / 2.0
    key = (m, D, K, round(float(a_loc[0] - s0), 9), round(float(h), 12), bool(w[0] == h / 2.0))
    cached = _UNIFORM_CACHE.get(key)
    if cached is None:
        phi = _basis(a_loc, D, K)
        wphi = w[:, None] * phi
        Ginv = np.linalg.inv(phi.T @ wphi)
        if len(_UNIFORM_CACHE) > 64:
            _UNIFORM_CACHE.clear()
        _UNIFORM_CACHE[key] = (wphi, Ginv)
    else:
        wphi, Ginv = cached
    C = values.shape[0]
    g = np.empty((C, S, wphi.shape[1]))
    for c in range(C):
        # a contiguous row reshapes without a copy: one BLAS product per channel
        g[c] = values[c, i_first:i_first + S * m].reshape(S, m) @ wphi[:m]
    tail = values[:, i_first + m: i_first + (S + 1) * m: m]
    if tail.shape[1] < S:   # last segment ends exactly on the last sample
        tail = np.concatenate([tail, values[:, -1:]], axis=1)[:, :S]
    g += tail[:, :, None] * wphi[m][None, None, :]
    coef = g @ Ginv.T
    status = np.full(S, "ok", dtype="<U10")
    return coef, status


def _general(alpha: FloatArray, values: FloatArray, j0: int, S: int, D: float, K: int,
             alpha_prev: float | None) -> tuple[FloatArray, StrArray]:
    """Any sampling: clipped cells, contributions split at boundaries, batched 2K+1 solves."""
    N = alpha.size
    P = 1 + 2 * K
    mid = (alpha[:-1] + alpha[1:]) / 2.0
    first_lo = alpha[0] if alpha_prev is None else (alpha_prev + alpha[0]) / 2.0
    lo = np.concatenate([[first_lo], mid])
    hi = np.concatenate([mid, [alpha[-1]]])
    seg_lo = np.floor(lo / D).astype(np.int64)
    seg_hi = np.floor(hi / D).astype(np.int64)
    # a cell may touch at most two segments for valid data; longer cells are gaps anyway
    cut = np.minimum(hi, (seg_lo + 1) * D)
    idx = np.concatenate([np.arange(N), np.arange(N)])
    seg = np.concatenate([seg_lo, seg_hi]) - j0
    w = np.concatenate([cut - lo, np.where(seg_hi > seg_lo, hi - np.maximum(lo, seg_hi * D),
                                           0.0)])
    keep = (w > 0) & (seg >= 0) & (seg < S)
    idx, seg, w = idx[keep], seg[keep], w[keep]
    phi = _basis(alpha[idx], D, K)
    wphi = w[:, None] * phi
    G = np.zeros((S, P, P))
    for a in range(P):
        for b in range(a, P):
            G[:, a, b] = np.bincount(seg, weights=wphi[:, a] * phi[:, b], minlength=S)
            G[:, b, a] = G[:, a, b]
    C = values.shape[0]
    g = np.zeros((C, S, P))
    x = values[:, idx]
    for a in range(P):
        for c in range(C):
            g[c, :, a] = np.bincount(seg, weights=wphi[:, a] * x[c], minlength=S)
    cover = np.bincount(seg, weights=w, minlength=S)
    count = np.bincount(seg, minlength=S)
    status = np.full(S, "ok", dtype="<U10")
    status[np.abs(cover - D) > 1e-9 * D] = "incomplete"
    status[count < P] = "incomplete"
    ok = status == "ok"
    coef = np.full((C, S, P), np.nan)
    if np.any(ok):
        Gok = G[ok]
        cond_ok = np.linalg.cond(Gok) < 1e10
        sol = np.full((C, int(ok.sum()), P), np.nan)
        if np.any(cond_ok):
            rhs = np.moveaxis(g[:, ok][:, cond_ok], 0, -1)            # (s, P, C)
            sol_ok = np.linalg.solve(Gok[cond_ok], rhs)             # (s, P, C)
            sol[:, cond_ok] = np.moveaxis(sol_ok, -1, 0)
        coef[:, ok] = sol
        st = status[ok]
        st[~cond_ok] = "incomplete"
        status[ok] = st
    return coef, status


# ----------------------------------------------------------------------------- features
def _features_from(h: CrankHarmonics, channels: tuple[str, ...], *, plant: str, D: float,
                   V_D: float, R: float) -> tuple[tuple[str, ...], tuple[str, ...], np.ndarray]:
    ci = {c: i for i, c in enumerate(channels)}
    mean = h.coef[:, :, 0]
    amp = h.amplitude(1)
    ph = h.phase_deg(1, D)
    n = mean[ci["n"]]
    p2 = mean[ci["p2"]]
    T2 = mean[ci["T2"]]
    maf = mean[ci["maf"]]
    rho2 = p2 / (R * T2)
    with np.errstate(divide="ignore", invalid="ignore"):
        eta = (maf / 3600.0) / (0.5 * n / 60.0 * V_D * rho2)
    cols = [n, rho2, p2, T2, maf, amp[ci["maf"]], ph[ci["maf"]], amp[ci["p2"]], ph[ci["p2"]],
            eta]
    names = list(FEATURE_NAMES)
    units = list(FEATURE_UNITS)
    for a in ACTUATOR_CHANNELS:
        if a in ci:
            cols.append(mean[ci[a]])
            names.append(a)
            units.append(ACTUATOR_UNITS[a])
    vals = np.stack(cols, axis=1) if cols else np.zeros((h.index.size, 0))
    vals[~h.valid] = np.nan
    return tuple(names), tuple(units), vals


def _check_units(block: SampleBlock) -> None:
    if block.alpha.size != block.t.size:
        raise ValueError("the block has no crank angles: crank-synchronous features need alpha")
    for name, unit in REQUIRED.items():
        if name not in block.channels:
            raise ValueError(f"channel {name!r} [{unit}] missing (has {block.channels})")
        got = block.units[block.channels.index(name)]
        if got != unit:
            raise ValueError(f"channel {name!r} must be in {unit!r}, got {got!r}")


@dataclass(frozen=True)
class SegmentTable:
    """Features of many segments as arrays (the fast form of a list of FeatureVector)."""

    plant: str
    index: np.ndarray
    t_start: np.ndarray
    t_end: np.ndarray
    alpha_start: np.ndarray
    valid: np.ndarray
    status: np.ndarray
    names: tuple[str, ...]
    units: tuple[str, ...]
    values: np.ndarray      # (S, F)

    def column(self, name: str) -> np.ndarray:
        return self.values[:, self.names.index(name)]

    def to_features(self) -> list[FeatureVector]:
        return [FeatureVector(plant=self.plant, index=int(self.index[i]),
                              t_start=float(self.t_start[i]), t_end=float(self.t_end[i]),
                              alpha_start=float(self.alpha_start[i]), valid=bool(self.valid[i]),
                              status=str(self.status[i]), names=self.names, units=self.units,
                              values=self.values[i].copy())
                for i in range(self.index.size)]


class CrankSegmenter:
    """Streaming segmenter: keeps the unfinished segment between blocks.

    Parameters
    ----------
    segment_deg : segment length [deg CA]: one firing, 720 / cylinders for a four-stroke.
    V_D : displacement [m^3]; R : gas constant [J/(kg K)] for rho2 and eta_v.
    The engine's wing gives all three (its parameters are their one source); the core
    assumes no engine.
    n_harmonics : harmonics fitted jointly (1..K) to keep higher orders out of the first.
    max_gap_deg : largest crank-angle step that is not a gap (default: relative rule, a step
        more than 1.5 x the smaller neighbouring step is a gap).
    rate_channels, rate_lag, rate_order : channels whose segment means also get a rate
        feature ``<channel>_rate`` [unit/s] over ``rate_lag`` + 1 consecutive valid segments
        (NaN until that many follow an invalid segment or a reset), e.g. to compensate a slow
        sensor's lag (``x + tau dx/dt``): the backward difference (``rate_order`` 1) or the
        end-point slope of a least-squares quadratic (2; see :func:`segment_rates`). A
        channel of ``rate_optional`` the blocks lack gets no rate; any other missing one
        raises ValueError.

    ``push(block)`` returns the feature vectors of the segments completed by the block.
    A block whose crank angles are not strictly increasing, or that starts at or before the
    previous block's last crank angle, raises ValueError and leaves the state unchanged.
    """

    def __init__(self, *, segment_deg: float, V_D: float, R: float, n_harmonics: int = 3,
                 max_gap_deg: float | None = None, rate_channels: Sequence[str] = (),
                 rate_lag: int = 8, rate_order: int = 1,
                 rate_optional: Sequence[str] = ()) -> None:
        if not (np.isfinite(segment_deg) and segment_deg > 0):
            raise ValueError("segment_deg must be > 0")
        if not (V_D > 0 and R > 0):
            raise ValueError("V_D and R must be > 0")
        if not 1 <= int(n_harmonics) <= 16:
            raise ValueError("n_harmonics must be within 1..16")
        self.D = float(segment_deg)
        self.V_D = float(V_D)
        self.R = float(R)
        self.K = int(n_harmonics)
        self.max_gap = max_gap_deg
        self.rate_channels = tuple(rate_channels)
        self.rate_optional = frozenset(rate_optional)
        if int(rate_lag) < 1:
            raise ValueError("rate_lag must be >= 1")
        self.rate_lag = int(rate_lag)
        self.rate_order = int(rate_order)
        _check_rate_order(self.rate_lag, self.rate_order)
        self.reset()

    def reset(self) -> None:
        self._alpha = np.zeros(0)
        self._t = np.zeros(0)
        self._vals: np.ndarray | None = None
        self._channels: tuple[str, ...] | None = None
        self._units: tuple[str, ...] | None = None
        self._prev: float | None = None
        self._next_seg: int | None = None
        self._plant = ""
        # the last rate_lag segments (index, end time, valid, means of the rate channels)
        self._rate_hist: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None

    def push_table(self, block: SampleBlock) -> SegmentTable:
        """Like :meth:`push` but returns a :class:`SegmentTable` (no per-segment objects)."""
        _check_units(block)
        alpha = np.asarray(block.alpha, dtype=float)
        t = np.asarray(block.t, dtype=float)
        _check_order(alpha, t)
        if self._channels is not None and block.channels != self._channels:
            raise ValueError("channels changed between blocks; reset() the segmenter first")
        last = self._alpha[-1] if self._alpha.size else self._prev
        if last is not None and alpha.size and not alpha[0] > last:
            raise ValueError(f"block starts at {alpha[0]} deg CA, not after the previous "
                             f"sample at {last} deg CA (unsorted or duplicate crank angles)")
        if self._channels is None:
            self._channels, self._units, self._plant = block.channels, block.units, block.plant
        A = np.concatenate([self._alpha, alpha])
        T = np.concatenate([self._t, t])
        V = block.values if self._vals is None else np.concatenate([self._vals, block.values],
                                                                    axis=1)
        h: CrankHarmonics | None = None
        nxt: int | None = self._next_seg
        if A.size >= 2:
            h, nxt = crank_harmonics(A, T, V, segment_deg=self.D, n_harmonics=self.K,
                                     max_gap_deg=self.max_gap, alpha_prev=self._prev,
                                     first_segment=self._next_seg)
        if nxt is None:
            nxt = int(math.ceil(A[0] / self.D - 1e-12))
        # keep the samples of the unfinished segment (and the one before, for its cell)
        i_keep = int(np.searchsorted(A, nxt * self.D - 1e-9 * self.D))
        i_keep = max(i_keep - 1, 0)
        if i_keep > 0:
            self._prev = float(A[i_keep - 1])
        self._alpha, self._t, self._vals = A[i_keep:], T[i_keep:], V[:, i_keep:]
        self._next_seg = nxt
        if h is None or h.index.size == 0:
            return _empty_table(self._plant)
        names, units, vals = _features_from(h, self._channels, plant=self._plant, D=self.D,
                                            V_D=self.V_D, R=self.R)
        if self.rate_channels:
            names, units, vals = self._with_rates(h, names, units, vals)
        return SegmentTable(plant=self._plant, index=h.index, t_start=h.t_start, t_end=h.t_end,
                            alpha_start=h.alpha_start, valid=h.valid, status=h.status,
                            names=names, units=units, values=vals)

    def _with_rates(self, h: CrankHarmonics, names: tuple[str, ...], units: tuple[str, ...],
                    vals: np.ndarray) -> tuple[tuple[str, ...], tuple[str, ...], np.ndarray]:
        """Append the rate features of this table's segments (history carried over)."""
        missing = [c for c in self.rate_channels
                   if c not in names and c not in self.rate_optional]
        if missing:
            raise ValueError(f"rate channels {missing} are not features of these blocks")
        have = [c for c in self.rate_channels if c in names]
        if not have:
            return names, units, vals
        cols = [names.index(c) for c in have]
        new = (np.asarray(h.index), np.asarray(h.t_end, dtype=float),
               np.asarray(h.valid, dtype=bool), vals[:, cols])
        old = self._rate_hist
        idx, t, ok, x = new if old is None else tuple(
            np.concatenate([a, b]) for a, b in zip(old, new))
        rates = segment_rates(idx, t, ok, x, self.rate_lag,
                              self.rate_order)[idx.size - new[0].size:]
        keep = max(idx.size - self.rate_lag, 0)
        self._rate_hist = (idx[keep:], t[keep:], ok[keep:], x[keep:])
        rate_units = tuple(f"{units[j]}/s" for j in cols)
        return (names + tuple(f"{c}_rate" for c in have), units + rate_units,
                np.column_stack([vals, rates]))

    def push(self, block: SampleBlock) -> list[FeatureVector]:
        """Feature vectors of the segments completed by this block (may be empty)."""
        return self.push_table(block).to_features()


def segment_rates(index: np.ndarray, t: np.ndarray, valid: np.ndarray, x: np.ndarray,
                  lag: int, order: int = 1) -> np.ndarray:
    """Rates of change of segment means over the ``lag + 1`` consecutive segments up to k
    (rows (N,) or (N, m)); NaN where those are not consecutive indices, all valid and finite.

    ``order`` 1: the backward difference ``(x[k] - x[k-lag]) / (t[k] - t[k-lag])``, the slope
    at the window's middle (it lags by half the window); 2: the slope at ``t[k]`` of the
    quadratic fitted by least squares to the window (a Savitzky-Golay end-point derivative
    on the segments' own times): no lag for a signal that bends within the window, such as
    a slow sensor's step response, at somewhat more noise (``lag >= 2``).
    """
    _check_rate_order(lag, order)
    X = np.asarray(x, dtype=float).reshape(len(index), -1)
    n = X.shape[0]
    out = np.full(X.shape, np.nan)
    if n <= lag:
        return out.reshape(np.shape(x))
    T = np.asarray(t, dtype=float)
    k = np.arange(n)
    bad = ~np.asarray(valid, dtype=bool) | ~np.all(np.isfinite(X), axis=1)
    brk = np.concatenate([[True], np.diff(np.asarray(index)) != 1])
    last_bad = np.maximum.accumulate(np.where(bad, k, -1))
    run_start = np.maximum.accumulate(np.where(brk, k, 0))
    j = k - lag
    ok = (j >= 0) & (last_bad < np.maximum(j, 0)) & (run_start <= j)
    ok &= T[k] > T[np.maximum(j, 0)]
    rows = np.flatnonzero(ok)
    span = (T[rows] - T[rows - lag])[:, None]
    if order == 1:
        out[rows] = (X[rows] - X[rows - lag]) / span
        return out.reshape(np.shape(x))
    win = rows[:, None] - np.arange(lag, -1, -1)            # (R, lag + 1), oldest first
    s = (T[win] - T[rows][:, None]) / span                  # in -1 .. 0
    P = np.stack([np.ones_like(s), s, s * s], axis=2)      # (R, lag + 1, 3)
    coef = np.linalg.solve(np.einsum("rwi,rwj->rij", P, P),
                           np.einsum("rwi,rwc->ric", P, X[win]))
    out[rows] = coef[:, 1, :] / span
    return out.reshape(np.shape(x))


def _check_rate_order(lag: int, order: int) -> None:
    if order not in (1, 2) or (order == 2 and lag < 2):
        raise ValueError("rate order must be 1, or 2 with rate_lag >= 2")


def _empty_table(plant: str) -> SegmentTable:
    z = np.zeros(0)
    return SegmentTable(plant=plant, index=np.zeros(0, int), t_start=z, t_end=z, alpha_start=z,
                        valid=np.zeros(0, bool), status=np.zeros(0, dtype="<U10"),
                        names=FEATURE_NAMES, units=FEATURE_UNITS,
                        values=np.zeros((0, len(FEATURE_NAMES))))


def segment_table(block: SampleBlock, *, segment_deg: float, V_D: float, R: float,
                  n_harmonics: int = 3,
                  max_gap_deg: float | None = None) -> SegmentTable:
    """Features of all complete segments of one block, as arrays."""
    seg = CrankSegmenter(segment_deg=segment_deg, V_D=V_D, R=R, n_harmonics=n_harmonics,
                         max_gap_deg=max_gap_deg)
    return seg.push_table(block)


def segment_features(block: SampleBlock, *, segment_deg: float, V_D: float, R: float,
                     n_harmonics: int = 3,
                     max_gap_deg: float | None = None) -> list[FeatureVector]:
    """Feature vectors of all complete segments of one block (see the module docstring)."""
    return segment_table(block, segment_deg=segment_deg, V_D=V_D, R=R,
                         n_harmonics=n_harmonics, max_gap_deg=max_gap_deg).to_features()


def join_blocks(blocks: Sequence[SampleBlock]) -> SampleBlock:
    """Consecutive sample blocks of one stream as one block (offline segmentation in one pass).

    The blocks must share plant, channels and units; the result carries the first index."""
    if not blocks:
        raise ValueError("no sample blocks to join")
    b0 = blocks[0]
    for b in blocks[1:]:
        if (b.plant, b.channels, b.units) != (b0.plant, b0.channels, b0.units):
            raise ValueError(f"block {b.index}: channels or units differ from block {b0.index}")
    return SampleBlock(plant=b0.plant, index=b0.index,
                       t=np.concatenate([b.t for b in blocks]),
                       alpha=np.concatenate([b.alpha for b in blocks]),
                       channels=b0.channels, units=b0.units,
                       values=np.concatenate([b.values for b in blocks], axis=1))
