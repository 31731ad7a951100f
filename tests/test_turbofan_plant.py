"""Turbofan simulator: design point, paper's scale, physical plausibility, faults, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from fdi_ros.plants.turbofan import plant as tfp

C0 = np.array(tfp.PAPER_CONDITION)


@pytest.fixture(scope="module")
def tf():
    return tfp.Turbofan()


def _q(**changes) -> np.ndarray:
    p = np.zeros(10)
    for name, v in changes.items():
        p[tfp.QUALITY_NAMES.index(name)] = v
    return p


def test_design_point_and_schedule(tf):
    x = tf.trim(tf.WF0, C0, np.zeros(10))
    np.testing.assert_allclose(x, [10700.0, 14150.0], atol=0.01)
    assert tf.scheduled_fuel(C0) == pytest.approx(tf.WF0, rel=1e-6)
    comp = tf.components(x, tf.WF0, C0, np.zeros(10))
    assert comp["T4"] == pytest.approx(tf.k.T4_0)
    # power balances close at equilibrium (the state equations are the balances)
    assert tf.k.eta_m * comp["P_lpt"] == pytest.approx(comp["P_fan"], rel=1e-9)
    assert tf.k.eta_m * comp["P_hpt"] == pytest.approx(comp["P_comp"], rel=1e-9)


def test_paper_scale_under_the_transient_input(tf):
    wf = tfp.paper_input(tf.scheduled_fuel(C0))
    health = tfp.Health(manufacturing=tfp.PAPER_MANUFACTURING, deterioration=0.1)
    r = tf.simulate(wf, C0, health.quality(), rng=np.random.default_rng(0))
    assert r["x"].shape == (1000, 2) and r["t"][1] == pytest.approx(0.02)
    nl, nh, nldot = r["x"][:, 0], r["x"][:, 1], r["xdot"][:, 0]
    assert nl.min() > 10400 and nl.max() < 10950
    assert nh.min() > 13850 and nh.max() < 14450
    assert 150 < np.abs(nldot).max() < 320
    noise = r["y"][:, 0] - nl
    assert noise.std() == pytest.approx(tf.k.noise_xnl, rel=0.15)
    # seeded noise is reproducible
    r2 = tf.simulate(wf, C0, health.quality(), rng=np.random.default_rng(0))
    np.testing.assert_array_equal(r["y"], r2["y"])


def test_rk4_states_match_a_fine_reference(tf):
    wf = tfp.paper_input(tf.scheduled_fuel(C0), duration_s=2.0)
    coarse = tf.simulate(wf, C0, np.zeros(10), noise=False)["x"]
    fine = tfp.Turbofan(constants=tfp.PlantConstants(Ts=0.002))
    ref = fine.simulate(np.repeat(wf, 10), C0, np.zeros(10), noise=False)["x"][::10]
    assert np.abs(coarse - ref).max() < 0.05  # rpm


@pytest.mark.parametrize("changes, spool, sign", [
    ({"fan_eff": -0.01}, 0, -1),   # fan needs more power at the same speed: fan slows
    ({"lpt_eff": -0.01}, 0, -1),   # LP turbine gives less power: fan slows
    ({"hub_eff": -0.01}, 1, -1),   # compressor hub needs more power: core slows
    ({"hpt_eff": -0.01}, 1, -1),   # HP turbine gives less power: core slows
    ({"fan_flow": -0.01}, 0, +1),  # less fan flow absorbs less power: fan speeds up
])
def test_quality_changes_move_speeds_plausibly(tf, changes, spool, sign):
    wf = tf.scheduled_fuel(C0)
    x0 = tf.trim(wf, C0, np.zeros(10))
    x1 = tf.trim(wf, C0, _q(**changes))
    assert np.sign(x1[spool] - x0[spool]) == sign
    assert abs(x1[spool] - x0[spool]) > 2.0


def test_fuel_and_altitude_responses(tf):
    wf = tf.scheduled_fuel(C0)
    x0 = tf.trim(wf, C0, np.zeros(10))
    assert np.all(tf.trim(1.05 * wf, C0, np.zeros(10)) > x0 + 50)
    high = C0.copy()
    high[0] = 17500.0
    # thinner, colder air: less fuel holds the scheduled corrected fan speed
    assert tf.scheduled_fuel(high) < wf
    assert tf.trim(wf, high, np.zeros(10))[0] > x0[0]


def test_fault_sizes_grow_and_reach_the_papers_scale(tf):
    wf = tf.scheduled_fuel(C0)
    x0 = tf.trim(wf, C0, np.zeros(10))
    for kind in ("fan", "hub"):
        shifts = [x0[0] - tf.trim(wf, C0, tfp.Health(faults={kind: s}).quality())[0]
                  for s in ("small", "medium", "large")]
        assert 10 < shifts[0] < shifts[1] < shifts[2] < 140, (kind, shifts)
    # the paper's manufacturing variation moves XN2 by less than a small fault
    man = abs(tf.trim(wf, C0, tfp.PAPER_MANUFACTURING)[0] - x0[0])
    small = x0[0] - tf.trim(wf, C0, tfp.Health(faults={"fan": "small"}).quality())[0]
    assert man < 0.5 * small


def test_health_and_bad_input(tf):
    h = tfp.Health(deterioration=0.5, faults={"fan": "medium"})
    np.testing.assert_allclose(h.quality(), 0.5 * tfp.DETERIORATION_FULL
                               + 2.0 * tfp.fault_vector("fan"))
    with pytest.raises(ValueError, match="unknown fault"):
        tfp.Health(faults={"valve": "small"})
    with pytest.raises(ValueError, match="size"):
        tfp.Health(faults={"fan": "huge"})
    with pytest.raises(ValueError, match="deterioration"):
        tfp.Health(deterioration=1.5)
    bad = C0.copy()
    bad[0] = 30000.0
    with pytest.raises(ValueError, match="ALT"):
        tf.simulate(np.full(10, 0.2), bad, np.zeros(10), noise=False)
    with pytest.raises(ValueError, match="fuel"):
        tf.simulate(np.array([0.2, np.nan]), C0, np.zeros(10), noise=False)
    with pytest.raises(ValueError, match="rng"):
        tf.simulate(np.full(10, 0.2), C0, np.zeros(10))
    with pytest.raises(ValueError, match="equilibrium"):
        tf.trim(50.0, C0, np.zeros(10))
