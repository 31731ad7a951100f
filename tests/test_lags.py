"""The dynamics the static reference models undo or respect: the T2 sensor's lag and the VGT
vanes' lag are identified from fault-free data (oracle: the plant's own time constants), and
an EGR valve below the boost pressure passes intake gas back (the plant and the EGR flow model
agree on it)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fdi_ros.plants.diesel import egrflow
from fdi_ros.plants.diesel.plant import FAULT_IDS, DieselIntakePlant, DieselParams, _area


def test_identified_lags_are_the_plants(diesel_reference_dir):
    """The bank's reference models were identified without access to the plant's parameters:
    the T2 sensor's time constant within 5 % of the plant's (0.8 s), the VGT vanes' within
    40 % of theirs (0.12 s; the estimate ``cmd - tau d(cmd)/dt`` is a first-order one), and
    both are undone on line: ``compensate`` moves T2 by ``tau T2_rate`` and the VGT command
    back by ``tau_vgt vgt_rate``."""
    from fdi_ros.plants.diesel.reference import ReferenceModelSet

    p = DieselParams()
    m = ReferenceModelSet.load(diesel_reference_dir)
    assert m.t2_tau == pytest.approx(p.tau_T2, rel=0.05)
    assert m.vgt_tau == pytest.approx(p.tau_vgt, rel=0.4)
    rng = np.random.default_rng()
    d = {"T2": rng.uniform(300, 450, 50), "T2_rate": rng.normal(0, 30, 50),
         "rho2": rng.uniform(1, 2.5, 50), "eta_v": rng.uniform(0.5, 1.0, 50),
         "vgt": rng.uniform(0.2, 0.8, 50), "vgt_rate": rng.normal(0, 0.5, 50)}
    c = m.compensate(d)
    np.testing.assert_allclose(c["T2"], d["T2"] + m.t2_tau * d["T2_rate"])
    np.testing.assert_allclose(c["rho2"] * c["T2"], d["rho2"] * d["T2"])
    np.testing.assert_allclose(c["vgt"], np.clip(d["vgt"] - m.vgt_tau * d["vgt_rate"], 0, 1))
    # without the rate the command stays as it is (e.g. a bag recorded before the feature)
    d.pop("vgt_rate")
    np.testing.assert_array_equal(m.compensate(d)["vgt"], d["vgt"])


@pytest.mark.parametrize("seed", range(3))
def test_a_valve_below_the_boost_pressure_passes_intake_gas_back(seed):
    """At a random boost pressure above the exhaust manifold's (a tip-in that opens the
    turbine, the boost still high), the plant's EGR flow is negative and carries the intake's
    gas: ``-A_egr sqrt(2 rho2 (p2 - p3))`` with ``rho2 = p2 / (R T2)``; the exhaust side's
    balance holds; the EGR flow model, given the plant's own parameters, says the same."""
    rng = np.random.default_rng(seed)
    p = DieselParams()
    plant = DieselIntakePlant(params=p, noise=False)
    n, fuel, egr = rng.uniform(1200, 3000), rng.uniform(3, 10), rng.uniform(0.3, 0.6)
    plant.set_inputs(n_rpm=n, fuel_mg=fuel, egr_cmd=egr)
    plant.advance(720)
    x = dict(plant._x)
    x["vgt"] = 0.0                         # vanes open: the exhaust pressure stays low
    inp = {"n": n, "fuel": fuel, "egr_cmd": egr, "swirl_cmd": 0.0}
    p2 = rng.uniform(1.5e5, 2.2e5)
    a = plant._algebra(p2, inp, dict.fromkeys(FAULT_IDS, 0.0), x)
    assert a["p3"] < p2 - 10 * p.dp_lin
    T2 = x["T2"]
    a_e = p.Cd_egr * _area(p.d_egr * 1e3) * egr
    want = -a_e * math.sqrt(2.0 * p2 / (p.R * T2)) * math.sqrt(p2 - a["p3"])
    assert a["m_egr"] == pytest.approx(want, rel=1e-6)
    assert a["m_t"] + a["m_egr"] == pytest.approx(a["m_cyl"] + a["m_fuel"], rel=1e-6)
    # the flow model with the plant's parameters (gamma 1, its turbine and exhaust heat)
    flow = egrflow.EgrFlowModel((p.Cd_egr * _area(p.d_egr * 1e3), 1.0, p.A_t_open,
                                 p.A_t_closed, p.f_exh * p.LHV / p.cp_e, p.k_exh), 2.0, 4)
    rho2 = p2 / (p.R * T2)
    d = {"n": np.array([n]), "rho2": np.array([rho2]), "T2": np.array([T2]),
         "fuel": np.array([fuel]), "egr_cmd": np.array([egr]), "vgt": np.array([0.0])}
    f = flow.flows(d, np.array([a["m_cyl"] / (rho2 * 2e-3 * n / 120.0)]))
    assert f["p3"][0] == pytest.approx(a["p3"], rel=2e-3)
    assert f["m_egr"][0] == pytest.approx(a["m_egr"], rel=2e-2)
