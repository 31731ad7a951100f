"""Validity regions: learned from every input of the identification, checked per segment.

Core oracles on :class:`ValidityRegion`, then the diesel bank as a user meets it: fault-free
operation with the EGR valve open or the swirl flaps closed, at operating points drawn at random
over the map, gives no symptom and no isolation (a valid diagnosis where the bank covers it,
"not valid here" with the reason where it does not).
"""

from __future__ import annotations

import numpy as np
import pytest

from fdi_ros.core.validity import InputRange, ValidityRegion


def test_learned_ranges_are_the_data_ranges_widened_by_the_tolerances():
    rng = np.random.default_rng(1)
    n = rng.uniform(900.0, 3900.0, 500)
    data = {"n": n, "valve": np.zeros(500), "flap": rng.choice([0.0, 1.0], 500)}
    reg = ValidityRegion.learn(data, ("n", "valve", "flap", "absent"),
                               tolerance={"valve": 0.02}, rel_tolerance=0.01)
    assert reg.names == ("n", "valve", "flap")          # absent inputs bound nothing
    assert reg["n"].lo == n.min() and reg["n"].hi == n.max()
    assert reg["n"].tol == pytest.approx(0.01 * np.ptp(n))
    assert reg["valve"].held and reg["valve"].tol == pytest.approx(0.02)
    assert reg.check({"n": 2000.0, "valve": 0.01, "flap": 1.0}) == ""
    why = reg.check({"n": 2000.0, "valve": 0.5, "flap": 0.0})
    assert why.startswith("not valid here") and "valve = 0.5" in why and "held at 0" in why
    assert "n" not in why.split(":")[1].split("=")[0]
    assert "not in the data" in reg.check({"n": 2000.0, "flap": 0.0})
    assert "not finite" in reg.check({"n": float("nan"), "valve": 0.0, "flap": 0.0})
    # vectorised == per row, on points drawn at random around the region
    q = {"n": rng.uniform(500, 4500, 300), "valve": rng.uniform(-0.1, 0.3, 300),
         "flap": rng.uniform(-0.1, 1.1, 300)}
    ok = reg.contains(q, 300)
    reasons = reg.reasons(q, 300)
    for i in range(300):
        one = reg.check({k: float(v[i]) for k, v in q.items()})
        assert (one == "") == bool(ok[i]) and one == reasons[i]
    assert not reg.contains({"n": q["n"]}, 300).any()
    assert ValidityRegion.from_dict(reg.to_dict()) == reg


def test_malformed_regions_are_refused():
    with pytest.raises(ValueError):
        InputRange("x", 2.0, 1.0)
    with pytest.raises(ValueError):
        InputRange("x", 0.0, 1.0, tol=-1.0)
    with pytest.raises(ValueError):
        ValidityRegion((InputRange("x", 0, 1), InputRange("x", 0, 2)))
    with pytest.raises(ValueError):
        ValidityRegion.from_dict({"ranges": [{"name": "x"}]})
    with pytest.raises(ValueError):
        ValidityRegion.learn({"x": [np.nan]}, ("x",))


def _fault_free(n_rpm: float, torque: float, egr: float, swirl: float, seed: int,
                seconds: float = 2.5) -> list:
    from fdi_ros.plants.diesel.plant import DieselIntakePlant, crank_segmenter, fuel_for_torque

    plant = DieselIntakePlant(seed=seed)
    plant.set_inputs(n_rpm=n_rpm, fuel_mg=float(fuel_for_torque(n_rpm, torque, plant.p)),
                     egr_cmd=egr, swirl_cmd=swirl)
    seg = crank_segmenter(plant.p)
    feats: list = []
    while True:
        block = plant.advance(720)
        feats.extend(seg.push_table(block).to_features())
        if block.t[-1] >= seconds:
            return feats


