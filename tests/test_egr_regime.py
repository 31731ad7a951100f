"""The EGR-open regime of the diesel reference models identified with the exhaust side's
physics (plants/diesel/egrflow) on a synthetic engine whose fresh air follows that structure
with known parameters: the regime's eta_V is the flow model with its parameters recovered,
it holds beyond the (n, rho2) its data covered, the regime is judged on eta_V alone, and the
model set and the step-wise, array and batch paths agree after a save and a load."""

from __future__ import annotations

import random

import numpy as np
import pytest

from fdi_ros.core.types import FeatureVector
from fdi_ros.plants.diesel import egrflow as ef
from fdi_ros.plants.diesel.reference import (
    IdentificationConfig,
    ReferenceModelSet,
    identify_regime_models,
)
from fdi_ros.plants.diesel.symptoms import (
    ReferenceResidualModel,
    calibrate_from_fault_free,
    parity,
    stream_residuals,
)

NAMES = ("n", "rho2", "p2", "T2", "T2_rate", "eta_v", "maf_amp", "maf_phase", "p2_amp",
         "p2_phase", "fuel", "egr_cmd", "swirl_cmd", "vgt")
TRUTH = ef.EgrFlowModel((3.0e-4, 1.1, 4.0e-4, 0.6e-4, 10000.0, 1.2e6), 2.0, 4)
SEG = 0.015


def _eta_tot(n, rho2):
    return 0.86 + 0.03 * np.sin(n / 700.0) - 0.03 * (rho2 - 1.4)


def _engine(n_seg: int, seed: int, speeds=(1200.0, 3200.0)) -> dict[str, np.ndarray]:
    """Operating points held for 4.5-6 s each (speed, fuel, VGT, the EGR valve open on every
    other one), noise on the sensors; eta_V the flow structure's with the valve open."""
    rng = np.random.default_rng(seed)
    parts: dict[str, list] = {k: [] for k in ("n", "fuel", "vgt", "egr_cmd", "T2")}
    k = 0
    while k < n_seg:
        m = int(rng.integers(300, 420))
        ramp = np.linspace(0.0, 1.0, m)   # slow ramps within the gate's limits
        n0, f0 = rng.uniform(*speeds), rng.uniform(8, 35)
        parts["n"].append(n0 + rng.uniform(-100, 100) * ramp)
        parts["fuel"].append(f0 + rng.uniform(-2, 2) * ramp)
        parts["vgt"].append(np.full(m, rng.uniform(0.1, 0.9)))
        open_ = len(parts["egr_cmd"]) % 2 == 1
        parts["egr_cmd"].append(np.full(m, rng.uniform(0.1, 0.6) if open_ else 0.0))
        parts["T2"].append(rng.uniform(315, 360) + rng.uniform(-3, 3) * ramp)
        k += m
    cols = {x: np.concatenate(v)[:n_seg] for x, v in parts.items()}
    n, fuel = cols["n"] + rng.normal(0, 3, n_seg), cols["fuel"]
    T2 = cols["T2"] + rng.normal(0, 0.05, n_seg)
    p2 = 1.0e5 + 1.5e3 * fuel
    rho2 = p2 / (ef.R_AIR * T2)
    d = {"n": n, "rho2": rho2, "p2": p2, "T2": T2, "T2_rate": rng.normal(0, 0.2, n_seg),
         "fuel": fuel, "vgt": cols["vgt"], "egr_cmd": cols["egr_cmd"],
         "swirl_cmd": np.zeros(n_seg), "t": np.arange(n_seg) * SEG}
    et = _eta_tot(n, rho2)
    eta = np.where(d["egr_cmd"] > 0, TRUTH.eta_fresh(d, et), et)
    d["eta_v"] = eta + rng.normal(0, 0.001, n_seg)
    d["maf_amp"] = 10 + 0.004 * n + 8 * d["egr_cmd"] + rng.normal(0, 0.1, n_seg)
    d["maf_phase"] = -30 + 0.01 * n + rng.normal(0, 0.3, n_seg)
    d["p2_amp"] = 500 + 0.1 * n - 300 * d["egr_cmd"] + rng.normal(0, 5, n_seg)
    d["p2_phase"] = 10 + 0.005 * n + rng.normal(0, 0.3, n_seg)
    return d


def _fvs(d: dict[str, np.ndarray]) -> list[FeatureVector]:
    return [FeatureVector(plant="diesel", index=i, t_start=float(d["t"][i]) - SEG,
                          t_end=float(d["t"][i]), alpha_start=180.0 * i, valid=True, status="",
                          names=NAMES, units=("",) * len(NAMES),
                          values=np.array([d[k][i] for k in NAMES]))
            for i in range(d["n"].size)]


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    data = _engine(24000, 1)
    res = identify_regime_models(data, config=IdentificationConfig(
        max_models=6, storage_correction=False))
    path = tmp_path_factory.mktemp("egr") / "models"
    res.models.save(path)
    return res.models, ReferenceModelSet._load(path)


