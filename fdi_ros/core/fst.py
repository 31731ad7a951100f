"""Fault-symptom tables and isolation by them.

A table maps each fault to its signature: one symptom level per column (``-`` -1, ``o`` 0,
``+`` 1, ``++`` 2). :func:`isolate` compares an observed symptom pattern with the table; a table
file (YAML) names its columns (``symptoms: [...]``) and holds one or more tables
(``tables: {name: {fault: "+,o,o"}}``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

__all__ = ["LEVEL_CODES", "FaultSymptomTable", "isolate", "load_fault_symptom_tables",
           "parse_signature", "signature_string"]

LEVEL_CODES = {"-": -1, "o": 0, "+": 1, "++": 2}
_CODE_OF = {v: k for k, v in LEVEL_CODES.items()}
Opposite = Literal["double", "exclude"]
Keep = Literal["nearest", "all"]


def signature_string(levels: Sequence[int]) -> str:
    """``(1, 0, -1)`` -> ``"+,o,-"``."""
    return ",".join(_CODE_OF[int(v)] for v in levels)


class FaultSymptomTable(dict[str, tuple[int, ...]]):
    """Fault -> signature, with the symptom names of the signature's columns."""

    def __init__(self, columns: Sequence[str],
                 rows: Mapping[str, Sequence[int]] | None = None) -> None:
        self.columns = tuple(columns)
        super().__init__({f: tuple(int(x) for x in s) for f, s in (rows or {}).items()})
        for fault, sig in self.items():
            if len(sig) != len(self.columns):
                raise ValueError(f"signature of {fault} has {len(sig)} symptoms, the table "
                                 f"{len(self.columns)} ({list(self.columns)})")


def _observed(symptom_levels: Sequence[int] | Mapping[str, int],
              columns: Sequence[str] | None) -> NDArray[np.int_]:
    if isinstance(symptom_levels, Mapping):
        if columns is None:
            raise ValueError("symptoms by name need a table with named columns")
        unknown = set(symptom_levels) - set(columns)
        if unknown:
            raise ValueError(f"symptoms {sorted(unknown)} are not columns of the table "
                             f"{list(columns)}")
        return np.array([int(symptom_levels.get(s, 0)) for s in columns])
    return np.asarray(symptom_levels, dtype=int)


def isolate(symptom_levels: Sequence[int] | Mapping[str, int],
            table: Mapping[str, Sequence[int]], *, max_mismatch: int = 0,
            columns: Sequence[str] | None = None, opposite: Opposite = "double",
            keep: Keep = "nearest") -> list[str]:
    """Candidate faults whose table signature matches the symptoms (the one matcher).

    ``symptom_levels`` in the table's column order, or a mapping by symptom name (``columns``,
    default the table's own). No symptom -> no candidate. Otherwise, in this order:

    1. the exact matches;
    2. if there is none, the matches in sign (``+`` == ``++``);
    3. if there is none and ``max_mismatch > 0``, the near matches. The distance of a
       signature is the sum over symptoms of ``|sign(table) - sign(observed)|``: a symptom
       missing or extra counts 1, one of the opposite sign 2. ``opposite="exclude"`` drops
       every signature with a symptom of the opposite sign to an observed one first (it
       contradicts the residuals). ``keep="nearest"``: the faults at the smallest distance,
       if it is at most ``max_mismatch``; ``keep="all"``: every fault within
       ``max_mismatch``.

    The table isolation of the reproductions uses the defaults (``"double"``, ``"nearest"``);
    the live diagnoser asks for the faults the symptoms do not contradict (``"exclude"``,
    ``"all"``), since a fault outside that list cannot explain the residuals.
    """
    if opposite not in ("double", "exclude") or keep not in ("nearest", "all"):
        raise ValueError(f"opposite must be 'double' or 'exclude' and keep 'nearest' or 'all', "
                         f"not {opposite!r}, {keep!r}")
    levels = _observed(symptom_levels, columns or getattr(table, "columns", None))
    obs = np.sign(levels)
    if not obs.any():
        return []
    exact: list[str] = []
    signed: list[str] = []
    dist: dict[str, int] = {}
    for fault, row in table.items():
        sig = np.asarray(row, dtype=int)
        if sig.shape != obs.shape:
            raise ValueError(f"signature of {fault} has {sig.size} symptoms, observed {obs.size}")
        if np.array_equal(sig, levels):
            exact.append(fault)
        elif np.array_equal(np.sign(sig), obs):
            signed.append(fault)
        diff = np.abs(np.sign(sig) - obs)
        if opposite == "exclude" and np.any(diff == 2):
            continue
        dist[fault] = int(np.sum(diff))
    if exact or signed or max_mismatch <= 0:
        return exact or signed
    if keep == "all":
        return [f for f, d in dist.items() if d <= max_mismatch]
    best = min(dist.values(), default=max_mismatch + 1)
    return [f for f, d in dist.items() if d == best] if best <= max_mismatch else []