def test_reference_models_carry_the_region_of_every_input(diesel_reference_dir):
    from fdi_ros.plants.diesel.reference import ReferenceModelSet

    mset = ReferenceModelSet.load(diesel_reference_dir)
    assert mset.validity is not None
    assert {"n", "rho2", "egr_cmd", "swirl_cmd"} <= set(mset.validity.names)
    # above the identified speed range (e.g. a 6000 rpm benchmark; the plant itself stops at
    # 5500 rpm): "not valid here", naming the speed
    lo, hi = mset.validity["n"].lo, mset.validity["n"].hi
    inside = {"n": 0.5 * (lo + hi), "rho2": mset.validity["rho2"].lo, "egr_cmd": 0.0,
              "swirl_cmd": 0.0}
    assert mset.validity.check(inside) == ""
    why = mset.validity.check({**inside, "n": 6000.0})
    assert why.startswith("not valid here") and "n = 6000 rpm" in why


def test_fault_free_with_egr_open_or_swirl_closed_gives_no_symptom_no_isolation(diesel_bank):
    """Random points of the speed-load map (a seed drawn at test time, printed), EGR valve open
    or swirl flaps closed (commanded, no fault), at any command and as the ECU's maps command
    them: never a symptom, never a detection; a segment the reference models judged is
    "no_fault" (with the EGR valve open the hypotheses' maps do not hold, and the diagnosis
    said "not_valid" although nothing was wrong); segments the bank does not cover say why."""
    import random

    from fdi_ros.core.diagnoser import diagnose_offline
    from fdi_ros.core.graphconfig import load_graph_config
    from fdi_ros.plants.diesel.ecu import EcuSchedule
    from fdi_ros.plants.diesel.plant import DieselParams, fuel_for_torque
    from fdi_ros.plants.diesel.reference import ReferenceModelSet

    cfg = load_graph_config(diesel_bank)
    mset = ReferenceModelSet.load(cfg.resolve("build/models/diesel"))
    seed = random.randrange(2**32)
    print(f"seed {seed}")
    rng = np.random.default_rng(seed)
    cases = [(float(rng.uniform(1100, 3600)), float(rng.uniform(20, 150)),
              float(rng.uniform(0.2, 1.0)), 0.0) for _ in range(2)]
    cases += [(float(rng.uniform(1100, 3600)), float(rng.uniform(20, 150)), 0.0, 1.0)]
    ecu = EcuSchedule()
    for _ in range(2):   # part load, where the ECU opens the valve (and closes the flaps)
        n, tq = float(rng.uniform(1000, 3400)), float(rng.uniform(30, 120))
        fuel = float(fuel_for_torque(n, tq, DieselParams()))
        cases.append((n, tq, ecu.egr(n, fuel), ecu.swirl(n, fuel)))
    cases += [(2000.0, 130.0, 0.5, 0.0), (2000.0, 130.0, 0.0, 1.0)]   # the reported cases
    cases += [(3450.0, 150.0, 0.02, 0.0)]   # 2 % open (the ECU's ramp): a 3.5 mm leak's flow
    for k, (n, tq, egr, swirl) in enumerate(cases):
        feats = _fault_free(n, tq, egr, swirl, seed=300 + k)
        steps = diagnose_offline(cfg, feats)
        where = f"n={n:.0f} rpm, torque={tq:.0f} Nm, egr_cmd={egr:.2f}, swirl_cmd={swirl:.0f}"
        states = {s.diagnosis.state for _, _, s in steps}
        assert states <= {"no_fault", "not_valid"}, (where, states)
        for _, _, s in steps:
            if s.symptoms.valid:
                assert not any(s.symptoms.levels), (where, s.symptoms)
                assert s.diagnosis.state == "no_fault", (where, s.diagnosis)
            elif feats[0].t_end + 1.5 < s.diagnosis.t:   # past the start-up settling
                assert s.symptoms.status.startswith("not valid here"), (where, s.symptoms)
        held = {r.name for r in mset.validity.ranges if r.held}
        last = steps[-1][2].symptoms
        if not last.valid and (("egr_cmd" in held and egr > 0.005)
                               or ("swirl_cmd" in held and swirl > 0.05)):
            # outside the base regime's held commands and no EGR-open regime covers it
            assert "regime" in last.status or "egr_cmd" in last.status \
                or "swirl_cmd" in last.status or "balanced" in last.status, (where, last)


