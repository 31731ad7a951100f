"""The ECU's EGR and swirl maps, scenarios that use them, the realistic drive and the coverage
report: schedules as an ECU runs them, the physics they act on, the drive's structure."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fdi_ros.plants.diesel.ecu import EcuSchedule

ROOT = Path(__file__).resolve().parents[1]


def test_schedule_opens_egr_at_part_load_and_closes_flaps_at_low_speed():
    ecu = EcuSchedule()
    rng = np.random.default_rng(7)
    for n, load in zip(rng.uniform(800, 5500, 200), rng.uniform(0.0, 1.0, 200)):
        fuel = load * float(np.interp(n, ecu.full_n, ecu.full_fuel))
        egr, swirl = ecu.commands(n, fuel)
        assert 0.0 <= egr <= ecu.egr_max
        if load >= ecu.egr_load[1] or n >= ecu.egr_speed[1]:
            assert egr == 0.0                      # full load and high speed: EGR closed
        if load <= ecu.egr_load[0] and n <= ecu.egr_speed[0]:
            assert egr == pytest.approx(ecu.egr_max)
        assert swirl == (1.0 if n < ecu.swirl_open[0] and load < ecu.swirl_open[1] else 0.0)
        # a trim moves an open valve, never opens a closed one
        assert ecu.commands(n, fuel, 0.1)[0] == (min(egr + 0.1, 1.0) if egr > 0 else 0.0)
    with pytest.raises(ValueError):
        EcuSchedule.from_dict({"egr_mx": 0.5})
    with pytest.raises(ValueError):
        EcuSchedule(egr_load=(0.8, 0.5))


def test_egr_displaces_fresh_air_and_closed_flaps_throttle_the_filling_ports():
    """Same speed and fuel: with the EGR valve open the MAF and the fresh-air eta_V fall and
    T2 rises; with the filling ports closed the engine breathes less and pulsates less."""
    from fdi_ros.plants.diesel.plant import DieselIntakePlant, fuel_for_torque

    def run(egr: float, swirl: float) -> dict:
        p = DieselIntakePlant(seed=1, noise=False)
        p.set_inputs(n_rpm=1800.0, fuel_mg=float(fuel_for_torque(1800.0, 80.0, p.p)),
                     egr_cmd=egr, swirl_cmd=swirl)
        p.advance(360 * 20)
        return p.truth()

    base, egr, swirl = run(0.0, 0.0), run(0.4, 0.0), run(0.0, 1.0)
    assert egr["m_egr"] > 0.1 * egr["m_cyl"]
    assert egr["m_maf"] < 0.9 * base["m_maf"]
    assert egr["eta_v_air"] < base["eta_v_air"] - 0.05 and egr["T2"] > base["T2"] + 10.0
    assert swirl["eta_v"] < base["eta_v"] and swirl["maf_amp"] < base["maf_amp"]
    assert swirl["m_egr"] == 0.0


def test_scenarios_take_the_ecu_maps_and_passes():
    from fdi_ros.plants.diesel.scenario import load_scenario

    doc = {"name": "x", "inputs": {"kind": "points", "ecu": {}, "points": [
        {"t": 0.0, "n": 1200, "torque": 40}, {"t": 10.0, "n": 1200, "torque": 40},
        {"t": 12.0, "n": 3000, "torque": 200}, {"t": 20.0, "n": 3000, "torque": 200,
                                                "ecu": False, "egr_cmd": 0.3}]}}
    sc = load_scenario(doc)
    n, fuel, egr, swirl = sc.inputs_at(5.0)
    assert (egr, swirl) == EcuSchedule().commands(n, fuel) and egr > 0.3 and swirl == 1.0
    assert sc.inputs_at(11.0)[0] > 2000 and sc.inputs_at(11.0)[3] == 0.0   # flaps open above
    assert sc.inputs_at(12.5)[2] == 0.0                                   # full load
    with pytest.raises(ValueError, match="ecu"):
        load_scenario({"name": "y", "inputs": {"kind": "points", "points": [
            {"t": 0.0, "n": 1000, "fuel": 10, "ecu": True}]}})
    zz = load_scenario({"name": "z", "inputs": {
        "kind": "zigzag", "n_min": 800, "n_max": 2000, "n_ramp_s": 20.0, "fuel_period_s": 8.0,
        "ecu": {}, "passes": [{"egr_cmd": 0.0}, {"ecu": True, "egr_trim": 0.1}]}})
    assert zz.duration_s == pytest.approx(80.5)
    first = np.array([zz.inputs_at(t)[2] for t in np.arange(0.0, 40.0, 0.5)])
    second = np.array([zz.inputs_at(t)[2] for t in np.arange(41.0, 80.0, 0.5)])
    assert np.all(first == 0.0) and second.max() > 0.3


def test_the_ecu_limits_a_torque_demand_to_its_full_load_fuel():
    """A torque the engine cannot give at that speed (200 Nm at 4200 rpm: the full-load curve
    gives about 170) gets the full-load fuel with an ECU; without one the plant's flat fuel
    limit applies; a demand below the curve is met as it is (random speeds and torques)."""
    from fdi_ros.plants.diesel.plant import DieselParams, fuel_for_torque
    from fdi_ros.plants.diesel.scenario import load_scenario

    ecu, p = EcuSchedule(), DieselParams()
    rng = np.random.default_rng()
    for n, tq in [(4200.0, 200.0)] + [(float(rng.uniform(900, 5000)),
                                       float(rng.uniform(0, 260))) for _ in range(20)]:
        pts = [{"t": 0.0, "n": n, "torque": tq}, {"t": 1.0, "n": n, "torque": tq}]
        with_ecu = load_scenario({"name": "a", "inputs": {"kind": "points", "ecu": {},
                                                          "points": pts}}).inputs_at(0.5)[1]
        without = load_scenario({"name": "b", "inputs": {"kind": "points",
                                                         "points": pts}}).inputs_at(0.5)[1]
        want = float(fuel_for_torque(n, tq, p))
        assert without == pytest.approx(want)
        assert with_ecu == pytest.approx(min(want, ecu.full_load_fuel(n))), (n, tq)
    assert ecu.full_load_fuel(4200.0) < fuel_for_torque(4200.0, 200.0, p)


def test_realistic_drive_file():
    from fdi_ros.plants.diesel.drive import drive_document, window
    from fdi_ros.plants.diesel.plant import FAULT_IDS
    from fdi_ros.plants.diesel.scenario import load_cases

    cases = load_cases(ROOT / "config" / "scenarios" / "diesel_realistic_drive.yaml")
    assert len(cases) == 1 + len(FAULT_IDS)
    assert cases[0].duration_s >= 20 * 60 and not cases[0].faults
    assert sorted(c.faults[0].fault for c in cases[1:]) == sorted(FAULT_IDS)
    onsets = [c.faults[0].t for c in cases[1:]]
    assert len(set(onsets)) == len(onsets)
    assert all(0.1 * cases[0].duration_s <= t <= 0.85 * cases[0].duration_s for t in onsets)
    U = np.array([cases[0].inputs_at(t) for t in np.arange(0.0, cases[0].duration_s, 1.0)])
    assert 0.3 < np.mean(U[:, 2] > 0.02) < 0.95       # EGR open over much of the drive
    assert 0.1 < np.mean(U[:, 3] > 0.5) < 0.6         # flaps closed at low speed
    # the file is what the generator writes (seeded)
    doc = drive_document()
    assert [p["t"] for p in doc["inputs"]["points"]][-1] == pytest.approx(cases[0].t[-1])
    # a window reproduces the drive's inputs, shifted
    w = window(cases[2], 100.0, 160.0)
    for t in (0.0, 13.3, 59.0):
        assert w.inputs_at(t) == pytest.approx(cases[2].inputs_at(100.0 + t))


def test_coverage_report_counts_regions_reasons_and_false_symptoms():
    from fdi_ros.core.types import FeatureVector
    from fdi_ros.plants.diesel.coverage import coverage_report

    class S:   # the fields of a SymptomState the report reads
        def __init__(self, valid, levels, status=""):
            self.valid, self.levels, self.status = valid, levels, status

    names = ("n", "fuel", "egr_cmd", "swirl_cmd")
    rows = [(1500, 10, 0.5, 1.0), (2500, 20, 0.3, 0.0), (3000, 40, 0.0, 0.0), (1500, 1, 0.5, 1.0)]
    feats = [FeatureVector(plant="diesel", index=i, t_start=i * 0.01, t_end=(i + 1) * 0.01,
                           alpha_start=0.0, valid=True, status="", names=names,
                           units=("",) * 4, values=np.array(r, dtype=float))
             for i, r in enumerate(rows * 5)]
    states = [S(True, (0,)) for _ in feats]
    states[1] = S(False, (0,), "not valid here: transient inputs (speed moved 80 rpm)")
    states[5] = S(False, (0,), "not valid here: egr_cmd = 0.3 outside the identified region")
    states[2] = S(True, (1,))
    rep = coverage_report(feats, states)
    assert rep["segments"] == 20 and rep["valid_segments"] == 18
    assert rep["coverage"] == pytest.approx(0.9)
    assert rep["false_symptom_segments"] == 1 and rep["false_symptom_onsets"] == 1
    assert rep["regions"]["egr_open_flaps_open"] == {
        "segments": 5, "share_of_drive": 0.25, "coverage": 0.6, "false_symptom_segments": 0}
    assert rep["regions"]["egr_closed"]["false_symptom_segments"] == 1
    assert rep["regions"]["overrun"]["coverage"] == 1.0
    assert rep["not_valid_reasons"] == {"transient inputs": 1,
                                        "EGR command outside the identified region": 1}
    from fdi_ros.plants.diesel.coverage import reason_class

    assert reason_class("not valid here: operating point n = 1250 rpm, rho2 = 1.4 kg/m^3 "
                        "outside the identified region") == \
        "(n, rho2) outside the identified coverage"
    assert reason_class("not valid here: n = 6000 rpm outside the identified region (over "
                        "800..4000 rpm)") == "speed outside the identified range"


def test_coverage_cells_count_the_residuals_judged_where_the_diagnosis_is_valid(tmp_path):
    """Per speed-fuel cell: the valid share and the mean number of residuals judged (finite
    thresholds) over the valid segments; invalid segments do not count; the figure is
    written."""
    from types import SimpleNamespace

    from fdi_ros.core.types import FeatureVector
    from fdi_ros.plants.diesel.coverage import coverage_cells, coverage_figure

    inf = float("inf")
    rows = [(1510.0, 21.0, (1.0, inf, inf, inf, inf), True),    # EGR open: eta_V alone
            (1520.0, 21.5, (1.0, 2.0, inf, 3.0, 4.0), True),    # ... with the pulsations
            (1530.0, 21.2, (1.0, 2.0, 3.0, 4.0, 5.0), False),   # not valid: not counted
            (3010.0, 41.0, (1.0, 2.0, 3.0, 4.0, 5.0), True)]    # EGR closed: all five
    feats = [FeatureVector(plant="diesel", index=i, t_start=i * 0.01, t_end=(i + 1) * 0.01,
                           alpha_start=0.0, valid=True, status="", names=("n", "fuel"),
                           units=("", ""), values=np.array(r[:2]))
             for i, r in enumerate(rows)]
    states = [SimpleNamespace(valid=r[3], levels=(0,) * 5, status="", names=("a",) * 5,
                              threshold_high=np.array(r[2])) for r in rows]
    cells = coverage_cells(feats, states)
    i, j = int((1500 - 750) // 250), int(21 // 2)
    assert cells["count"][i, j] == 3 and cells["share"][i, j] == pytest.approx(2 / 3)
    assert cells["judged"][i, j] == pytest.approx(2.5)
    assert cells["judged"][int((3000 - 750) // 250), int(41 // 2)] == 5
    assert np.isnan(cells["judged"][0, 0]) and np.isnan(cells["share"][0, 0])
    assert coverage_figure(feats, states, tmp_path / "c.png").stat().st_size > 0


def test_fault_case_report_counts_valid_segments_from_the_onset():
    from types import SimpleNamespace as NS

    from fdi_ros.core.types import FeatureVector
    from fdi_ros.plants.diesel.coverage import fault_case_report

    feats = [FeatureVector(plant="diesel", index=i, t_start=i * 0.015, t_end=(i + 1) * 0.015,
                           alpha_start=0.0, valid=True, status="", names=("n", "fuel"),
                           units=("rpm", "mg/stroke"), values=np.array([2000.0, 20.0]))
             for i in range(40)]
    # onset at 0.15 s (segment 10); segments 10-12 not valid, 13-14 valid and quiet,
    # symptom from 15 on; isolated at the end
    def step(i):
        valid = not 10 <= i <= 12
        lv = (-1, 0) if i >= 15 else (0, 0)
        sym = NS(valid=valid, levels=lv if valid else (0, 0), signature="-,o",
                 status="" if valid else "not valid here: transient inputs")
        iso = ("leak_ic_engine",) if i >= 30 else ()
        return None, None, NS(symptoms=sym, diagnosis=NS(isolated_faults=iso))

    rep = fault_case_report([step(i) for i in range(40)], feats, "leak_ic_engine", 0.15)
    assert rep["detected"] and rep["delay_valid_segments"] == 3 and rep["within_segments"]
    assert rep["delay_s"] == pytest.approx(16 * 0.015 - 0.15)
    assert rep["first_valid_after_onset_s"] == pytest.approx(14 * 0.015 - 0.15)
    assert rep["isolated_correctly"] and rep["false_symptom_segments_before"] == 0
    assert rep["observable_at_onset"]


def test_stuck_actuators_are_observable_only_below_the_command():
    from fdi_ros.core.types import FeatureVector
    from fdi_ros.plants.diesel.coverage import observable

    def fv(egr, swirl):
        return FeatureVector(plant="diesel", index=0, t_start=0.0, t_end=0.015,
                             alpha_start=0.0, valid=True, status="",
                             names=("egr_cmd", "swirl_cmd"), units=("1", "1"),
                             values=np.array([egr, swirl]))

    assert observable("egr_stuck_open", 0.5, fv(0.0, 0.0))
    assert not observable("egr_stuck_open", 0.5, fv(0.6, 0.0))
    assert observable("swirl_flap_closed", 1.0, fv(0.3, 0.0))
    assert not observable("swirl_flap_closed", 1.0, fv(0.3, 1.0))
    assert observable("leak_ic_engine", 5.0, fv(0.6, 1.0))


def test_fault_effect_against_the_fault_free_twin():
    """The fault's change of each judged residual in threshold units, and whether it crosses a
    threshold the twin stays within; not comparable across regimes or where a run is not
    valid; a residual not judged (infinite threshold) never counts."""
    from fdi_ros.core.symptoms import SymptomState
    from fdi_ros.plants.diesel.coverage import fault_case_report, fault_effect

    rng = np.random.default_rng()
    inf = np.inf

    def st(r, valid=True, regime="a"):
        return SymptomState(0, 0.0, valid, "", ("s_x", "s_y", "s_z"), (0, 0, 0), tuple(r),
                            (-1.0, 0.0, -inf), (3.0, 4.0, inf), (5.0, 8.0, inf),
                            regime=regime)

    # thresholds: x centre 1 half-width 2; y centre 2 half-width 2; z not judged
    free = [st((1.0, 2.0, 0.0)), st((4.5, 2.0, 0.0)), st((1.0, 2.0, 0.0)),
            st((1.0, 2.0, 0.0), valid=False), st((1.0, 2.0, 0.0), regime="b"),
            st((1.0, 2.0, 0.0))]
    z = float(rng.uniform(-1e6, 1e6))
    fault = [st((1.0, 7.0, z)), st((5.5, 2.0, z)), st((2.0, 1.0, z)), st((9.0, 2.0, z)),
             st((9.0, 2.0, z)), st((1.0, 2.0, z), valid=False)]
    effect, shown = fault_effect(fault, free)
    assert effect[:3] == pytest.approx([2.5, 0.5, 0.5])
    assert np.isnan(effect[3:]).all()
    assert shown.tolist() == [True, False, False, False, False, False]
    with pytest.raises(ValueError, match="same drive"):
        fault_effect(fault, free[:-1])

    # the detector's delay counted in segments where the fault shows, from the onset
    from types import SimpleNamespace as NS

    from fdi_ros.core.types import FeatureVector

    n = 30
    feats = [FeatureVector(plant="diesel", index=i, t_start=i * 0.02, t_end=(i + 1) * 0.02,
                           alpha_start=0.0, valid=True, status="", names=("n", "fuel"),
                           units=("rpm", "mg/stroke"), values=np.array([1500.0, 20.0]))
             for i in range(n)]
    det_at = int(rng.integers(12, n))
    shows = np.zeros(n, dtype=bool)
    shows[int(rng.integers(0, 4))] = True            # before the onset: not counted
    picked = rng.choice(np.arange(6, det_at), size=int(rng.integers(0, 4)), replace=False)
    shows[picked] = True
    steps = [(None, None, NS(symptoms=NS(valid=True, levels=(1,) if i >= det_at else (0,),
                                         signature="+"),
                            diagnosis=NS(isolated_faults=())))
             for i in range(n)]
    rep = fault_case_report(steps, feats, "egr_leaky", 0.1, effect=(np.where(shows, 2.0, 0.1),
                                                                      shows))
    assert rep["detectable_segments_to_detection"] == len(picked)
    assert rep["within_segments_detectable"]
    assert rep["max_effect"] == (2.0 if len(picked) else 0.1)
    first = min(picked) if len(picked) else None
    assert rep["first_detectable_after_onset_s"] == (
        None if first is None else pytest.approx((first + 1) * 0.02 - 0.1))
