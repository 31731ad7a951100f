"""Diesel intake plant: operating point, eta_V oracle, pulsation physics, the six faults."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from fdi_ros.core.types import FaultEvent
from fdi_ros.plants.diesel.plant import (
    CHANNELS,
    FAULT_IDS,
    UNITS,
    DieselIntakePlant,
    DieselParams,
    crank_segmenter,
    fuel_for_torque,
)
from fdi_ros.plants.diesel.scenario import load_cases, load_scenario, simulate

ROOT = Path(__file__).resolve().parents[1]
SCEN = ROOT / "config" / "scenarios"
P = DieselParams()
FUEL_130 = float(fuel_for_torque(2000.0, 130.0, P))


def _steady(n=2000.0, fuel=FUEL_130, *, faults=(), seconds=6.0, seed=0, noise=True,
            window=2.0, egr=0.0, swirl=0.0):
    """Run at constant inputs; mean features of the last ``window`` seconds and the truth."""
    plant = DieselIntakePlant(seed=seed, noise=noise)
    plant.set_inputs(n_rpm=n, fuel_mg=fuel, egr_cmd=egr, swirl_cmd=swirl)
    for ev in faults:
        plant.inject(ev)
    per_s = int(round(6.0 * n))          # deg CA per second at 1 deg CA sampling
    block = plant.advance(int(seconds * per_s))
    tab = crank_segmenter(plant.p).push_table(block)
    m = tab.t_start > seconds - window
    assert tab.valid[m].all()
    feats = {k: float(np.mean(tab.column(k)[m])) for k in tab.names}
    return feats, plant.truth()


@pytest.fixture(scope="module")
def base():
    return _steady()


def test_paper_operating_point(base):
    # DESIGN.md A: 2000 rpm, 130 Nm -> p2 ~ 1.5 bar, ~165 kg/h air, eta_V ~ 0.84, T2 ~ 320 K
    f, tr = base
    assert f["p2"] == pytest.approx(1.5e5, rel=0.02)
    assert f["maf"] == pytest.approx(165.0, rel=0.03)
    assert f["eta_v"] == pytest.approx(0.84, abs=0.015)
    assert f["T2"] == pytest.approx(320.0, abs=6.0)
    assert f["n"] == pytest.approx(2000.0, abs=0.5)
    assert tr["p2"] == pytest.approx(tr["p2_sp"], rel=2e-3)       # boost controller settled


@pytest.mark.parametrize("n,torque", [(2000.0, 130.0), (1200.0, 60.0), (3200.0, 150.0)])
def test_steady_eta_from_sensor_means_within_one_percent_of_truth(n, torque):
    f, tr = _steady(n, float(fuel_for_torque(n, torque, P)), seconds=5.0, window=1.5)
    assert f["eta_v"] == pytest.approx(tr["eta_v"], rel=0.01)
    # and the crank front end recovers the plant's true first harmonics (noise averaged out)
    assert f["maf_amp"] == pytest.approx(tr["maf_amp"], rel=0.02, abs=0.05)
    assert f["p2_amp"] == pytest.approx(tr["p2_amp"], rel=0.02, abs=20.0)


def test_noise_free_features_equal_plant_harmonics():
    f, tr = _steady(seconds=4.0, noise=False, window=0.5)
    assert f["maf_amp"] == pytest.approx(tr["maf_amp"], rel=1e-3)
    assert f["maf_phase"] == pytest.approx(tr["maf_phase"], abs=0.05)
    assert f["p2_phase"] == pytest.approx(tr["p2_phase"], abs=0.05)


def test_block_channels_units_and_crank_timing():
    plant = DieselIntakePlant(seed=1)
    plant.set_input_profile(lambda t: (1500.0 + 1000.0 * min(t, 1.0), 20.0, 0.0, 0.0))
    b = plant.advance(9000)
    assert b.channels == CHANNELS and b.units == UNITS and b.plant == "diesel"
    assert np.all(np.diff(b.alpha) == 1.0) and np.all(np.diff(b.t) > 0)
    # d(alpha)/dt = 6 n [deg CA/s, rpm]: crank timing consistent with the speed ramp
    rate = np.diff(b.alpha) / np.diff(b.t)
    n_mid = 0.5 * (b.channel("n")[1:] + b.channel("n")[:-1])
    assert np.allclose(rate, 6.0 * n_mid, rtol=2e-3)
    b2 = plant.advance(100)
    assert b2.alpha[0] == b.alpha[-1] + 1.0 and b2.index == b.index + 1
    # a step change of the held inputs between blocks keeps the time axis monotone
    plant.set_inputs(n_rpm=900.0, fuel_mg=5.0)
    b3 = plant.advance(3000)
    t_all = np.concatenate([b2.t, b3.t])
    assert np.all(np.diff(t_all) > 0)
    assert np.diff(b3.t)[-1] == pytest.approx(1.0 / (6 * 900.0), rel=1e-6)


def test_seeded_runs_are_reproducible():
    d = dataclasses.replace(load_scenario(SCEN / "diesel_paper_op.yaml"), duration_s=4.0)
    r1 = simulate(d, seed=3, features=False)
    r2 = simulate(d, seed=3, features=False)
    r3 = simulate(d, seed=4, features=False)
    a1, a2, a3 = r1.arrays(), r2.arrays(), r3.arrays()
    assert np.array_equal(a1["maf"], a2["maf"])
    assert not np.array_equal(a1["maf"], a3["maf"])
    assert np.allclose(r1.truth["eta_v"], r3.truth["eta_v"])     # noise only differs


@pytest.mark.parametrize("seconds", [3.0, 7.3])
def test_chunked_simulation_gives_the_samples_and_features_of_the_scenario_blocks(seconds):
    """A features-only run advances the plant many blocks at a time (less overhead per
    block); its noise is drawn per scenario block, so samples, segments and the end of the run
    are those of the block-by-block run (up to rounding)."""
    from fdi_ros.plants.diesel.scenario import iter_simulate

    sc = dataclasses.replace(load_cases(SCEN / "diesel_realistic_drive.yaml")[0],
                             duration_s=seconds)
    one = [b for b, _ in iter_simulate(sc, seed=5)]
    many = [b for b, _ in iter_simulate(sc, seed=5, chunk=7)]
    t1, tm = (np.concatenate([b.t for b in bs]) for bs in (one, many))
    assert t1.size == tm.size and t1[-1] >= seconds > t1[-1 - one[0].t.size]
    assert np.allclose(t1, tm, rtol=0, atol=1e-9)
    v1, vm = (np.concatenate([b.values for b in bs], axis=1) for bs in (one, many))
    assert np.allclose(v1, vm, rtol=1e-12, atol=1e-9)      # same noise, same order
    f1 = simulate(sc, seed=5, keep_blocks=True).features     # block by block
    fm = simulate(sc, seed=5, keep_blocks=False).features    # chunked
    assert np.array_equal(f1.index, fm.index)
    assert np.allclose(f1.values, fm.values, rtol=1e-10, atol=1e-9, equal_nan=True)


def test_maf_pulsation_peaks_near_2000_rpm_and_phase_falls_with_speed():
    # air-path resonance (Helmholtz-like: duct inertance vs. volumes) near the 180 deg CA
    # fundamental at 2000 rpm (66.7 Hz)
    speeds = [1000.0, 1500.0, 2000.0, 2500.0, 3000.0, 3500.0]
    amps, phases = [], []
    for n in speeds:
        plant = DieselIntakePlant(noise=False)
        plant.set_inputs(n_rpm=n, fuel_mg=float(fuel_for_torque(n, 100.0, P)))
        plant.advance(int(6 * n * 2.5))
        tr = plant.truth()
        amps.append(tr["maf_amp"])
        phases.append(tr["maf_phase"])
    assert speeds[int(np.argmax(amps))] == 2000.0
    assert amps[2] > 1.3 * amps[0] and amps[2] > 3 * amps[-1]
    # the phase lag grows with speed (duct propagation, resonance, sensor lag): monotone once
    # unwrapped (period 180 deg CA), by more than 90 deg CA across the resonance
    ph = np.unwrap(np.asarray(phases), period=180.0)
    assert np.all(np.diff(ph) < 0) and ph[0] - ph[-1] > 90.0


def _fault(fid, size, unit, seconds=7.0):
    ev = FaultEvent(t=3.0, fault=fid, size=size, size_unit=unit)
    return _steady(faults=[ev], seconds=seconds, window=2.0)


def test_crankcase_vent_open_lowers_metered_air_and_eta(base):
    # Physics: the boost controller holds p2, so the engine still draws m_cyl; the compressor
    # therefore takes the same flow, but part of it now enters through the opening after the
    # MAF (both paths share p_amb - p1: m_vent / m_maf = Cd A_v sqrt(2 rho) / sqrt(rho/k_af)).
    # The metered air and hence the measured eta_V = maf / m_th fall (r_eta > 0).
    f0, _ = base
    f, tr = _fault("crankcase_vent_open", 12.0, "mm")
    assert tr["m_vent"] > 0.0
    assert f["maf"] < f0["maf"] - 0.8 * 3600 * tr["m_vent"] + 3.0
    assert f["eta_v"] < f0["eta_v"] - 0.05
    assert f["p2"] == pytest.approx(f0["p2"], rel=2e-3)


def test_leak_ic_engine_raises_metered_air_and_eta(base):
    # Physics: the leak orifice after the intercooler vents m_leak to ambient; p2 is held by
    # the controller, so the engine flow is unchanged and the compressor (and the MAF) must
    # deliver m_cyl + m_leak: measured eta_V rises by m_leak / m_th (r_eta < 0), more for a
    # larger diameter (orifice area ~ d^2).
    f0, _ = base
    rises = []
    for d in (4.0, 7.0):
        f, tr = _fault("leak_ic_engine", d, "mm")
        assert tr["m_leak"] > 0.0
        assert f["maf"] - f0["maf"] == pytest.approx(3600 * tr["m_leak"], rel=0.15)
        assert f["p2"] == pytest.approx(f0["p2"], rel=2e-3)
        rises.append(f["eta_v"] - f0["eta_v"])
    assert 0.02 < rises[0] < rises[1]
    assert rises[1] / rises[0] == pytest.approx((7.0 / 4.0) ** 2, rel=0.25)


def test_restriction_damps_pulsation_but_not_mean_flow(base):
    # Physics: the restriction adds a quadratic loss between intercooler and manifold; the
    # controller raises the compressor pressure to hold p2, so the mean flows (eta_V) stay.
    # Acoustically it is a series resistance R = 2 dp / m_d in the pipe that carries the
    # air-path resonance excited at 2000 rpm: more damping -> smaller pulsation of the flow
    # reaching the MAF and of the manifold pressure.
    f0, _ = base
    f, tr = _fault("restriction_ic_engine", 0.7, "1")
    assert tr["p_ic"] - tr["p2"] > 1500.0            # the loss is really there
    assert f["eta_v"] == pytest.approx(f0["eta_v"], rel=4e-3)
    assert f["maf_amp"] < 0.7 * f0["maf_amp"]
    assert f["p2_amp"] < 0.7 * f0["p2_amp"]


def test_swirl_flap_closed_filters_the_suction(base):
    # Physics: closing the filling ports leaves only the swirl ports; the port loss rises and
    # with the cylinder volume forms a first-order lag (tau = R_port C_cyl) on the suction
    # pulses: their fundamental at the manifold becomes smaller and later (phase lag), and
    # the share of the port loss left at inlet valve closing lowers the charge a little.
    f0, _ = base
    f, tr = _fault("swirl_flap_closed", 1.0, "1")
    assert tr["fault:swirl_flap_closed"] == 1.0
    assert f["p2_amp"] < 0.9 * f0["p2_amp"]
    assert f["maf_amp"] < 0.95 * f0["maf_amp"]
    assert f["p2_phase"] < f0["p2_phase"] - 3.0
    assert -0.05 < f["eta_v"] - f0["eta_v"] < 0.0


def test_egr_stuck_open_displaces_fresh_air(base):
    # Physics: p3 > p2, so the open valve lets exhaust gas into the manifold; at the held p2
    # the cylinders' gas flow barely changes, but a large part of it is now recirculated
    # gas: fresh (metered) air and the measured eta_V drop strongly (r_eta ++), and the hot
    # EGR raises T2.
    f0, _ = base
    f, tr = _fault("egr_stuck_open", 0.5, "1")
    assert tr["m_egr"] > 0.15 * tr["m_cyl"]
    assert f["eta_v"] < f0["eta_v"] - 0.1
    assert f["maf"] < 0.8 * f0["maf"]
    assert f["T2"] > f0["T2"] + 10.0


def test_egr_leaky_is_a_small_egr_flow(base):
    # Physics: a leak past the closed valve is a small orifice from p3 to p2: the same
    # direction as an open valve, scaled by the leak area.
    f0, _ = base
    f3, tr3 = _fault("egr_leaky", 3.0, "mm")
    f5, tr5 = _fault("egr_leaky", 5.0, "mm")
    assert 0.0 < tr3["m_egr"] < tr5["m_egr"] < 0.1 * tr5["m_cyl"]
    assert f5["eta_v"] < f3["eta_v"] < f0["eta_v"] - 0.008
    assert f5["T2"] > f0["T2"]


def test_ramp_profile_and_simultaneous_faults():
    plant = DieselIntakePlant(noise=False)
    plant.set_inputs(n_rpm=2000.0, fuel_mg=FUEL_130)
    plant.inject(FaultEvent(t=1.0, fault="leak_ic_engine", size=6.0, size_unit="mm",
                            profile="ramp", ramp_s=2.0))
    plant.inject(FaultEvent(t=1.0, fault="crankcase_vent_open", size=8.0, size_unit="mm"))
    plant.advance(int(12000 * 2.0))
    tr = plant.truth()
    assert tr["fault:leak_ic_engine"] == pytest.approx(3.0, abs=0.05)    # half-way up
    assert tr["fault:crankcase_vent_open"] == 8.0
    assert tr["m_leak"] > 0 and tr["m_vent"] > 0
    plant.inject(FaultEvent(t=2.5, fault=""))                             # clear all
    plant.advance(12000)
    tr = plant.truth()
    assert tr["m_leak"] == 0.0 and tr["m_vent"] == 0.0


def test_bad_input_is_rejected():
    plant = DieselIntakePlant()
    with pytest.raises(ValueError, match="unknown diesel fault"):
        plant.inject(FaultEvent(t=0.0, fault="turbo_on_fire"))
    with pytest.raises(ValueError, match="sized in 'mm'"):
        plant.inject(FaultEvent(t=0.0, fault="leak_ic_engine", size=5.0, size_unit="1"))
    with pytest.raises(ValueError, match="outside"):
        plant.inject(FaultEvent(t=0.0, fault="restriction_ic_engine", size=1.5))
    with pytest.raises(ValueError, match="engine speed"):
        plant.set_inputs(n_rpm=9000.0, fuel_mg=10.0)
    with pytest.raises(ValueError, match="finite"):
        plant.set_inputs(n_rpm=float("nan"), fuel_mg=10.0)
    with pytest.raises(ValueError):
        DieselIntakePlant(dalpha_deg=0.0)
    with pytest.raises(ValueError, match="unknown scenario keys"):
        load_scenario({"inputs": {"kind": "points", "points": [{"t": 0, "n": 2000,
                                                                   "fuel": 10}]},
                       "speed": 3})
    with pytest.raises(ValueError, match="exactly one"):
        load_scenario({"inputs": {"kind": "points", "points": [{"t": 0, "n": 2000}]}})
    with pytest.raises(FileNotFoundError):
        load_scenario(SCEN / "no_such_file.yaml")


def test_delivered_scenarios_load_and_cover_all_faults():
    names = sorted(p.name for p in SCEN.glob("diesel_*.yaml"))
    for fid in FAULT_IDS:
        assert f"diesel_fault_{fid}.yaml" in names
    for p in SCEN.glob("diesel_*.yaml"):
        for sc in load_cases(p):
            assert sc.duration_s > 0
    ident = load_scenario(SCEN / "diesel_ident.yaml")
    assert ident.n.min() <= 800 and ident.n.max() >= 4000 and ident.duration_s > 180
    assert np.all(ident.egr_cmd == 0) and np.all(ident.swirl_cmd == 0)
    drive = load_scenario(SCEN / "diesel_drive.yaml")
    assert drive.duration_s >= 600 and not drive.faults


def test_simulate_command_writes_bag_and_csv(tmp_path):
    from fdi_ros import bag
    from fdi_ros.cli import main

    out, csv = tmp_path / "bag", tmp_path / "run.csv"
    rc = main(["simulate", str(SCEN / "diesel_fault_leak_ic_engine.yaml"), "--out", str(out),
               "--csv", str(csv), "--duration", "0.5", "--features"])
    assert rc == 0
    blocks = bag.read_blocks(out)
    assert blocks and blocks[0].channels == CHANNELS
    assert len(bag.read_faults(out)) == 6
    assert bag.read_features(out)
    header = csv.read_text().splitlines()[0].split(",")
    assert header == ["t", "alpha", "n", "p2", "T2", "maf", "fuel", "egr_cmd", "swirl_cmd",
                      "vgt"]
    rows = np.loadtxt(csv, delimiter=",", skiprows=1)
    assert rows.shape[0] == sum(b.t.size for b in blocks)
    assert main(["simulate", str(SCEN / "diesel_paper_op.yaml")]) == 2      # no output given