def test_hypotheses_effect_maps_with_the_egr_valve_open_have_the_physics_sign(diesel_bank):
    """The fault hypotheses carry effect maps of the EGR-open regimes (eta_V judged there
    only): over operating points drawn at random in each regime's part of the map, a leak
    behind the compressor reads as more fresh air (r_eta down), an open crank-case vent and
    a leaky EGR valve as less (up); the residuals not judged there get no effect."""
    import random

    from fdi_ros.core.graphconfig import load_graph_config
    from fdi_ros.core.residual_models import load_residual_model

    cfg = load_graph_config(diesel_bank)
    seed = random.randrange(2**32)
    print(f"seed {seed}")
    rng = np.random.default_rng(seed)
    boxes = {"egr_open_flaps_open": [(2200, 3000), (1.1, 1.5), (5, 20), (0.2, 0.6)],
             "egr_open_flaps_closed": [(1100, 1900), (0.95, 1.4), (3, 20), (0.3, 0.6)]}
    sign = {"leak_ic_engine": -1, "crankcase_vent_open": 1, "egr_leaky": 1}
    for fault, want in sign.items():
        h = load_residual_model(cfg.resolve_spec(cfg.entry(fault).model), model_id=fault)
        for regime, box in boxes.items():
            assert h.covers(regime) and not h.covers(regime + "/transient")
            X = np.column_stack([rng.uniform(a, b, 200) for a, b in box])
            G = h.direction(X, regime)
            assert np.sign(np.median(G[:, 0])) == want, (fault, regime, np.median(G[:, 0]))
            assert not G[:, 1:].any(), (fault, regime)


def test_a_tip_in_that_closes_the_egr_valve_is_no_leak(diesel_bank):
    """The ECU closes the EGR valve when the driver asks for full load: the segments after it
    are "not valid" while the boost temperature falls fast, then "transient" (judged by the
    fault-free transients' thresholds) until the manifold gas and the T2 sensor have settled:
    no symptom (they read as a leak for a second with the quasi-stationary thresholds); the
    batch path and the segment-by-segment path agree."""
    from fdi_ros.core.diagnoser import diagnose_offline
    from fdi_ros.core.graphconfig import load_graph_config
    from fdi_ros.plants.diesel.identify import simulate_features
    from fdi_ros.plants.diesel.scenario import load_scenario

    cfg = load_graph_config(diesel_bank)
    rng = np.random.default_rng(17)
    n = float(rng.uniform(1900.0, 3200.0))
    sc = load_scenario({"name": "tip_in", "inputs": {"kind": "points", "ecu": {}, "points": [
        {"t": 0.0, "n": n, "torque": 50}, {"t": 2.5, "n": n, "torque": 50},
        {"t": 2.9, "n": n, "torque": 185}, {"t": 7.5, "n": n, "torque": 185}]}})
    assert sc.inputs_at(1.0)[2] > 0.3 and sc.inputs_at(4.0)[2] == 0.0
    feats, _ = simulate_features(sc, seed=int(rng.integers(1000)))
    fast = diagnose_offline(cfg, feats)
    slow = diagnose_offline(cfg, feats, batch=False)
    for (fv, _, a), (_, _, b) in zip(fast, slow):
        assert (a.symptoms.valid, a.symptoms.status, a.symptoms.levels) == \
            (b.symptoms.valid, b.symptoms.status, b.symptoms.levels)
        assert not (a.symptoms.valid and any(a.symptoms.levels)), (n, fv.t_end, a.symptoms)
        if 3.0 < fv.t_end < 5.5:   # within 3 s of the valve closing
            assert not a.symptoms.valid or a.symptoms.regime.endswith("/transient")
    assert any("changing too fast" in s.symptoms.status for _, _, s in fast)
    assert any(s.symptoms.valid and s.symptoms.regime.endswith("/transient")
               for _, _, s in fast if 3.0 < s.diagnosis.t < 5.5)
    # settled again: the quasi-stationary thresholds
    assert any(s.symptoms.valid and s.symptoms.regime == "egr_closed_flaps_open"
               for _, _, s in fast if s.diagnosis.t > 6.5)
    assert {s.diagnosis.state for _, _, s in fast} <= {"no_fault", "not_valid"}


