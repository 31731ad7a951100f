"""Measured data for the discrepancy analysis: CSV (+ mapping) and bag loading, validation.

A measured record is a set of time-sampled signals on one time base. Sources:

* a CSV with our own column names (those of ``fdi-ros simulate --csv``: ``t``, ``alpha``, ``n``,
  ``p2``, ``T2``, ``maf``, actuator inputs ...);
* any CSV plus a **mapping** YAML that renames columns and converts units::

      time: {column: time, unit: s}
      signals:
        p_im: {column: intake_manifold_pressure, unit: Pa}
        n: {column: engine_speed, unit: rpm, scale: 9.5492966}   # rad/s -> rpm
      keep_unmapped: true      # unmapped columns stay as candidate explanations

  ``value = scale * raw + offset``; the unit given is the unit *after* conversion;
* a rosbag2 directory holding ``/fdi/sensor_block`` messages (see :mod:`fdi_ros.bag`).

Validation never guesses: a non-numeric cell, a time column that is not strictly increasing,
or a mapped column that is absent raises :class:`ValueError` with the row/column; NaN cells
(empty fields, ``nan``) are kept as NaN and *masked* (see :attr:`Measured.valid`); gaps longer
than ``max_gap_s`` split the record into segments (:attr:`Measured.segment`) so that filters
and derivatives never run across a gap.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

# Our own column names and their units (as written by ``fdi-ros simulate --csv``).
OWN_UNITS = {
    "t": "s", "alpha": "deg CA", "n": "rpm", "p2": "Pa", "T2": "K", "maf": "kg/h",
    "p_amb": "Pa", "T_amb": "K",
}


@dataclass(frozen=True)
class Measured:
    """One measured record on a single time base.

    Attributes
    ----------
    t : (N,) sample times [s], strictly increasing.
    signals : name -> (N,) values in the unit of ``units[name]``; NaN = missing sample.
    units : name -> unit string.
    alpha : (N,) unwrapped crank angle [deg CA], or ``None`` for mean-value data.
    segment : (N,) int segment id; it increments after every gap longer than ``max_gap_s``.
    source : where the data came from (path), for reports.
    mapped : names that came through the mapping (or our own known column names); the other
        signals are unmapped columns, kept as candidate explanations.
    """

    t: np.ndarray
    signals: dict[str, np.ndarray]
    units: dict[str, str]
    alpha: np.ndarray | None = None
    segment: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    source: str = ""
    mapped: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        n = self.t.shape[0]
        if n < 2:
            raise ValueError(f"{self.source or 'measured data'}: needs at least 2 samples")
        if not np.all(np.isfinite(self.t)):
            raise ValueError(f"{self.source}: time column has missing or non-finite values")
        if np.any(np.diff(self.t) <= 0):
            k = int(np.argmax(np.diff(self.t) <= 0))
            raise ValueError(f"{self.source}: time is not strictly increasing at sample {k + 1} "
                             f"(t = {self.t[k]:g} then {self.t[k + 1]:g} s)")
        for name, v in self.signals.items():
            if v.shape != (n,):
                raise ValueError(f"signal {name!r} has shape {v.shape}, expected ({n},)")
        if self.alpha is not None and self.alpha.shape != (n,):
            raise ValueError("alpha must have one value per sample")
        if self.segment.shape != (n,):
            object.__setattr__(self, "segment", np.zeros(n, dtype=int))

    @property
    def n_samples(self) -> int:
        return int(self.t.shape[0])

    @property
    def dt(self) -> float:
        """Median sample step [s]."""
        return float(np.median(np.diff(self.t)))

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self.signals[name]
        except KeyError:
            raise KeyError(f"signal {name!r} not in measured data (has {sorted(self.signals)})"
                           ) from None

    def valid(self, names: tuple[str, ...] | list[str]) -> np.ndarray:
        """Mask of samples where every signal in ``names`` is finite."""
        ok = np.ones(self.n_samples, dtype=bool)
        for name in names:
            ok &= np.isfinite(self[name])
        return ok

    def skipped(self, names: tuple[str, ...] | list[str]) -> dict[str, Any]:
        """What an analysis of ``names`` leaves out: samples where any of them is missing or
        non-finite, in all and per signal (``{"samples", "of", "by_signal"}``)."""
        by_signal = {n: int(np.sum(~np.isfinite(self[n]))) for n in names}
        return {"samples": int(np.sum(~self.valid(names))), "of": self.n_samples,
                "by_signal": {n: k for n, k in by_signal.items() if k}}

    def window(self, t0: float, t1: float) -> Measured:
        """The samples with ``t0 <= t < t1`` as a new record."""
        sel = (self.t >= t0) & (self.t < t1)
        if sel.sum() < 2:
            raise ValueError(f"window [{t0}, {t1}) s holds fewer than 2 samples")
        return Measured(t=self.t[sel], signals={k: v[sel] for k, v in self.signals.items()},
                        units=dict(self.units),
                        alpha=None if self.alpha is None else self.alpha[sel],
                        segment=self.segment[sel], source=f"{self.source}[{t0:g}:{t1:g}]",
                        mapped=self.mapped)

    @property
    def unmapped(self) -> tuple[str, ...]:
        return tuple(k for k in self.signals if k not in self.mapped)


def segments_from_gaps(t: np.ndarray, max_gap_s: float) -> np.ndarray:
    """Segment id per sample: a new segment starts after each step longer than ``max_gap_s``."""
    seg = np.zeros(t.shape[0], dtype=int)
    seg[1:] = np.cumsum(np.diff(t) > max_gap_s)
    return seg


@dataclass(frozen=True)
class SignalMap:
    """One mapped signal: ``value = scale * raw[column] + offset`` in ``unit``."""

    column: str
    unit: str = ""
    scale: float = 1.0
    offset: float = 0.0


@dataclass(frozen=True)
class Mapping:
    """Column mapping of a CSV source (see the module docstring for the YAML form)."""

    time: SignalMap
    signals: dict[str, SignalMap]
    alpha: SignalMap | None = None
    keep_unmapped: bool = True
    max_gap_s: float | None = None
    name: str = ""

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, name: str = "") -> Mapping:
        if not isinstance(d, dict):
            raise ValueError(f"mapping {name}: expected a mapping at top level")
        unknown = set(d) - {"time", "signals", "alpha", "keep_unmapped", "max_gap_s",
                            "description", "source"}
        if unknown:
            raise ValueError(f"mapping {name}: unknown keys {sorted(unknown)}")
        if "time" not in d or "signals" not in d:
            raise ValueError(f"mapping {name}: needs 'time' and 'signals'")

        def one(key: str, v: object) -> SignalMap:
            if isinstance(v, str):
                return SignalMap(column=v)
            if not isinstance(v, dict) or "column" not in v:
                raise ValueError(f"mapping {name}: entry {key!r} needs a 'column'")
            bad = set(v) - {"column", "unit", "scale", "offset", "description"}
            if bad:
                raise ValueError(f"mapping {name}: entry {key!r} has unknown keys {sorted(bad)}")
            sm = SignalMap(column=str(v["column"]), unit=str(v.get("unit", "")),
                           scale=float(v.get("scale", 1.0)), offset=float(v.get("offset", 0.0)))
            if not (math.isfinite(sm.scale) and sm.scale != 0 and math.isfinite(sm.offset)):
                raise ValueError(f"mapping {name}: entry {key!r} needs finite non-zero scale")
            return sm

        sig = d["signals"]
        if not isinstance(sig, dict) or not sig:
            raise ValueError(f"mapping {name}: 'signals' must be a non-empty mapping")
        gap = d.get("max_gap_s")
        return cls(time=one("time", d["time"]),
                   signals={str(k): one(str(k), v) for k, v in sig.items()},
                   alpha=one("alpha", d["alpha"]) if d.get("alpha") else None,
                   keep_unmapped=bool(d.get("keep_unmapped", True)),
                   max_gap_s=None if gap is None else float(gap), name=name)


def load_mapping(path: str | Path) -> Mapping:
    """Read a mapping YAML file."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mapping file {path} not found")
    with open(path) as f:
        try:
            d = yaml.safe_load(f)
        except yaml.YAMLError as exc:
            raise ValueError(f"mapping file {path}: not valid YAML ({exc})") from None
    return Mapping.from_dict(d, name=str(path))


