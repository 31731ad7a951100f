"""The EGR-open fresh-air eta_V from the exhaust side's physics (plants/diesel/egrflow): the
mass balance it solves holds, a closed valve gives the EGR-closed map back, and parameters
drawn at random are recovered from segments the structure generated (with noise)."""

from __future__ import annotations

import random

import numpy as np

from fdi_ros.plants.diesel import egrflow as ef


def _segments(rng: np.random.Generator, n: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    speed = rng.uniform(1000, 3500, n)
    fuel = rng.uniform(5, 35, n)
    T2 = rng.uniform(310, 380, n)
    p2 = 1.0e5 + 1.2e3 * fuel * rng.uniform(0.6, 1.0, n)
    d = {"n": speed, "rho2": p2 / (ef.R_AIR * T2), "T2": T2, "fuel": fuel,
         "egr_cmd": rng.uniform(0.05, 0.8, n), "vgt": rng.uniform(0.1, 0.9, n)}
    eta_tot = 0.88 + 0.03 * np.sin(speed / 600.0) - 0.02 * (d["rho2"] - 1.3)
    return d, eta_tot


def _theta(rng: random.Random) -> tuple[float, ...]:
    return (rng.uniform(1.5e-4, 4e-4), rng.uniform(0.8, 1.5), rng.uniform(3e-4, 5e-4),
            rng.uniform(0.4e-4, 1e-4), rng.uniform(7000, 14000), rng.uniform(0.5e6, 2e6))


def test_mass_balance_and_closed_valve():
    seed = random.randrange(2**32)
    rng = np.random.default_rng(seed)
    d, eta_tot = _segments(rng, 400)
    m = ef.EgrFlowModel(_theta(random.Random(seed)), 2.0, 4)
    f = m.flows(d, eta_tot)
    out = f["m_t"] + f["m_egr"]
    assert np.allclose(out, f["m_cyl"] + f["m_fuel"], rtol=1e-9), seed
    assert np.all(f["p3"] >= f["p4"]), seed
    p2 = d["rho2"] * ef.R_AIR * d["T2"]
    assert np.array_equal(f["m_egr"] < 0, f["p3"] < p2), seed  # back flow below the boost
    shut = {**d, "egr_cmd": np.zeros_like(d["egr_cmd"])}
    assert np.allclose(m.eta_fresh(shut, eta_tot), eta_tot, atol=1e-12), seed
    # more valve, more recirculated gas and less fresh air; where the boost is above the
    # exhaust pressure the valve passes intake air back to the exhaust: more valve, more of
    # it, and more fresh air through the MAF than the cylinders take
    more = {**d, "egr_cmd": d["egr_cmd"] * 1.2}
    a, b = m.eta_fresh(more, eta_tot), m.eta_fresh(d, eta_tot)
    fwd, rev = f["m_egr"] > 0, f["m_egr"] < 0
    assert np.all(a[fwd] < b[fwd]) and np.all(a[rev] > b[rev]), seed
    assert np.all(b[rev] > eta_tot[rev]) and np.all(b[fwd] < eta_tot[fwd]), seed
    assert ef.EgrFlowModel.from_dict(m.to_dict()) == m


def test_closed_valve_exhaust_pressure_in_closed_form_equals_the_solved_balance():
    """With the valve closed p3 solves a quadratic (the turbine alone): the closed form equals
    the bisection of the mass balance, parameters and segments drawn at random; the margin
    p3 - p2 follows (negative where the boost is above the exhaust pressure)."""
    seed = random.randrange(2**32)
    rng = np.random.default_rng(seed)
    d, eta_tot = _segments(rng, 500)
    d["egr_cmd"] = np.zeros(500)
    d["rho2"] = d["rho2"] * rng.uniform(0.8, 1.8, 500)   # boost above the exhaust, some
    m = ef.EgrFlowModel(_theta(random.Random(seed)), 2.0, 4)
    f = m.flows(d, eta_tot)
    np.testing.assert_allclose(m.closed_valve_p3(d, eta_tot), f["p3"], rtol=1e-9)
    margin = m.closed_valve_margin(d, eta_tot)
    np.testing.assert_allclose(margin, f["p3"] - f["p2"], rtol=1e-9, atol=1e-3)
    assert (margin < 0).any() and (margin > 0).any(), seed


def test_closed_valve_leak_is_the_small_valve_opening_limit():
    """A leak of area A across the closed valve lowers the fresh-air eta_V by A times
    ``closed_valve_leak``: equal to the solved balance with the valve opened to that area, in
    the limit of a small area (the leak's own change of p3 neglected), with the backflow's
    sign where the boost is above the exhaust pressure (segments and parameters at random)."""
    seed = random.randrange(2**32)
    rng = np.random.default_rng(seed)
    d, eta_tot = _segments(rng, 400)
    d["rho2"] = d["rho2"] * rng.uniform(0.8, 1.8, 400)
    theta = _theta(random.Random(seed))
    m = ef.EgrFlowModel(theta, 2.0, 4)
    q = m.closed_valve_leak(d, eta_tot)
    area = 1e-3 * theta[0]                       # a thousandth of the open valve's
    tiny = {**d, "egr_cmd": np.full(400, 1e-3 ** (1.0 / theta[1]))}
    drop = eta_tot - m.eta_fresh(tiny, eta_tot)
    margin = m.closed_valve_margin(d, eta_tot)
    assert np.array_equal(q > 0, margin > 0) and (q < 0).any() and (q > 0).any(), seed
    far = np.abs(margin) > 2000.0                # the orifice's root is steep at balance
    np.testing.assert_allclose(area * q[far], drop[far], rtol=0.02, atol=1e-6,
                               err_msg=str(seed))


def test_parameters_drawn_at_random_are_recovered():
    seed = random.randrange(2**32)
    print("seed", seed)
    rng = np.random.default_rng(seed)
    truth = ef.EgrFlowModel(_theta(random.Random(seed)), 2.0, 4)
    d, eta_tot = _segments(rng, 3000)
    y = truth.eta_fresh(d, eta_tot) + rng.normal(0, 0.002, 3000)
    f = ef.fit(d, eta_tot, y, displacement_l=2.0, n_cyl=4)
    assert f.rmse < 0.0025, (seed, f)
    # what the data decide: the predicted fresh air everywhere (the six parameters trade
    # against each other a little); the valve area and exponent themselves to 10 %
    d2, eta2 = _segments(np.random.default_rng(seed + 1), 2000)
    err = f.model.eta_fresh(d2, eta2) - truth.eta_fresh(d2, eta2)
    assert np.sqrt(np.mean(err ** 2)) < 0.001, (seed, f.model.theta, truth.theta)
    got, want = dict(zip(ef.PARAMS, f.model.theta)), dict(zip(ef.PARAMS, truth.theta))
    for k in ("A_e", "gamma"):
        assert abs(got[k] / want[k] - 1) < 0.1, (seed, k, got, want)


def test_the_regime_map_saved_and_loaded_predicts_the_same(tmp_path):
    """An EGR-open regime's eta_V map (the flow model over the base regime's map) written
    beside the regime's data map and read back: the same numbers; a data map without a flow
    model beside it is read as itself."""
    from fdi_ros.core.lolimot import Lolimot

    seed = random.randrange(2**32)
    rng = np.random.default_rng(seed)
    d, eta_tot = _segments(rng, 1500)
    inputs = ("n", "rho2", "egr_cmd", "fuel", "vgt", "T2")
    X = np.column_stack([d[k] for k in inputs])
    base = Lolimot(max_models=4)
    base.fit(X[:, :2], eta_tot)
    flow = ef.EgrFlowModel(_theta(random.Random(seed)), 2.0, 4, port=(0.02, 0.01))
    region = Lolimot(max_models=3)
    region.fit(X, flow.eta_fresh(d, base.predict(X[:, :2])))
    m = ef.EgrFlowEta(flow, base, region, inputs)
    m.save(tmp_path / "eta_v.npz")
    back = ef.EgrFlowEta.load_beside(tmp_path / "eta_v.npz", Lolimot.load(tmp_path / "eta_v.npz"),
                                     base, inputs)
    assert isinstance(back, ef.EgrFlowEta) and back.flow == flow
    probe = X[rng.choice(X.shape[0], 200)] * rng.uniform(0.8, 1.2, (200, len(inputs)))
    assert np.array_equal(back.predict(probe), m.predict(probe))
    # its region: the regime's box of every input (checked apart; the structure carries over
    # beyond its data's (n, rho2) coverage), but not with the valve nearly balanced
    inside = back.in_region(probe)
    assert np.array_equal(inside, m.in_region(probe))
    pd = {k: probe[:, inputs.index(k)] for k in ef.INPUTS}
    f = flow.flows(pd, base.predict(probe[:, :2]))
    dp = f["p3"] - pd["rho2"] * ef.R_AIR * pd["T2"]
    assert np.array_equal(inside, np.abs(dp) >= ef.BALANCED_PA), seed
    why = back.outside(probe)
    assert all((w == "") == ok for w, ok in zip(why, inside)), seed
    assert all("nearly balanced" in w for w, ok in zip(why, inside) if not ok), seed
    assert np.allclose(m.predict(X), flow.eta_fresh(d, base.predict(X[:, :2])), atol=1e-12)
    (tmp_path / "plain").mkdir()
    region.save(tmp_path / "plain" / "eta_v.npz")
    plain = Lolimot.load(tmp_path / "plain" / "eta_v.npz")
    assert ef.EgrFlowEta.load_beside(tmp_path / "plain" / "eta_v.npz", plain, base,
                                     inputs) is plain
