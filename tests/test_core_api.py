"""Small generic parts of the core: the fault-event queue, the one meaning of a fault profile,
named kinds and fault-symptom tables by column name."""

from __future__ import annotations

import pytest

from fdi_ros.core.fst import FaultSymptomTable, isolate
from fdi_ros.core.kinds import Kinds
from fdi_ros.core.plant_api import FaultQueue
from fdi_ros.core.types import FaultEvent


def test_fault_queue_hands_out_each_event_once_in_time_order():
    q = FaultQueue()
    for t in (3.0, 1.0, 2.0):
        q.add(FaultEvent(t=t, fault="f"))
    assert [e.t for e in q.due(1.5)] == [1.0]
    assert q.due(1.5) == []
    assert [e.t for e in q.due(10.0)] == [2.0, 3.0] and len(q) == 0


def test_profiles_step_and_ramp_from_the_size_before():
    step = FaultEvent(t=2.0, fault="f", size=4.0)
    assert step.size_at(2.0, before=1.0) == 4.0
    ramp = FaultEvent(t=2.0, fault="f", size=4.0, profile="ramp", ramp_s=2.0)
    assert ramp.size_at(2.0) == 0.0
    assert ramp.size_at(3.0) == pytest.approx(2.0)          # halfway from 0
    assert ramp.size_at(3.0, before=2.0) == pytest.approx(3.0)  # halfway from 2
    assert ramp.size_at(9.0, before=2.0) == 4.0
    with pytest.raises(ValueError):
        FaultEvent(t=0.0, fault="f", profile="ramp")  # a ramp needs its duration


def test_kinds_register_look_up_and_refuse():
    k: Kinds = Kinds("widget")

    @k.register("a")
    def make_a() -> str:
        return "a"

    assert k.get("a")() == "a" and "a" in k and "b" not in k
    with pytest.raises(ValueError, match="unknown widget type 'b'"):
        k.get("b")
    with pytest.raises(ValueError, match="already registered"):
        k.register("a")(lambda: "other")


def test_isolation_by_symptom_name_follows_the_table_columns():
    table = FaultSymptomTable(("s_x", "s_y"), {"fx": (1, 0), "fy": (0, -1)})
    assert isolate({"s_y": -1}, table) == ["fy"]
    assert isolate((1, 0), table) == ["fx"]
    with pytest.raises(ValueError, match="not columns"):
        isolate({"s_z": 1}, table)
    with pytest.raises(ValueError):
        FaultSymptomTable(("s_x",), {"fx": (1, 0)})
