"""The one symptom-vs-table matcher (core/fst.isolate): each rule from a table of cases worked
out by hand, and random cases against the rules written out from their definitions."""

from __future__ import annotations

import itertools
import os

import numpy as np
import pytest

from fdi_ros.core.fst import FaultSymptomTable, covering, isolate, isolate_in_sign

TABLE = FaultSymptomTable(("s1", "s2", "s3"), {
    "leak": (-1, 0, 0), "egr": (2, -1, -1), "vent": (1, 0, 0), "restr": (0, -1, 1)})

# (observed, max_mismatch, opposite, keep, expected), worked out by hand from the rules.
CASES = [
    ((-1, 0, 0), 1, "double", "nearest", ["leak"]),            # exact
    ((1, 0, 0), 1, "exclude", "all", ["vent"]),                # exact beats signed
    ((2, 0, 0), 0, "double", "nearest", ["vent"]),             # signed (+ == ++)
    ((1, -1, -1), 0, "exclude", "all", ["egr"]),               # signed
    ((0, 0, 0), 2, "double", "nearest", []),                   # no symptom, no candidate
    # (-,-,o): leak misses s2 (1); egr has s1 opposite (2) + s3 missing (1) = 3;
    # vent: s1 opposite (2) + s2 (1) = 3; restr: s1 (1) + s3 extra (1) = 2
    ((-1, -1, 0), 1, "double", "nearest", ["leak"]),
    ((-1, -1, 0), 1, "exclude", "all", ["leak"]),
    ((-1, -1, 0), 0, "exclude", "all", []),
    ((-1, -1, 0), 2, "double", "nearest", ["leak"]),           # only the nearest
    ((-1, -1, 0), 2, "exclude", "all", ["leak", "restr"]),     # all within 2, none opposite
    ((-1, -1, 0), 3, "double", "all", ["leak", "egr", "vent", "restr"]),
    # (o,o,+): restr misses s2 (1); leak/vent s1 missing + s3 extra (2); egr 2 + 1 + 2 = 5
    ((0, 0, 1), 1, "double", "nearest", ["restr"]),
    ((0, 0, 1), 2, "exclude", "all", ["leak", "vent", "restr"]),
    ((0, 0, 1), 2, "double", "nearest", ["restr"]),
    # (o,+,o): egr and restr have s2 opposite (2 + ...): excluded; leak and vent at 2
    ((0, 1, 0), 2, "exclude", "nearest", ["leak", "vent"]),
    ((0, 1, 0), 1, "exclude", "all", []),
]


@pytest.mark.parametrize(("observed", "mm", "opposite", "keep", "expected"), CASES)
def test_cases_worked_out_by_hand(observed, mm, opposite, keep, expected):
    assert isolate(observed, TABLE, max_mismatch=mm, opposite=opposite, keep=keep) == expected


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="symptoms"):
        isolate((1, 0), TABLE)
    with pytest.raises(ValueError, match="opposite"):
        isolate((1, 0, 0), TABLE, opposite="ignore")
    with pytest.raises(ValueError, match="not columns"):
        isolate({"s9": 1}, TABLE)
    assert isolate({"s2": -1, "s3": 1}, TABLE) == ["restr"]  # by name


def _sign(v: int) -> int:
    return (v > 0) - (v < 0)


def _by_definition(obs, table, mm, opposite, keep):
    """The rules of the docstring, written out symptom by symptom."""
    if all(v == 0 for v in obs):
        return []
    exact = [f for f, s in table.items() if list(s) == list(obs)]
    signed = [f for f, s in table.items()
              if f not in exact and all(_sign(a) == _sign(b) for a, b in zip(s, obs))]
    if exact or signed or mm <= 0:
        return exact or signed
    dist = {}
    for f, s in table.items():
        d = [abs(_sign(a) - _sign(b)) for a, b in zip(s, obs)]
        if opposite == "exclude" and 2 in d:
            continue
        dist[f] = sum(d)
    if keep == "all":
        return [f for f, d in dist.items() if d <= mm]
    best = min(dist.values(), default=None)
    return [f for f, d in dist.items() if d == best] if best is not None and best <= mm else []


def _previous_diagnoser_rule(observed, table, mm):
    """The live diagnoser's own matcher before there was one (kept as the oracle of its
    behaviour): no symptom of the opposite sign, at most ``mm`` symptoms differing."""
    obs = [int(v) for v in observed]
    if not any(obs):
        return []
    exact, signed, near = [], [], []
    for fault, sig in table.items():
        a, b = [_sign(v) for v in sig], [_sign(v) for v in obs]
        if list(sig) == obs:
            exact.append(fault)
        elif a == b:
            signed.append(fault)
        elif all(x * y >= 0 for x, y in zip(a, b)) and sum(x != y for x, y in zip(a, b)) <= mm:
            near.append(fault)
    return exact or signed or near


