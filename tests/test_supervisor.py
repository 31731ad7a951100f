"""Expert supervisor: bank rules (table-driven), detection, hold-time isolation, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fdi_ros.core.supervisor import (
    BankModel,
    ExpertSupervisor,
    fault_type,
    models_online,
    sized_bank,
)
from fdi_ros.core.types import ResidualVector

BANK = sized_bank(("fan", "hub"))
DOUBLES = [f"fan_{a}+hub_{b}" for a in ("small", "medium", "large")
           for b in ("small", "medium", "large")]


def test_paper_bank_has_16_models_in_paper_order():
    ids = [m.id for m in BANK]
    assert len(ids) == 16
    assert ids[:7] == ["nominal", "fan_small", "fan_medium", "fan_large",
                       "hub_small", "hub_medium", "hub_large"]
    assert ids[7:] == DOUBLES


@pytest.mark.parametrize("isolated, expected", [
    ((), ["nominal", "fan_small", "fan_medium", "fan_large",
          "hub_small", "hub_medium", "hub_large"]),
    (("fan_small",), ["fan_small", "fan_medium", "fan_large"] + DOUBLES),
    (("hub_large",), ["hub_small", "hub_medium", "hub_large"] + DOUBLES),
    (("fan_medium", "hub_medium"), DOUBLES),
    (("hub",), ["hub_small", "hub_medium", "hub_large"] + DOUBLES),
])
def test_models_online_table(isolated, expected):
    assert models_online(BANK, isolated) == expected


def test_models_online_three_types_generalises():
    bank = sized_bank(("a", "b", "c"), sizes=("small",), max_faults=3)
    assert models_online(bank, ["a_small"]) == ["a_small", "a_small+b_small", "a_small+c_small"]
    assert models_online(bank, ["a_small", "c_small"]) == ["a_small+c_small",
                                                           "a_small+b_small+c_small"]


def test_bad_banks_and_faults_rejected():
    with pytest.raises(ValueError, match="nominal"):
        models_online([BankModel(id="x", faults=frozenset({"fan_small"}))], [])
    with pytest.raises(ValueError, match="duplicate"):
        models_online([BankModel(id="n"), BankModel(id="n")], [])
    with pytest.raises(ValueError, match="not represented"):
        models_online(BANK, ["valve_small"])
    with pytest.raises(ValueError, match="two sizes"):
        BankModel(id="bad", faults=frozenset({"fan_small", "fan_large"}))
    with pytest.raises(ValueError, match="t0_s"):
        ExpertSupervisor(bank=BANK, t0_s=-1.0)
    assert fault_type("fan_small") == "fan" and fault_type("leak") == "leak"
    assert fault_type("big_valve_large") == "big_valve"


def _residuals(true_model: str, t: float, rng) -> dict[str, float]:
    """Residual norms: 3 for the true model, 20 + noise for the others."""
    return {m.id: (3.0 if m.id == true_model else 20.0) + rng.uniform(0, 1) for m in BANK}


def _run(sup, schedule, t_end, rng, ts=0.02, glitch=None):
    diags = []
    for k in range(int(round(t_end / ts)) + 1):
        t = k * ts
        true = [m for t_on, m in schedule if t >= t_on][-1]
        res = _residuals(true, t, rng)
        if glitch and glitch[0] <= t < glitch[1]:
            res[glitch[2]] = 0.0
        diags.append(sup.update(t, res))
    return diags


def test_isolation_after_hold_time_and_bank_switch():
    rng = np.random.default_rng(1)
    sup = ExpertSupervisor(bank=BANK, t0_s=1.2)
    d = _run(sup, [(0.0, "nominal"), (5.0, "hub_small"), (15.0, "hub_large")], 20.0, rng)
    assert d[0].state == "no_fault" and d[0].fault_model == "nominal"
    events = [(round(t, 2), kind, m) for t, kind, m in sup.history]
    assert events == [(5.0, "detected", "hub_small"), (6.2, "isolated", "hub_small"),
                      (15.0, "detected", "hub_large"), (16.2, "isolated", "hub_large")]
    last = d[-1]
    assert last.state == "isolated" and last.fault_model == "hub_large"
    assert last.isolated_faults == ("hub_large",)
    assert last.fault_index == 6
    assert last.models_online == tuple(models_online(BANK, ["hub"]))
    assert last.isolation_time == pytest.approx(16.2)
    # between detection and isolation the state is "detected", fault index still the old one
    mid = d[int(5.6 / 0.02)]
    assert mid.state == "detected" and mid.fault_model == "nominal"
    assert mid.min_residual_model == "hub_small" and mid.detection_time == pytest.approx(5.0)


def test_short_glitch_is_detected_but_not_isolated():
    rng = np.random.default_rng(2)
    sup = ExpertSupervisor(bank=BANK, t0_s=1.2)
    d = _run(sup, [(0.0, "nominal")], 6.0, rng, glitch=(2.0, 3.1, "fan_large"))
    kinds = [k for _, k, _ in sup.history]
    assert kinds == ["detected", "cleared"]
    assert d[-1].state == "no_fault" and not d[-1].isolated_faults
    assert math.isclose(d[-1].detection_time, 2.0)


def test_double_fault_isolated_after_single():
    rng = np.random.default_rng(3)
    sup = ExpertSupervisor(bank=BANK, t0_s=0.5)
    d = _run(sup, [(0.0, "fan_medium"), (10.0, "fan_medium+hub_medium")], 14.0, rng)
    assert [m for _, k, m in sup.history if k == "isolated"] == ["fan_medium",
                                                                 "fan_medium+hub_medium"]
    assert d[-1].isolated_faults == ("fan_medium", "hub_medium")
    assert set(d[-1].models_online) == set(DOUBLES)


def _rv(mid, t, norm, valid=True):
    return ResidualVector(model_id=mid, index=0, t=t, valid=valid, status="", names=("XN2",),
                          units=("rpm",), values=np.array([norm]), norm=norm)


def test_dead_stale_and_invalid_models_are_skipped():
    sup = ExpertSupervisor(bank=BANK, t0_s=0.1, stale_s=0.05)
    online = sup.models_online
    # fan_small's node died: it sends a very small residual once, then nothing new
    stale = _rv("fan_small", -1.0, 0.0)
    for k in range(20):
        t = 0.02 * k
        res = {m: _rv(m, t, 5.0 if m == "nominal" else 30.0) for m in online}
        res["fan_small"] = stale if k > 0 else _rv("fan_small", t, 50.0)
        del res["hub_medium"]  # never reports at all
        d = sup.update(t, res)
        assert d.state == "no_fault", (t, d)
    # all residuals outside the identified region -> not_valid, never an alarm
    res = {m: _rv(m, 1.0, 0.0, valid=False) for m in online}
    d = sup.update(1.0, res)
    assert d.state == "not_valid" and d.fault_model == "nominal"
    d = sup.update(1.02, {m: float("nan") for m in online})
    assert d.state == "not_valid"


def test_gap_restarts_hold_timer():
    sup = ExpertSupervisor(bank=BANK, t0_s=1.0)
    for k in range(40):  # fan_large best for 0.78 s
        sup.update(0.02 * k, {m.id: 1.0 if m.id == "fan_large" else 9.0 for m in BANK[:7]})
    sup.update(0.8, {})  # gap
    for k in range(41, 80):
        d = sup.update(0.02 * k, {m.id: 1.0 if m.id == "fan_large" else 9.0 for m in BANK[:7]})
    assert d.state == "detected" and not sup.isolated
    d = sup.update(1.82, {m.id: 1.0 if m.id == "fan_large" else 9.0 for m in BANK[:7]})
    assert d.state == "isolated" and d.fault_model == "fan_large"