def test_the_flow_model_is_identified_with_its_parameters(models):
    ms, _ = models
    assert [r.regime for r in ms.regimes] == ["egr_open_flaps_open"]
    reg = ms.regimes[0]
    m = reg.models["eta_v"]
    assert isinstance(m, ef.EgrFlowEta) and reg.info["judged_outputs"] == ["eta_v"]
    got, want = dict(zip(ef.PARAMS, m.flow.theta)), dict(zip(ef.PARAMS, TRUTH.theta))
    for k in ("A_e", "gamma"):
        assert abs(got[k] / want[k] - 1) < 0.1, (k, got, want)


def test_it_holds_where_its_data_map_had_no_coverage(models):
    """Valid in the regime's box of every input, also at (n, rho2) its own data did not cover
    (as a drive between the identification's passes), and right there; outside the box "not
    valid here" with the input named."""
    seed = random.randrange(2**32)
    ms, _ = models
    reg = ms.regimes[0]
    fresh = _engine(6000, seed)
    R, valid, regime = parity(ms, fresh)
    X = np.column_stack([fresh[k] for k in reg.inputs])
    bare = valid & (regime == "egr_open_flaps_open") & ~reg.models["eta_v"].region.in_region(X)
    assert bare.sum() > 20, (seed, bare.sum())
    assert np.sqrt(np.mean(R[bare, 0] ** 2)) < 0.01, seed
    out = {k: v[:400].copy() for k, v in fresh.items()}
    out["egr_cmd"] = np.full(400, 0.95)   # beyond the identified valve positions
    _, ok, _ = parity(ms, out)
    assert not ok.any()
    rv = stream_residuals(ms, _fvs(out)[200:201])[0]
    assert "egr_cmd = 0.95 outside" in rv.status, rv.status


def test_judged_on_eta_v_alone_and_the_paths_agree_after_a_load(models):
    ms, loaded = models
    seed = random.randrange(2**32)
    # thresholds from a part of the identification's own data (covered by every map) and a
    # fresh run (the random operating points of a short run fall partly outside them)
    cfg = calibrate_from_fault_free(loaded, [_fvs(_engine(24000, 1))[:12000],
                                             _fvs(_engine(8000, seed))])
    assert cfg.regimes["egr_open_flaps_open"]["judged"] == (True, False, False, False, False)
    feats = _fvs(_engine(6000, seed + 1))
    a = stream_residuals(ms, feats, config=cfg)
    b = stream_residuals(loaded, feats, config=cfg)
    model = ReferenceResidualModel(models=loaded, config=cfg, window=1)
    batch = model.batch(feats, {})
    c = [batch.residuals(fv) for fv in feats]
    assert any(x.valid and x.regime == "egr_open_flaps_open" for x in a), seed
    for x, y, z in zip(a, b, c):
        assert (x.valid, x.status, x.regime) == (y.valid, y.status, y.regime) \
            == (z.valid, z.status, z.regime)
        np.testing.assert_allclose(y.values, x.values, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(z.values, y.values, rtol=1e-9, atol=1e-12)


def test_segments_for_the_further_regimes_only_leave_the_base_maps_alone(models):
    """Segments marked for the further regimes only (a slow pass identifying the EGR flow
    model): their EGR-closed part, however wrong for the base map, does not change it."""
    from fdi_ros.plants.diesel.reference import REGIMES_ONLY

    ms, _ = models
    data = _engine(24000, 1)
    extra = _engine(4000, random.randrange(2**32))
    extra["eta_v"] = extra["eta_v"] + 0.3   # nothing the base map may learn
    both = {k: np.r_[data[k], extra[k]] for k in data}
    both[REGIMES_ONLY] = np.r_[np.zeros(24000), np.ones(4000)]
    res = identify_regime_models(both, config=IdentificationConfig(
        max_models=6, storage_correction=False))
    X = np.column_stack([data["n"], data["rho2"]])[::7]
    np.testing.assert_array_equal(res.models.models["eta_v"].predict(X),
                                  ms.models["eta_v"].predict(X))
    assert res.models.t2_tau == ms.t2_tau


def test_transients_of_the_flow_regime_need_enough_calibration(models, monkeypatch):
    """With transients as regimes of their own, an EGR-open regime's transients get
    thresholds (judged on eta_V alone) only with MIN_TRANSIENT_ROWS of them in the
    calibration; with fewer they stay "not valid here"."""
    from fdi_ros.plants.diesel import symptoms as sy

    _, loaded = models
    seed = random.randrange(2**32)
    streams = [_fvs(_engine(24000, 1))[:12000], _fvs(_engine(8000, seed))]
    few = calibrate_from_fault_free(loaded, streams, transients="regime")
    assert not few.knows("egr_open_flaps_open/transient"), seed
    monkeypatch.setattr(sy, "MIN_TRANSIENT_ROWS", 20)
    enough = calibrate_from_fault_free(loaded, streams, transients="regime")
    assert enough.knows("egr_open_flaps_open/transient"), seed
    assert enough.regimes["egr_open_flaps_open/transient"]["judged"] == (
        True, False, False, False, False)

