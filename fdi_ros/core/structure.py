"""Structured residuals: the fault-symptom table follows from what each residual uses.

A residual generator (a parity equation) uses some measured signals and some model relations
(e.g. "the manifold's mass balance"). A fault acts on one of them: a sensor fault on the
sensor's signal, a process fault on a relation. The residual responds to the fault exactly
when it uses what the fault acts on, so the fault-symptom table (FST) is derived, not tuned:

.. math:: S_{jf} = 1 \\iff \\mathrm{acts}(f) \\in \\mathrm{uses}(r_j)

Faults are *structurally isolable* from each other when their columns differ, and isolable
against every single other fault under an exoneration-free reading when no column is contained
in another (a fault whose residuals are a subset of another's would be consistent with both).

:func:`hypothesis_norm` turns normalised residuals (units of their thresholds, fault-free
within +-1) into the norm of one fault hypothesis for a minimum-residual supervisor: a
hypothesis must leave every residual it cannot explain below its threshold, and pays a little
for each residual it should drive but that stays quiet.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import numpy as np

__all__ = ["derive_fst", "fst_report", "hypothesis_norm", "isolability"]


def derive_fst(uses: Mapping[str, Iterable[str]],
               acts_on: Mapping[str, str | Iterable[str]]) -> dict[str, tuple[int, ...]]:
    """Fault-symptom table ``{fault: (0/1 per residual in the order of uses)}``.

    Parameters
    ----------
    uses : residual name -> signals and relations it uses.
    acts_on : fault -> the signal or relation (or several) it acts on.
    """
    if not uses or not acts_on:
        raise ValueError("need at least one residual and one fault")
    names = list(uses)
    sets = {r: frozenset(uses[r]) for r in names}
    table = {}
    for fault, target in acts_on.items():
        targets = {target} if isinstance(target, str) else set(target)
        if not targets:
            raise ValueError(f"fault {fault!r} acts on nothing")
        table[fault] = tuple(int(bool(targets & sets[r])) for r in names)
    return table


def isolability(table: Mapping[str, Sequence[int]]) -> dict[str, object]:
    """Structural properties of a table: undetectable faults, pairs with equal columns, pairs
    where one column lies inside another (``(a, b)``: every residual of a also responds to b)."""
    faults = list(table)
    cols = {f: np.asarray(table[f], dtype=bool) for f in faults}
    same, inside = [], []
    for i, a in enumerate(faults):
        for b in faults[i + 1:]:
            if np.array_equal(cols[a], cols[b]):
                same.append((a, b))
            elif not np.any(cols[a] & ~cols[b]):
                inside.append((a, b))
            elif not np.any(cols[b] & ~cols[a]):
                inside.append((b, a))
    return {"undetectable": [f for f in faults if not cols[f].any()],
            "not_isolable": same, "column_inside": inside,
            "isolable": not same and not any(not cols[f].any() for f in faults)}


def hypothesis_norm(z: np.ndarray, column: Sequence[int] | None, *,
                    quiet_penalty: float = 0.3,
                    bound: np.ndarray | Sequence[float] | None = None,
                    sign: Sequence[int] | None = None) -> float:
    """Norm of one hypothesis given residuals ``z`` in threshold units.

    ``column`` is the hypothesis' FST column (``None``: the fault-free hypothesis, which
    explains no residual). A residual the hypothesis cannot explain counts with ``|z|``; one it
    explains counts ``quiet_penalty * max(0, 1 - |z|)`` (nothing when it fires, a little
    when it stays quiet, so that of two hypotheses that both explain the data the one whose
    residuals respond wins). ``bound`` (threshold units, per residual) is the largest effect
    the hypothesis can have (e.g. a sensor gain within +-20 %): what an explained residual
    shows beyond it counts as unexplained. ``sign`` (+1, -1 or 0 = either, per residual) is
    the direction the fault drives an explained residual; a residual moved the other way
    counts ``quiet_penalty + |z|`` (never less than one that stays quiet). The norm is the
    RMS over the residuals.
    """
    z = np.asarray(z, dtype=float)
    if column is None:
        return float(np.sqrt(np.mean(z ** 2)))
    s = np.asarray(column, dtype=bool)
    if s.shape != z.shape:
        raise ValueError(f"column has {s.size} entries, residuals {z.size}")
    a = np.abs(z)
    e = np.where(s, quiet_penalty * np.maximum(0.0, 1.0 - a), z)
    if bound is not None:
        e = np.where(s, e + np.maximum(0.0, a - np.asarray(bound, dtype=float)), e)
    if sign is not None:
        # driven the wrong way: as if it had not responded, plus what it shows
        sg = np.asarray(sign, dtype=float)
        wrong = s & (sg != 0) & (np.sign(z) == -sg)
        e = np.where(wrong, quiet_penalty + a, e)
    return float(np.sqrt(np.mean(e ** 2)))


def fst_report(residuals: Sequence[str], table: Mapping[str, Sequence[int]],
               uses: Mapping[str, Iterable[str]] | None = None) -> str:
    """The table as Markdown (residual rows, fault columns, ``X`` where it responds)."""
    faults = list(table)
    head = "| residual | uses | " + " | ".join(f"`{f}`" for f in faults) + " |"
    lines = [head, "|" + "---|" * (len(faults) + 2)]
    for j, r in enumerate(residuals):
        u = ", ".join(sorted(uses[r])) if uses else ""
        marks = " | ".join("X" if table[f][j] else "o" for f in faults)
        lines.append(f"| `{r}` | {u} | {marks} |")
    return "\n".join(lines)
