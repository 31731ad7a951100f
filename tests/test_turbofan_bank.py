"""Turbofan node/global models, the 16-model bank, its residual model and the diagnosis runs.

A small grid (one operating condition, three deterioration nodes, all fault sizes: 48 nodes)
keeps training to a few seconds; the full grid is trained by ``fdi-ros train turbofan``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from fdi_ros.core.supervisor import ExpertSupervisor, models_online
from fdi_ros.core.types import FeatureVector
from fdi_ros.plants import load_residual_model
from fdi_ros.plants.turbofan import bank as tfb
from fdi_ros.plants.turbofan import plant as tfp
from fdi_ros.plants.turbofan.models import GlobalModel, GridSpec, train_global

C0 = np.array(tfp.PAPER_CONDITION)
SMALL_GRID = GridSpec(ALT=(15000.0,), XM=(0.7,), deterioration=(0.0, 0.1, 0.2),
                      region={"ALT": (14500.0, 15500.0), "XM": (0.68, 0.72),
                              "DTAMB": (-5.0, 5.0), "PC": (45.5, 46.5)})


@pytest.fixture(scope="module")
def gm() -> GlobalModel:
    return train_global(SMALL_GRID, seed=0, progress=False)


@pytest.fixture(scope="module")
def model_file(gm, tmp_path_factory):
    return gm.save(tmp_path_factory.mktemp("tf") / "global_model.npz")


def test_training_report_and_node_accuracy(gm):
    rep = gm.report
    assert rep.n_nodes == 48 and rep.n_fits == 96 and rep.seconds > 0
    assert rep.rmse_xnldot_max < 2.0  # rpm/s, on signals of +-300 rpm/s
    # every bank model reproduces its own noise-free plant open loop within a few rpm
    tf = tfp.Turbofan()
    wf = tfp.paper_input(tf.scheduled_fuel(C0), duration_s=10.0)
    ids = [m.id for m in tfb.PAPER_BANK]
    mix = tfb.bank_mixture(gm, ids, condition=C0, deterioration=0.1)
    for j, mid in enumerate(ids):
        faults = {f.split("_")[0]: f.split("_")[1] for f in tfb.faults_of(mid)}
        p = tfp.Health(deterioration=0.1, faults=faults).quality()
        x = tf.simulate(wf, C0, p, noise=False)["x"]
        pred = mix.take([j]).simulate(wf, x[0])[0]
        assert np.abs(pred[:, 0] - x[:, 0]).max() < 3.0, mid


def test_save_load_round_trip_and_bad_files(gm, model_file, tmp_path):
    again = GlobalModel.load(model_file)
    v = gm.coordinates(C0, 0.1, 1.0, 0.0)
    x = np.array([[10650.0, 14100.0]])
    np.testing.assert_array_equal(gm.mixture(v[None]).derivatives(x, 0.19),
                                  again.mixture(v[None]).derivatives(x, 0.19))
    assert again.report == gm.report
    with pytest.raises(FileNotFoundError, match="train turbofan"):
        GlobalModel.load(tmp_path / "missing.npz")
    junk = tmp_path / "junk.npz"
    np.savez(junk, a=np.zeros(3))
    with pytest.raises(ValueError, match="not a turbofan"):
        GlobalModel.load(junk)
    far = C0.copy()
    far[0] = 17000.0
    with pytest.raises(ValueError, match="ALT"):
        tfb.bank_mixture(gm, ["nominal"], condition=far, deterioration=0.1)


def test_interpolation_weights_are_normalised_and_local(gm):
    w = gm.weights(gm.coordinates(C0, 0.1, 2.0, 0.0))
    assert w.sum() == pytest.approx(1.0)
    top = int(np.argmax(w))
    np.testing.assert_allclose(gm.nodes[top], [15000, 0.7, 0, 46, 0.1, 2.0, 0.0])
    assert w[top] > 0.98
    mid = gm.weights(gm.coordinates(C0, 0.15, 0.0, 0.0))
    ids = np.argsort(-mid)[:2]
    assert set(np.round(gm.nodes[ids, 4], 2)) == {0.1, 0.2}
    assert mid[ids[0]] == pytest.approx(mid[ids[1]], rel=1e-9)


def _feature(index, t, xnl, xnh, wf, valid=True):
    return FeatureVector(plant="turbofan", index=index, t_start=t, t_end=t, alpha_start=0.0,
                         valid=valid, status="", names=("XNL", "XNH", "WF36"),
                         units=("rpm", "rpm", "kg/s"), values=np.array([xnl, xnh, wf]))


def test_residual_model_matches_batch_run_and_registry(gm, model_file):
    sc = tfb.Scenario(name="fan", events=((0.0, {"fan": "small"}),), duration_s=4.0, seed=3)
    sim = tfb.simulate_plant(sc)
    res = tfb.run_scenario(gm, sc, t0_s=1.2, sim=sim, xnh_weight=0.25)
    spec = {"type": "turbofan_ts", "module": "fdi_ros.plants.turbofan.bank",
            "path": str(model_file), "condition": list(C0), "deterioration": 0.1,
            "xnh_weight": 0.25}
    live = load_residual_model(spec, model_id="fan_small")
    j = list(res.model_ids).index("fan_small")
    for k in range(sim["t"].size):
        rv = live.residuals(_feature(k, sim["t"][k], *sim["y"][k], sim["wf"][k]))
        assert rv.valid and rv.model_id == "fan_small"
        assert rv.values[0] == pytest.approx(res.residuals[j, k], abs=1e-6)
        assert rv.norm == pytest.approx(res.norms[j, k], abs=1e-6)
    # bad input -> invalid, never an exception
    assert live.residuals(_feature(999, 5.0, math.nan, 14000.0, 0.2)).status == "invalid_input"
    assert live.residuals(_feature(999, 5.0, 10700.0, 14000.0, 0.2, valid=False)).valid is False
    out = live.residuals(_feature(1000, 5.02, 12500.0, 15000.0, 0.2))
    assert not out.valid and out.status == "outside_region"
    with pytest.raises(ValueError, match="unknown key"):
        load_residual_model({**spec, "colour": "red"}, model_id="nominal")
    with pytest.raises(ValueError, match="fan and hub"):
        load_residual_model(spec, model_id="valve_small")


def test_paper_cases_on_the_small_grid(gm):
    free = tfb.run_scenario(gm, tfb.Scenario(name="free"), t0_s=1.2, xnh_weight=0.25)
    s = free.summary()
    assert not s["false_isolations"] and not s["fault_index_ever_wrong"]
    assert s["max_nominal_residual_fault_free_rpm"] < 12.0
    fan = tfb.run_scenario(gm, tfb.Scenario(name="fan", events=((0.0, {"fan": "small"}),)),
                           t0_s=1.2, xnh_weight=0.25).summary()
    ev = fan["events"][0]
    assert ev["correct"] and ev["isolated_model"] == "fan_small"
    assert 1.2 <= ev["isolated_s"] < 3.0
    hub = tfb.run_scenario(gm, tfb.Scenario(name="hub", events=((5.0, {"hub": "small"}),)),
                           t0_s=1.2, xnh_weight=0.25)
    hs = hub.summary()["events"][0]
    assert hs["correct"] and 5.0 < hs["detected_s"] < 6.5 and hs["isolated_s"] < 8.0
    assert set(hub.online[-1]) == set(models_online(tfb.PAPER_BANK, ["hub_small"]))


def test_longest_wrong_hold_agrees_with_the_supervisor(gm):
    ff = tfb.fault_free_batch(gm, n_runs=4, seed=5, deterioration_range=(0.0, 0.2),
                              manufacturing_sigma=0.3e-2, duration_s=10.0)
    hold = tfb.longest_wrong_hold(ff["res"], ts=0.02)
    bank = [m for m in tfb.PAPER_BANK if m.id in ff["ids"]]
    for t0 in (0.1, 0.5, 2.0):
        for r in range(4):
            sup = ExpertSupervisor(bank=bank, t0_s=t0)
            for k, t in enumerate(ff["t"]):
                sup.update(float(t), dict(zip(ff["ids"], ff["res"][r, :, k])))
                if sup.isolated:
                    break
            assert bool(sup.isolated) == bool(hold[r] >= t0 - 1e-9), (t0, r, hold[r])
    # a large manufacturing spread must produce some wrong minimum somewhere
    assert hold.max() > 0.0


def test_live_runner_preprocessor_and_bank_isolate_a_hub_fault(model_file):
    from fdi_ros.plants import make_preprocessor, make_runner

    scenario = {"name": "live", "duration_s": 8.0, "seed": 4,
                "events": [{"t": 3.0, "faults": {"hub": "small"}}]}
    runner = make_runner("turbofan", scenario)
    pre = make_preprocessor("turbofan")
    spec = {"type": "turbofan_ts", "path": str(model_file), "condition": list(C0),
            "deterioration": 0.1, "xnh_weight": 0.25}
    models = {m.id: load_residual_model(spec, model_id=m.id) for m in tfb.PAPER_BANK}
    sup = ExpertSupervisor(bank=tfb.PAPER_BANK, t0_s=1.2)
    truth = []
    while not runner.done:
        block = runner.next_block()
        assert block.channels == ("XN2", "XNH", "WF36") and block.values.shape[1] == 5
        truth += runner.pop_truth()
        for fv in pre.push(block):
            d = sup.update(fv.t_start, {mid: models[mid].residuals(fv)
                                        for mid in sup.models_online})
    assert [e.fault for e in truth] == ["hub_small"] and truth[0].t == 3.0
    assert d.state == "isolated" and d.fault_model == "hub_small"
    iso = [t for t, kind, m in sup.history if kind == "isolated"]
    assert len(iso) == 1 and 3.0 < iso[0] < 6.0
    # run-time injection: a large fan fault, ramped, then cleared
    run2 = make_runner("turbofan", {"name": "inj", "duration_s": 3.0, "events": []})
    from fdi_ros.core.types import FaultEvent

    run2.inject(FaultEvent(t=0.5, fault="fan", size=3.0, size_unit="small", profile="ramp",
                           ramp_s=1.0))
    run2.inject(FaultEvent(t=2.0, fault=""))
    np.testing.assert_allclose(run2._quality(1.0) - run2._quality(0.0),
                               1.5 * tfp.fault_vector("fan"))
    np.testing.assert_allclose(run2._quality(2.5), run2._quality(0.0))
    with pytest.raises(ValueError, match="unknown fault"):
        run2.inject(FaultEvent(t=1.0, fault="hub_gigantic"))
    with pytest.raises(ValueError, match="size"):
        run2.inject(FaultEvent(t=1.0, fault="hub", size=-1.0))


def test_lm_fit_of_interpolation_widths(gm, tmp_path):
    from fdi_ros.plants.turbofan.models import fit_widths

    fitted, res = fit_widths(gm, n_random=6, seed=2, duration_s=2.0)
    assert res.success and res.n_points == 6 and res.nfev > 1
    assert res.rms_after <= res.rms_before
    assert all(w > 0 for w in res.x) and fitted.widths == res.x
    again = GlobalModel.load(fitted.save(tmp_path / "w.npz"))
    assert again.widths == fitted.widths
    np.testing.assert_allclose(again.weights(gm.nodes[5] + 0.01), fitted.weights(
        gm.nodes[5] + 0.01))
    assert fitted.same_structure(gm.grid) and not fitted.same_structure(
        GridSpec(ALT=(15000.0,), XM=(0.7,), deterioration=(0.0, 0.2),
                 region=SMALL_GRID.region))