def test_random_tables_match_the_definition_and_the_previous_rule():
    seed = int(os.environ.get("FST_SEED", np.random.SeedSequence().entropy % 2**32))
    rng = np.random.default_rng(seed)
    for _ in range(400):
        n = int(rng.integers(1, 7))
        table = {f"f{i}": tuple(int(v) for v in rng.choice([-1, 0, 1, 2], n,
                                                            p=[0.2, 0.5, 0.2, 0.1]))
                 for i in range(int(rng.integers(1, 8)))}
        obs = tuple(int(v) for v in rng.choice([-1, 0, 1, 2], n, p=[0.25, 0.4, 0.25, 0.1]))
        mm = int(rng.integers(0, 4))
        for opposite, keep in itertools.product(("double", "exclude"), ("nearest", "all")):
            got = isolate(obs, table, max_mismatch=mm, opposite=opposite, keep=keep)
            assert got == _by_definition(obs, table, mm, opposite, keep), (seed, table, obs)
        assert isolate(obs, table, max_mismatch=mm, opposite="exclude", keep="all") == \
            _previous_diagnoser_rule(obs, table, mm), (seed, table, obs, mm)


def test_partial_signatures_match_in_sign_on_the_judged_symptoms_only():
    """A regime that judges some symptoms: the table compared there, in sign; a random table
    and observation against the definition (seeded at test time)."""
    assert isolate_in_sign({"s1": -1}, TABLE, ["s1"]) == ["leak"]
    assert isolate_in_sign({"s1": 1}, TABLE, ["s1"]) == ["egr", "vent"]   # + == ++
    assert isolate_in_sign({"s1": 2, "s2": -1}, TABLE, ["s1"]) == ["egr", "vent"]  # s2 unjudged
    assert isolate_in_sign({"s2": -1}, TABLE, ["s1"]) == []       # no judged symptom
    assert isolate_in_sign({"s1": 0, "s2": -1}, TABLE, ["s1", "s2"]) == ["restr"]
    seed = int(os.environ.get("FST_SEED", np.random.SeedSequence().entropy % 2**32))
    rng = np.random.default_rng(seed)
    names = ("s1", "s2", "s3", "s4")
    for _ in range(300):
        table = FaultSymptomTable(names, {f"f{i}": tuple(int(v) for v in rng.choice(
            [-1, 0, 1, 2], 4)) for i in range(int(rng.integers(1, 7)))})
        judged = [c for c in names if rng.random() < 0.5] or ["s1"]
        obs = {c: int(rng.choice([-1, 0, 1, 2])) for c in names}
        want = [f for f, row in table.items()
                if all(np.sign(row[names.index(c)]) == np.sign(obs[c]) for c in judged)] \
            if any(obs[c] for c in judged) else []
        assert isolate_in_sign(obs, table, judged) == want, (seed, table, obs, judged)


def test_covering_keeps_every_fault_that_shows_the_observed_symptoms():
    """A fault is kept when its signature has every observed symptom in sign; its other
    symptoms may not show (checked against the definition on random tables, seed at test
    time)."""
    assert covering((-1, 0, 0), TABLE) == ["leak"]
    assert covering((2, 0, 0), TABLE) == ["egr", "vent"]      # "++" shows as "+" too
    assert covering((1, -1, 0), TABLE) == ["egr"]             # egr's s3 does not show
    assert covering((0, -1, 1), TABLE) == ["restr"]
    assert covering((0, 0, 0), TABLE) == []
    seed = int(os.environ.get("FST_SEED", np.random.SeedSequence().entropy % 2**32))
    rng = np.random.default_rng(seed)
    for _ in range(300):
        n = int(rng.integers(1, 6))
        table = {f"f{i}": tuple(int(v) for v in rng.choice([-1, 0, 1, 2], n))
                 for i in range(int(rng.integers(1, 7)))}
        obs = tuple(int(v) for v in rng.choice([-1, 0, 1, 2], n))
        want = [f for f, row in table.items()
                if all(np.sign(row[j]) == np.sign(obs[j]) for j in range(n) if obs[j])] \
            if any(obs) else []
        assert covering(obs, table) == want, (seed, table, obs)
