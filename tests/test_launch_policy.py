"""The launcher's pure parts: respawn back-off, what counts as a death, diagnosis events."""

from __future__ import annotations

import math
import random
import signal

from fdi_ros.core.events import diagnosis_events
from fdi_ros.core.types import Diagnosis
from fdi_ros.launcher import RespawnPolicy, _died


def test_respawn_backoff_doubles_up_to_its_cap() -> None:
    p = RespawnPolicy(limit=5, first_delay_s=1.0, max_delay_s=8.0)
    assert [p.delay(k) for k in range(6)] == [1.0, 2.0, 4.0, 8.0, 8.0, 8.0]


def test_clean_stops_are_not_deaths() -> None:
    for code in (None, 0, -signal.SIGINT, -signal.SIGTERM, 130, 143):
        assert not _died(code)
    for code in (1, 2, -signal.SIGKILL, -signal.SIGSEGV, 137):
        assert _died(code)


def _diag(i: int, state: str, online: tuple[str, ...]) -> Diagnosis:
    return Diagnosis(t=0.015 * (i + 1), index=i, state=state, models_online=online,
                     min_residual_model="nominal", fault_model="nominal")


def test_events_are_the_changes_of_state_and_of_the_bank() -> None:
    seed = random.randrange(1 << 30)
    print(f"seed {seed}")
    rng = random.Random(seed)
    states = ["no_fault", "detected", "isolated", "not_valid"]
    banks = [("nominal",), ("nominal", "leak")]
    seq = [(rng.choice(states), rng.choice(banks)) for _ in range(200)]
    ds = [_diag(i, st, b) for i, (st, b) in enumerate(seq)]
    ev = diagnosis_events(ds)
    # oracle: count the changes directly
    n_state = 1 + sum(seq[i][0] != seq[i - 1][0] for i in range(1, len(seq)))
    n_bank = sum(seq[i][1] != seq[i - 1][1] for i in range(1, len(seq)))
    assert sum("state" in e for e in ev) == n_state
    assert sum("bank_switch" in e for e in ev) == n_bank
    assert all(math.isclose(e["t"], 0.015 * (e["index"] + 1), abs_tol=1e-4) for e in ev)
    assert [e["index"] for e in ev] == sorted(e["index"] for e in ev)
    assert diagnosis_events([]) == []