def _read_csv_columns(path: Path) -> dict[str, np.ndarray]:
    """All columns of a numeric CSV with a header row; empty/'nan' cells become NaN.

    A clean file (every cell a number or 'nan') is parsed by numpy's C reader (a 10-minute
    1 deg CA record, 7 million rows: 14 s instead of about a minute); anything else (empty
    cells, 'na', ragged rows, text) by the row-by-row reader below, which says where."""
    with open(path, newline="") as f:
        reader = csv.reader(f)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise ValueError(f"{path}: empty file") from None
        if len(set(header)) != len(header) or any(h == "" for h in header):
            raise ValueError(f"{path}: header has empty or duplicate column names: {header}")
    arr: np.ndarray | None
    try:
        arr = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, dtype=float, comments=None)
    except ValueError:
        arr = None
    if arr is not None and arr.shape[0] >= 2 and arr.shape[1] == len(header):
        return {h: arr[:, i] for i, h in enumerate(header)}
    return _read_csv_rows(path, header)


def _read_csv_rows(path: Path, header: list[str]) -> dict[str, np.ndarray]:
    """:func:`_read_csv_columns` row by row, with the line and column of a bad cell."""
    with open(path, newline="") as f:
        reader = csv.reader(f)
        next(reader)
        rows: list[list[float]] = []
        for lineno, row in enumerate(reader, start=2):
            if not row or all(c.strip() == "" for c in row):
                continue
            if len(row) != len(header):
                raise ValueError(f"{path}: line {lineno} has {len(row)} fields, "
                                 f"header has {len(header)}")
            vals = []
            for col, cell in zip(header, row):
                cell = cell.strip()
                if cell == "" or cell.lower() in ("nan", "na", "null"):
                    vals.append(math.nan)
                    continue
                try:
                    vals.append(float(cell))
                except ValueError:
                    raise ValueError(f"{path}: line {lineno}, column {col!r}: "
                                     f"{cell!r} is not a number") from None
            rows.append(vals)
    if len(rows) < 2:
        raise ValueError(f"{path}: fewer than 2 data rows")
    arr = np.asarray(rows, dtype=float)
    return {h: arr[:, i] for i, h in enumerate(header)}


