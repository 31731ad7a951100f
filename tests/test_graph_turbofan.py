"""The turbofan through the same live graph: 16 lifecycle residual nodes (one per bank model of
Diao & Passino), a small compressor-hub fault at 5 s growing to large at 15 s; the supervisor
isolates it by the minimum residual held for T0 and switches the bank through the lifecycle
services (checked with get_state). The 16 nodes live in two model-host processes, as a
component container holds components (each still a lifecycle node with its own services); the
diesel graph tests run one process per node."""

from __future__ import annotations

from pathlib import Path

import pytest

from fdi_ros.livegraph import run_live

pytestmark = [pytest.mark.graph, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config" / "turbofan.yaml"
SCENARIO = ROOT / "config" / "turbofan_hub_small_to_large.yaml"


@pytest.fixture(scope="module")
def live(turbofan_bank):
    lines: list[str] = []
    run, w = run_live(CONFIG, scenario=SCENARIO, timeout_s=150, log=lines.append,
                      hosting={"mode": "container", "containers": 2})
    return run, w, lines


def test_hub_fault_isolated_and_followed_as_it_grows(live):
    run, _, lines = live
    models = [(i["t"], i["model"]) for i in run.isolations]
    assert models and models[0][1] == "hub_small", lines
    # paper: isolated 7.38 s (fault at 5 s, T0 = 1.2 s); ours must be after onset + T0
    assert 5.0 + 1.2 <= models[0][0] <= 8.5, models
    assert models[-1][1] == "hub_large" and 15.0 + 1.2 <= models[-1][0] <= 19.0, models
    # never a fan fault (the fault index was never wrong)
    assert not any("fan" in m and "+" not in m for _, m in models), models


def test_bank_switched_by_the_rules_through_lifecycle_services(live):
    run, _, _ = live
    states = run.lifecycle_after
    assert len(states) == 16
    # hub isolated -> the other single-fault models (fan) and the nominal model go off line;
    # every size of hub stays, and the double faults containing hub come on line
    for mid in ("nominal", "fan_small", "fan_medium", "fan_large"):
        assert states[mid] == "inactive", states
    for mid in ("hub_small", "hub_large", "fan_small+hub_small", "fan_large+hub_large"):
        assert states[mid] == "active", states
