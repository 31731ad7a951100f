"""Run-time fault requests: every malformed kind refused with its reason, valid ones turned
into the event the plant schedules; the pacer's rate change applies from the moment of it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fdi_ros.core.faultcheck import FaultRejected, FaultRequests, check_fault_request, describe
from fdi_ros.core.pacing import Pacer
from fdi_ros.plants import fault_rules


@pytest.fixture(scope="module")
def diesel():
    faults, check = fault_rules("diesel")
    return dict(faults=faults, plant_check=check)


@pytest.mark.parametrize("req, words", [
    ((0.0, "no_such_fault", 5.0, "mm"), "unknown fault"),
    ((0.0, "leak_ic_engine", -5.0, "mm"), ">= 0"),
    ((0.0, "leak_ic_engine", math.nan, "mm"), "finite"),
    ((0.0, "leak_ic_engine", math.inf, "mm"), "finite"),
    ((0.0, "leak_ic_engine", 5.0, "mm", "zigzag"), "unknown profile"),
    ((0.0, "leak_ic_engine", 5.0, "mm", "ramp", 0.0), "ramp_s > 0"),
    ((0.0, "leak_ic_engine", 5.0, "mm", "ramp", -1.0), "ramp_s must be >= 0"),
    ((math.nan, "leak_ic_engine", 5.0, "mm"), "t_s must be finite"),
    ((1.0, "leak_ic_engine", 5.0, "mm"), "in the past"),
    ((0.0, "leak_ic_engine", 500.0, "mm"), "outside"),  # the plant's own limit
    ((0.0, "leak_ic_engine", 5.0, "bar"), "sized in"),  # the plant's own unit
    ((0.0, "leak_ic_engine", "five", "mm"), "must be a number"),  # type: ignore
    ((0.0, 42, 5.0, "mm"), "must be a string"),  # type: ignore[arg-type]
])
def test_malformed_requests_refused_with_reason(diesel, req, words):
    with pytest.raises(FaultRejected) as exc:
        check_fault_request(*req, now=2.0, **diesel)
    assert words in str(exc.value)


def test_valid_requests_become_events(diesel):
    ev = check_fault_request(0.0, "leak_ic_engine", 5.0, "mm", now=2.5, **diesel)
    assert (ev.t, ev.fault, ev.size, ev.profile, ev.active) == (2.5, "leak_ic_engine", 5.0,
                                                                 "step", True)
    ev = check_fault_request(7.0, "egr_leaky", 2.0, "mm", "ramp", 1.5, now=2.5,
                             **diesel)
    assert ev.t == 7.0 and ev.profile == "ramp" and ev.ramp_s == 1.5
    assert "ramp over 1.5 s" in describe(ev)
    clear = check_fault_request(-1.0, "", now=3.0, **diesel)
    assert clear.fault == "" and "cleared" in describe(clear)
    off = check_fault_request(0.0, "egr_leaky", 0.0, "mm", active=False, now=1.0,
                              **diesel)
    assert not off.active and "removed" in describe(off)


def test_fault_types_admit_sized_ids():
    faults, check = fault_rules("turbofan")
    assert check_fault_request(0.0, "hub_small", now=0.0, faults=faults,
                               plant_check=check).fault == "hub_small"
    with pytest.raises(FaultRejected, match="unknown fault"):
        check_fault_request(0.0, "hub_huge", now=0.0, faults=faults,
                            plant_check=check)


def test_pacer_rate_change_applies_from_then_on():
    rng = np.random.default_rng()
    seed = int(rng.integers(1 << 31))
    print(f"seed {seed}")
    rng = np.random.default_rng(seed)
    p = Pacer(1.0)
    assert p.target(5.0) == -math.inf  # nothing before start
    w0, lag = float(rng.uniform(0, 100)), float(rng.uniform(0, 0.5))
    p.start(w0, 0.0)
    assert p.target(w0 + 10.0) == pytest.approx(10.0)
    # at w0 + 10 the plant lags by `lag`; the new rate runs from where the plant is
    p.set_rate(4.0, w0 + 10.0, 10.0 - lag)
    assert p.target(w0 + 10.0) == pytest.approx(10.0 - lag)  # no catch-up of the past
    assert p.target(w0 + 12.0) == pytest.approx(10.0 - lag + 8.0)
    p.set_rate(0.0, w0 + 13.0, 14.0)
    assert p.target(w0 + 13.0) == math.inf
    for bad in (-1.0, math.nan, math.inf):
        with pytest.raises(ValueError):
            p.set_rate(bad, w0, 0.0)


def test_a_stalled_plant_goes_on_at_its_rate_instead_of_bursting():
    """A plant held up for longer than CATCH_UP_S sends at most CATCH_UP_S of plant time at
    once, then follows its rate from there; a plant keeping up is paced as before."""
    from fdi_ros.core.pacing import CATCH_UP_S

    rng = np.random.default_rng(seed := int(np.random.SeedSequence().entropy % 2**31))
    rate, stall = float(rng.uniform(0.5, 4.0)), float(rng.uniform(0.2, 3.0))
    p = Pacer(rate)
    p.start(100.0, 0.0)
    assert p.target_within(101.0, rate - 0.01, CATCH_UP_S) == pytest.approx(rate), seed
    # held up at plant time `rate` for `stall` wall seconds
    t = p.target_within(101.0 + stall, rate, CATCH_UP_S)
    assert t == pytest.approx(rate + CATCH_UP_S), seed
    # a second later, having kept up since, it is paced from the new anchor
    assert p.target_within(102.0 + stall, t + rate - 0.01, CATCH_UP_S) == pytest.approx(
        t + rate), seed
    fast = Pacer(0.0)   # as fast as the graph takes it: never held back
    fast.start(4.0, 0.0)
    assert fast.target_within(5.0, 1.0, CATCH_UP_S) == math.inf


def test_pacer_starts_once_readers_are_there_and_the_delay_has_passed():
    p = Pacer(2.0)
    assert not p.start_when_ready(1.0, 0.0, readers_ok=False, delay_s=0.5)
    assert not p.start_when_ready(2.0, 0.0, readers_ok=True, delay_s=0.5)  # delay from 2.0
    assert not p.start_when_ready(2.4, 0.0, readers_ok=False, delay_s=0.5)  # reader gone
    assert p.start_when_ready(2.5, 0.0, readers_ok=True, delay_s=0.5)
    assert p.started and p.target(3.5) == pytest.approx(2.0)
    assert p.start_when_ready(9.0, 7.0, readers_ok=False)  # started stays started


def test_fault_requests_count_refuse_and_report():
    from types import SimpleNamespace

    from fdi_ros.core.supervision import OK, WARN

    def req(fault, size=1.0, unit="mm", t_s=0.0, profile="", ramp_s=0.0, active=True):
        return SimpleNamespace(t_s=t_s, fault=fault, size=size, size_unit=unit,
                               profile=profile, ramp_s=ramp_s, active=active)

    def check(ev):
        if ev.size > 5.0:
            raise ValueError(f"{ev.fault}: size {ev.size} above 5 mm")

    scheduled = []
    r = FaultRequests(("leak",), check)
    assert r.entry("n", "p", t=0.0, rate=1.0).level == OK and r.last == "none"
    ok, reason = r.handle(req("leak", 2.0), now=3.0, schedule=scheduled.append)
    assert ok and reason == "scheduled: leak 2 mm at t = 3.000 s" and r.ok
    assert [e.fault for e in scheduled] == ["leak"] and scheduled[0].t == 3.0
    for bad, why in ((req("vent"), "unknown fault"), (req("leak", 9.0), "above 5 mm"),
                     (req("leak", t_s=1.0), "in the past"), (req("leak", size=math.nan),
                                                              "finite")):
        ok, reason = r.handle(bad, now=3.0, schedule=scheduled.append)
        assert not ok and why in reason and why in r.last and not r.ok
    assert len(scheduled) == 1 and (r.accepted, r.rejected) == (1, 4)
    e = r.entry("fdi_plant: fault injection", "p", t=3.0, rate=4.0)
    assert e.level == WARN and e.message == r.last and e.hardware_id == "p"
    assert dict(e.values) == {"plant_time_s": "3.000", "realtime_factor": "4",
                              "accepted": "1", "rejected": "4"}

    def full(ev):
        raise ValueError("queue full")

    assert r.handle(req("leak"), now=3.0, schedule=full) == (False, "queue full")