def load_csv(path: str | Path, mapping: Mapping | str | Path | None = None, *,
             max_gap_s: float | None = None) -> Measured:
    """Load a measured CSV, optionally through a mapping.

    Without a mapping the columns must use our names (``t`` is the time column; ``alpha``, if
    present, the crank angle). With a mapping, mapped columns are renamed and converted and the
    remaining columns are kept (unless ``keep_unmapped: false``) as candidate explanations.

    Parameters
    ----------
    max_gap_s : a step longer than this starts a new segment; default 5 median steps.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"measured CSV {path} not found")
    cols = _read_csv_columns(path)
    if mapping is not None and not isinstance(mapping, Mapping):
        mapping = load_mapping(mapping)
    units: dict[str, str] = {}
    signals: dict[str, np.ndarray] = {}
    alpha = None
    if mapping is None:
        if "t" not in cols:
            raise ValueError(f"{path}: no 't' column; give a mapping file for other column "
                             f"names (columns: {sorted(cols)})")
        t = cols.pop("t")
        if "alpha" in cols:
            alpha = cols.pop("alpha")
        for k, v in cols.items():
            signals[k] = v
            units[k] = OWN_UNITS.get(k, "")
        mapped = tuple(k for k in signals if k in OWN_UNITS)
        gap = max_gap_s
    else:
        used = set()

        def get(sm: SignalMap, key: str) -> np.ndarray:
            if sm.column not in cols:
                raise ValueError(f"{path}: mapping {mapping.name} wants column {sm.column!r} "
                                 f"for {key!r}; columns are {sorted(cols)}")
            used.add(sm.column)
            return sm.scale * cols[sm.column] + sm.offset

        t = get(mapping.time, "time")
        if mapping.alpha is not None:
            alpha = get(mapping.alpha, "alpha")
        for k, sm in mapping.signals.items():
            signals[k] = get(sm, k)
            units[k] = sm.unit
        mapped = tuple(signals)
        if mapping.keep_unmapped:
            for c, v in cols.items():
                if c not in used and c not in signals:
                    signals[c] = v
                    units[c] = ""
        gap = max_gap_s if max_gap_s is not None else mapping.max_gap_s
    if not np.all(np.isfinite(t)):
        row = int(np.argmin(np.isfinite(t)))
        raise ValueError(f"{path}: time missing at data row {row + 1}")
    steps = np.diff(t)
    if np.any(steps <= 0):
        row = int(np.argmax(steps <= 0))
        raise ValueError(f"{path}: time is not strictly increasing at data row {row + 2} "
                         f"(t = {t[row]:g} then {t[row + 1]:g} s)")
    if gap is None:
        gap = 5.0 * float(np.median(steps))
    return Measured(t=t, signals=signals, units=units, alpha=alpha,
                    segment=segments_from_gaps(t, gap), source=str(path), mapped=mapped)


def load_bag(path: str | Path, *, topic: str = "/fdi/sensor_block",
             max_gap_s: float | None = None) -> Measured:
    """Concatenate the sensor blocks of a rosbag2 directory into one measured record."""
    from fdi_ros import bag

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"bag {path} not found")
    blocks = list(bag.read_blocks(path, topic=topic))
    if not blocks:
        raise ValueError(f"bag {path}: no sensor blocks")
    chans = blocks[0].channels
    for b in blocks:
        if b.channels != chans:
            raise ValueError(f"bag {path}: block {b.index} has channels {b.channels}, "
                             f"first block has {chans}")
    t = np.concatenate([b.t for b in blocks])
    vals = np.concatenate([b.values for b in blocks], axis=1)
    has_alpha = all(b.alpha.size for b in blocks)
    alpha = np.concatenate([b.alpha for b in blocks]) if has_alpha else None
    order = np.argsort(t, kind="stable")
    t, vals = t[order], vals[:, order]
    keep = np.concatenate([[True], np.diff(t) > 0])  # duplicated stamps: keep the first
    t, vals = t[keep], vals[:, keep]
    if alpha is not None:
        alpha = alpha[order][keep]
    signals = {c: vals[i] for i, c in enumerate(chans)}
    units = dict(zip(chans, blocks[0].units))
    gap = max_gap_s if max_gap_s is not None else 5.0 * float(np.median(np.diff(t)))
    return Measured(t=t, signals=signals, units=units, alpha=alpha,
                    segment=segments_from_gaps(t, gap), source=str(path), mapped=tuple(chans))


def load_measured(path: str | Path, mapping: str | Path | None = None) -> Measured:
    """A CSV file (with optional mapping) or a bag directory."""
    path = Path(path)
    if path.is_dir():
        return load_bag(path)
    if not path.exists():
        raise FileNotFoundError(f"measured data {path} not found")
    if path.suffix.lower() != ".csv":
        raise ValueError(f"{path}: measured data must be a .csv file or a bag directory")
    return load_csv(path, mapping)


def segment_means(data: Measured, *, segment_deg: float = 180.0) -> Measured:
    """Average every signal over complete crank-angle segments (180 deg CA for 4 cylinders).

    The mean-value view of crank-resolved data: the pulsation of the cylinders' suction
    (integer orders of the 180 deg CA fundamental) averages out. A segment with a missing
    sample (NaN) gets NaN for that signal; incomplete first/last segments are dropped.
    """
    if data.alpha is None:
        raise ValueError("segment means need crank-angle resolved data (alpha)")
    seg = np.floor((data.alpha - data.alpha[0]) / segment_deg + 1e-9).astype(np.int64)
    # a segment is complete when it spans the whole segment angle at the typical spacing
    counts = np.bincount(seg)
    full = int(np.median(counts[1:-1])) if counts.size > 2 else int(counts.max())
    ok_seg = counts >= full
    ok_seg[0] = ok_seg[-1] = False
    keep = ok_seg[seg]
    s = seg[keep]
    _, inv = np.unique(s, return_inverse=True)
    cnt = np.bincount(inv)

    def mean(x: np.ndarray) -> np.ndarray:
        return np.bincount(inv, weights=x[keep]) / cnt

    t = mean(data.t)
    sig = {k: mean(v) for k, v in data.signals.items()}
    alpha0 = np.bincount(inv, weights=data.alpha[keep]) / cnt
    grp_seg = np.bincount(inv, weights=data.segment[keep].astype(float)) / cnt
    # a segment straddling a gap is not a segment
    seg_id = np.round(grp_seg).astype(int)
    out = Measured(t=t, signals=sig, units=dict(data.units), alpha=None, segment=seg_id,
                   source=f"{data.source} (180 deg CA segment means)", mapped=data.mapped)
    object.__setattr__(out, "segment_alpha", alpha0)
    return out


def decimate_crank(data: Measured, step_deg: float) -> Measured:
    """Every k-th sample so that the crank-angle spacing is about ``step_deg`` (no filter: the
    pulsation orders of interest stay well below the new Nyquist order ``90 / step_deg``)."""
    if data.alpha is None:
        return data
    da = float(np.median(np.diff(data.alpha)))
    k = int(step_deg // da) if da > 0 else 1
    if k <= 1:
        return data
    sel = slice(0, None, k)
    return Measured(t=data.t[sel], signals={n: v[sel] for n, v in data.signals.items()},
                    units=dict(data.units), alpha=data.alpha[sel], segment=data.segment[sel],
                    source=f"{data.source} (every {k}th sample, {k * da:g} deg CA)",
                    mapped=data.mapped)