def isolate_in_sign(symptom_levels: Mapping[str, int], table: FaultSymptomTable,
                    columns: Sequence[str]) -> list[str]:
    """Faults whose signatures have the observed signs on ``columns`` (symptom names; the
    others are not judged): the matcher of a partial signature, where the table's
    intensities, measured with every symptom judged, do not carry over. No symptom among
    ``columns`` -> no candidate."""
    cols = [c for c in columns if c in table.columns]
    obs = [int(np.sign(symptom_levels.get(c, 0))) for c in cols]
    if not any(obs):
        return []
    at = [table.columns.index(c) for c in cols]
    return [f for f, row in table.items() if [int(np.sign(row[j])) for j in at] == obs]


def covering(symptom_levels: Sequence[int], table: Mapping[str, Sequence[int]]) -> list[str]:
    """Faults whose signatures show every observed symptom, in sign (``symptom_levels`` in
    the table's column order): a symptom of the signature that does not show is allowed. A
    table measured at one operating point says which symptoms a fault can produce; elsewhere,
    or at a smaller size, some stay below their thresholds (a stuck-open EGR valve at 4400 rpm
    shows s_eta "++" and none of the pulsation symptoms the table has at 2000 rpm). No
    symptom -> no candidate."""
    obs = np.sign(np.asarray(symptom_levels, dtype=int))
    if not obs.any():
        return []
    on = obs != 0
    return [f for f, row in table.items()
            if np.array_equal(np.sign(np.asarray(row, dtype=int))[on], obs[on])]


def parse_signature(sig: str | Sequence[str | int], n: int) -> tuple[int, ...]:
    """``"+,o,-"`` (or a list of codes / integers) -> levels; ``n`` symptoms expected."""
    if isinstance(sig, str):
        sig = [s.strip() for s in sig.split(",")]
    try:
        out = tuple(LEVEL_CODES[s] if isinstance(s, str) else int(s) for s in sig)
    except KeyError as exc:
        raise ValueError(f"unknown symptom level {exc}; use one of {list(LEVEL_CODES)}") from None
    if len(out) != n or not set(out) <= set(LEVEL_CODES.values()):
        raise ValueError(f"a signature needs {n} levels in {list(LEVEL_CODES)}")
    return out


def load_fault_symptom_tables(path: str | Path, columns: Sequence[str] | None = None
                              ) -> dict[str, FaultSymptomTable]:
    """The tables of a YAML file; ``columns``, if given, must equal the file's ``symptoms:``."""
    from fdi_ros.core.files import read_document

    path = Path(path)
    doc = read_document(path, "fault-symptom table file", fmt="yaml") or {}
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: a fault-symptom table file must be a mapping")
    cols = doc.get("symptoms", columns)
    if not isinstance(cols, list | tuple) or not cols:
        raise ValueError(f"{path}: no 'symptoms' list naming the columns")
    cols = tuple(str(c) for c in cols)
    if columns is not None and cols != tuple(columns):
        raise ValueError(f"{path}: symptom columns must be {list(columns)}, got {list(cols)}")
    tables = doc.get("tables")
    if not isinstance(tables, dict) or not tables:
        raise ValueError(f"{path}: no 'tables' mapping")
    out = {}
    for name, tab in tables.items():
        if not isinstance(tab, dict):
            raise ValueError(f"{path}: table {name!r} must map faults to signatures")
        out[str(name)] = FaultSymptomTable(
            cols, {str(f): parse_signature(s, len(cols)) for f, s in tab.items()})
    return out