def test_hard_tip_ins_and_tip_outs_drawn_at_random_give_no_symptom(diesel_bank):
    """A hard driver, drawn at random (seed printed): at a random speed from part load to
    near full load in 0.2-1 s and back, the ECU closing and opening the EGR valve, switching
    the flaps, the boost controller saturating the VGT. No symptom, no isolation, wherever the
    segments are judged (the calibration's own tip-ins are another seed: 7 of 16 such cases
    gave a false symptom without them, 8 of 16 before the lags were undone); the batch and the
    step-wise paths agree."""
    import secrets

    from fdi_ros.core.diagnoser import diagnose_offline
    from fdi_ros.core.graphconfig import load_graph_config
    from fdi_ros.plants.diesel.drive import tips_document
    from fdi_ros.plants.diesel.identify import simulate_features
    from fdi_ros.plants.diesel.scenario import load_scenario

    seed = secrets.randbelow(2 ** 31)
    print(f"seed {seed}")
    cfg = load_graph_config(diesel_bank)
    sc = load_scenario(tips_document(seed=seed, events=2, name="tips"))
    feats, _ = simulate_features(sc, seed=seed % 1000)
    fast = diagnose_offline(cfg, feats)
    slow = diagnose_offline(cfg, feats, batch=False)
    judged = 0
    for (fv, _, a), (_, _, b) in zip(fast, slow):
        assert (a.symptoms.valid, a.symptoms.levels) == (b.symptoms.valid, b.symptoms.levels)
        assert not (a.symptoms.valid and any(a.symptoms.levels)), (seed, fv.t_end, a.symptoms)
        judged += a.symptoms.valid
    assert judged > 0.3 * len(fast)
    assert {s.diagnosis.state for _, _, s in fast} <= {"no_fault", "not_valid"}


def test_faults_opened_at_random_on_the_realistic_drive_are_never_isolated_wrong(diesel_bank):
    """Three of the six faults, each opened at a random time of the realistic drive (seed
    printed), in whatever regime the drive is then: no symptom before it, and an isolation,
    if any, names it (312 such draws measured: 0 wrong). The table is measured at one operating
    point: elsewhere a fault shows fewer of its symptoms (the stuck valve at 4400 rpm s_eta
    alone, which is the vent's exact row: it was isolated as the vent), so every fault whose
    row shows the observed symptoms competes, and a close runner-up or a norm hardly below the
    nominal model's blocks the isolation."""
    import dataclasses
    import os
    import secrets

    from fdi_ros.core.diagnoser import diagnose_offline
    from fdi_ros.core.graphconfig import load_graph_config
    from fdi_ros.core.types import FaultEvent
    from fdi_ros.plants.diesel.coverage import REALISTIC_DRIVE
    from fdi_ros.plants.diesel.drive import DRIVE_FAULT_SIZES, window
    from fdi_ros.plants.diesel.identify import simulate_features
    from fdi_ros.plants.diesel.plant import FAULT_UNITS
    from fdi_ros.plants.diesel.scenario import load_cases

    cfg = load_graph_config(diesel_bank)
    drive = load_cases(cfg.resolve(REALISTIC_DRIVE))[0]
    seed = int(os.environ.get("FDI_TEST_SEED") or secrets.randbelow(2**32))
    print(f"seed {seed}")
    rng = np.random.default_rng(seed)
    for fault in rng.choice(sorted(DRIVE_FAULT_SIZES), 3, replace=False):
        fault = str(fault)
        onset = float(rng.uniform(30.0, drive.duration_s - 20.0))
        sc = dataclasses.replace(window(drive, onset - 4.0, onset + 10.0), faults=(
            FaultEvent(t=4.0, fault=fault, size=DRIVE_FAULT_SIZES[fault],
                       size_unit=FAULT_UNITS[fault]),))
        feats, _ = simulate_features(sc, seed=int(rng.integers(10_000)))
        steps = diagnose_offline(cfg, feats)
        where = (seed, fault, round(onset, 2))
        for fv, _, s in steps:
            if fv.t_end < 4.0:
                assert not (s.symptoms.valid and any(s.symptoms.levels)), (where, fv.t_end)
            assert set(s.diagnosis.isolated_faults) <= {fault}, (where, s.diagnosis)
