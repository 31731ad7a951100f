"""Reference model set on a synthetic engine map with known functions (no plant needed):
held-out accuracy, phase wrapping, tables, save/load, residual model via the registry."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fdi_ros.core.types import FeatureVector
from fdi_ros.plants import load_residual_model
from fdi_ros.plants.diesel.reference import (
    INPUTS,
    OUTPUTS,
    IdentificationConfig,
    ReferenceModelSet,
    feature_table,
    identify_reference_models,
    wrap_phase,
)
from fdi_ros.plants.diesel.symptoms import (
    RESIDUALS,
    THRESHOLDS_FILE,
    calibrate_thresholds,
    parity_residuals,
)

TRUE = {
    "eta_v": lambda n, r: 0.80 + 0.05 * np.sin(n / 600.0) - 0.02 * (r - 2.0) ** 2,
    "maf_amp": lambda n, r: 30.0 * np.exp(-((n - 2000.0) / 600.0) ** 2) * r + 2.0,
    "maf_phase": lambda n, r: -40.0 + 0.03 * n + 2.0 * r,
    "p2_amp": lambda n, r: 900.0 * r + 0.2 * n,
    "p2_phase": lambda n, r: 80.0 + 0.02 * n,      # crosses the +-90 deg CA wrap
}
NOISE = {"eta_v": 0.003, "maf_amp": 0.5, "maf_phase": 1.0, "p2_amp": 20.0, "p2_phase": 1.0}
NAMES = INPUTS + OUTPUTS


def _synthetic(n_seg, seed, period=3000.0):
    rng = np.random.default_rng(seed)
    # A sweep of speed and boost with the "low speed, high boost" corner empty.
    t = np.arange(n_seg)
    n = 2400 + 1500 * np.sin(2 * np.pi * t / period) + rng.normal(0, 20, n_seg)
    rmax = 1.3 + 1.7 * np.clip((n - 800) / 2400, 0, 1)
    r = 1.1 + (rmax - 1.1) * (0.5 + 0.5 * np.sin(2 * np.pi * t / 377.0))
    d = {"n": n, "rho2": r}
    for k, f in TRUE.items():
        d[k] = f(n, r) + rng.normal(0, NOISE[k], n_seg)
    for k in ("maf_phase", "p2_phase"):
        d[k] = wrap_phase(d[k], 0.0)   # measured phases come wrapped to +-90 deg CA
    return d


def _fvs(d, start=0):
    m = d["n"].size
    return [FeatureVector(plant="diesel", index=start + i, t_start=0.015 * (start + i),
                          t_end=0.015 * (start + i + 1), alpha_start=180.0 * (start + i),
                          valid=True, status="", names=NAMES, units=("",) * len(NAMES),
                          values=np.array([d[k][i] for k in NAMES])) for i in range(m)]


@pytest.fixture(scope="module")
def identified():
    d = _synthetic(9000, 0)
    res = identify_reference_models(d, config=IdentificationConfig(max_models=12))
    return d, res


def test_held_out_accuracy_and_phase_branches(identified):
    d, res = identified
    assert res.success and res.n_test > 1000
    # Noise-limited: the held-out NRMSE is close to noise std / signal std.
    for k in OUTPUTS:
        y = d[k] if k not in res.models.phase_centre else wrap_phase(
            d[k], res.models.phase_centre[k])
        floor = NOISE[k] / np.std(y)
        assert res.nrmse_test[k] < floor + 0.08, (k, res.nrmse_test[k], floor)
        assert res.nrmse_test_lut[k] < res.nrmse_test[k] + 0.05
    # p2_phase spans 96..160 deg CA: centred branch, no jump at the wrap.
    assert 110 < wrap_phase(res.models.phase_centre["p2_phase"], 130.0) < 150
    n = np.array([1500.0, 3500.0])
    ref, valid = res.models.predict(n, np.array([1.5, 2.5]))
    assert valid.all()
    np.testing.assert_allclose(wrap_phase(ref["p2_phase"] - TRUE["p2_phase"](n, 0)), 0, atol=2.0)


def test_empty_corner_is_not_identified(identified):
    _, res = identified
    _, valid = res.models.predict(np.array([900.0, 3000.0]), np.array([2.8, 2.0]))
    assert valid.tolist() == [False, True]


def test_save_load_and_residual_model_through_registry(identified, tmp_path):
    d, res = identified
    res.models.save(tmp_path)
    back = ReferenceModelSet.load(tmp_path)
    X = np.column_stack([d["n"][:200], d["rho2"][:200]])
    a, _ = res.models.predict(X[:, 0], X[:, 1])
    b, _ = back.predict(X[:, 0], X[:, 1])
    for k in OUTPUTS:
        np.testing.assert_array_equal(a[k], b[k])
    # Fault-free residual statistics on fresh data, then the bank's nominal model.
    fresh = _synthetic(3000, 7)
    R, valid = parity_residuals(back, fresh)
    cfg = calibrate_thresholds(R, valid)
    (tmp_path / THRESHOLDS_FILE).write_text(json.dumps(cfg.to_dict()))
    model = load_residual_model(tmp_path, model_id="nominal")
    fv = _fvs(fresh)[100]
    rv = model.residuals(fv)
    assert rv.model_id == "nominal" and rv.valid and rv.names == RESIDUALS
    np.testing.assert_allclose(rv.values, R[100])
    assert 0 <= rv.norm < 5
    # Residual sign of eq. 10: less air than the model -> positive r_eta.
    vals = fv.values.copy()
    vals[NAMES.index("eta_v")] -= 0.05
    low = FeatureVector(**{**fv.__dict__, "values": vals})
    assert model.residuals(low).values[0] == pytest.approx(R[100, 0] + 0.05)
    # Outside the identified region: not valid here.
    vals = fv.values.copy()
    vals[:2] = [900.0, 2.8]
    out = model.residuals(FeatureVector(**{**fv.__dict__, "values": vals}))
    assert not out.valid and "identified region" in out.status
    bad = FeatureVector(**{**fv.__dict__, "valid": False, "status": "crank gap"})
    assert not model.residuals(bad).valid


def test_feature_table_and_bad_input():
    d = _synthetic(50, 1)
    fvs = _fvs(d)
    fvs[3] = FeatureVector(**{**fvs[3].__dict__, "valid": False})
    tab = feature_table(fvs)
    assert tab["n"].size == 49
    with pytest.raises(ValueError):
        identify_reference_models({"n": d["n"]})
    with pytest.raises(ValueError):
        identify_reference_models(d)  # too few segments
    with pytest.raises(FileNotFoundError):
        ReferenceModelSet.load("/nonexistent/models")


def test_stream_residuals_equal_the_per_segment_model(identified, tmp_path):
    from fdi_ros.plants.diesel.symptoms import ReferenceResidualModel, stream_residuals

    d, res = identified
    fresh = _synthetic(400, 9)
    R, valid = parity_residuals(res.models, fresh)
    cfg = calibrate_thresholds(R, valid)
    fvs = _fvs(fresh)
    vals = fvs[5].values.copy()
    vals[:2] = [900.0, 2.8]
    fvs[5] = FeatureVector(**{**fvs[5].__dict__, "values": vals})
    one = ReferenceResidualModel(models=res.models, config=cfg)
    for a, b in zip(stream_residuals(res.models, fvs, config=cfg),
                    [one.residuals(fv) for fv in fvs]):
        assert (a.valid, a.status, a.index) == (b.valid, b.status, b.index)
        np.testing.assert_allclose(a.values, b.values)
        np.testing.assert_allclose(a.norm, b.norm)


def test_fault_hypotheses_separate_faults_of_equal_signature(identified, tmp_path):
    """Two faults that both raise r_eta only (same table signature "+,o,o,o,o") but with a
    different shape over the operating range are told apart by their hypothesis models."""
    from fdi_ros.plants.diesel.symptoms import identify_fault_hypothesis

    _, res = identified
    clean = _synthetic(3000, 11)
    R, valid = parity_residuals(res.models, clean)
    cfg = calibrate_thresholds(R, valid)
    shapes = {"flat": lambda n: 0.02 + 0 * n, "speedy": lambda n: 0.03 * (n / 2500.0) ** 3}

    def faulty(shape, seed, period=3000.0):
        d = _synthetic(3000, seed, period)
        d["eta_v"] = d["eta_v"] - shapes[shape](d["n"])   # less air -> r_eta > 0
        return _fvs(d)

    hyp = {k: identify_fault_hypothesis(res.models, cfg, faulty(k, 20 + i), fault=k, size=1.0,
                                        t_from=0.0, residual_names=("r_eta",),
                                        inputs=("n", "rho2"), window=150)
           for i, k in enumerate(shapes)}
    hyp["flat"].save(tmp_path / "flat")
    res.models.save(tmp_path)
    (tmp_path / THRESHOLDS_FILE).write_text(json.dumps(cfg.to_dict()))
    loaded = load_residual_model({"type": "diesel_fault_hypothesis", "path": str(tmp_path),
                                  "hypothesis": str(tmp_path / "flat"), "window": 150},
                                 model_id="flat")
    assert loaded.window == 150 and loaded.fault == "flat"
    loaded_base = load_residual_model(tmp_path, model_id="nominal")
    assert loaded_base.model_id == "nominal"
    for truth in shapes:
        # Operating points that change within the estimation window (driving, not steady).
        stream = faulty(truth, 40, period=200.0)[:1500]
        norms = {k: [] for k in shapes}
        for k, h in hyp.items():
            norms[k] = np.array([rv.norm for rv in h.stream(stream)])[300:]
        other = next(k for k in shapes if k != truth)
        assert np.nanmedian(norms[truth]) < 0.75 * np.nanmedian(norms[other]), truth
    assert hyp["speedy"].size_estimate > 0.5
    # Fault-free: no hypothesis explains a threshold's worth, none beats the nominal model.
    from fdi_ros.plants.diesel.symptoms import ReferenceResidualModel

    clean_fv = _fvs(_synthetic(600, 77, period=200.0))
    nominal = ReferenceResidualModel(models=res.models, config=cfg, window=150)
    nom = np.array([nominal.residuals(fv).norm for fv in clean_fv])
    for h in hyp.values():
        hn = np.array([rv.norm for rv in h.stream(clean_fv)])
        ok = np.isfinite(nom) & np.isfinite(hn)
        assert np.all(hn[ok] >= nom[ok] + h.penalty - 1e-9)
    # The vectorised offline stream equals the segment-by-segment model.
    stream = faulty("speedy", 41, period=200.0)[:400]
    h = hyp["speedy"]
    fast = h.stream(stream)
    h.reset()
    slow = [h.residuals(fv) for fv in stream]
    for a, b in zip(fast, slow):
        assert a.valid == b.valid
        np.testing.assert_allclose(a.values, b.values)
        np.testing.assert_allclose(a.norm, b.norm)
    del loaded


def test_storage_coefficient_recovered_with_the_static_map():
    from fdi_ros.plants.diesel.reference import storage_regressor

    d = _synthetic(9000, 3)
    d["t"] = 0.015 * np.arange(9000)
    d["p2"] = d["rho2"] * 287.0 * 320.0
    x = storage_regressor(d["t"], d["n"], d["p2"], 2)
    d["eta_v"] = d["eta_v"] + 400.0 * np.nan_to_num(x)   # stored air passes the MAF
    res = identify_reference_models(d, config=IdentificationConfig(max_models=12))
    assert res.models.info["storage_coeff"] == pytest.approx(400.0, rel=0.05)
    off = identify_reference_models(d, config=IdentificationConfig(max_models=12,
                                                                   storage_correction=False))
    assert res.nrmse_test["eta_v"] < off.nrmse_test["eta_v"]


def test_effect_maps_of_further_regimes_are_saved_loaded_and_used_there(identified, tmp_path):
    """A hypothesis with effect maps of a further regime (judged on r_eta only): saved and
    loaded through the registry it gives the same g(x) there, covers that regime and the
    base one, nothing else; a hypothesis of the older layout (no such maps) still loads."""
    from fdi_ros.core.lolimot import Lolimot
    from fdi_ros.plants.diesel.symptoms import FaultHypothesisResidualModel

    _, res = identified
    clean = _synthetic(2000, 12)
    R, valid = parity_residuals(res.models, clean)
    cfg = calibrate_thresholds(R, valid)
    rng = np.random.default_rng()
    X = np.column_stack([rng.uniform(1000, 3000, 400), rng.uniform(1.0, 1.6, 400),
                         rng.uniform(2, 30, 400), rng.uniform(0.1, 0.6, 400)])
    g = -0.5 + 0.3 * X[:, 3] - 1e-4 * (X[:, 0] - 2000)   # a smooth effect with the valve
    m = Lolimot(max_models=3, min_samples_per_model=50)
    m.fit(X, g, input_names=("n", "rho2", "fuel", "egr_cmd"), output_name="g_r_eta")
    base = {name: Lolimot(max_models=1, min_samples_per_model=20) for name in ("r_eta",)}
    base["r_eta"].fit(X[:, :2], np.full(400, 0.4), input_names=("n", "rho2"),
                      output_name="g_r_eta")
    h = FaultHypothesisResidualModel(models=res.models, config=cfg, fault="leak",
                                     directions=base, model_id="leak", regimes=("base",),
                                     regime_directions={"egr_open_flaps_open": {"r_eta": m}})
    h.save(tmp_path / "leak")
    res.models.save(tmp_path)
    (tmp_path / THRESHOLDS_FILE).write_text(json.dumps(cfg.to_dict()))
    spec = {"type": "diesel_fault_hypothesis", "path": str(tmp_path),
            "hypothesis": str(tmp_path / "leak")}
    back = load_residual_model(spec, model_id="leak")
    assert back.covers("base") and back.covers("egr_open_flaps_open")
    assert not back.covers("egr_open_flaps_closed")
    assert back.inputs_for("egr_open_flaps_open") == ("n", "rho2", "fuel", "egr_cmd")
    G = back.direction(X, "egr_open_flaps_open")
    np.testing.assert_allclose(G, h.direction(X, "egr_open_flaps_open"), rtol=1e-12)
    np.testing.assert_allclose(G[:, 0], m.predict(X), rtol=1e-9, atol=1e-12)
    assert not G[:, 1:].any()   # residuals not judged there: no effect
    np.testing.assert_allclose(back.direction(X[:, :2])[:, 0], 0.4, atol=1e-9)
    meta = json.loads((tmp_path / "leak" / "hypothesis.json").read_text())
    del meta["regime_directions"]
    (tmp_path / "leak" / "hypothesis.json").write_text(json.dumps(meta))
    old = load_residual_model(spec, model_id="leak")
    assert old.covers("base") and not old.covers("egr_open_flaps_open")
