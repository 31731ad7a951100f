"""The EGR-open regime judged on the crank pulsations where the base maps cover it
(plants/diesel/pulsation): on a synthetic engine whose EGR-open harmonics are the EGR-closed
ones times a known transfer ratio of (n, x_egr), the ratio maps recover it, the covered
regime is tried first and only where its maps cover a segment, its transients are its
parent's, it judges what it should, and it survives a save and a load."""

from __future__ import annotations

import random

import numpy as np
import pytest
from test_egr_regime import SEG, TRUTH, _eta_tot, _fvs

from fdi_ros.plants.diesel.pulsation import JUDGED, PulsationRatio, ratio_inputs
from fdi_ros.plants.diesel.reference import (
    PULSATION_SUFFIX,
    IdentificationConfig,
    ReferenceModelSet,
    identify_regime_models,
    transient_regime,
)
from fdi_ros.plants.diesel.symptoms import calibrate_from_fault_free, parity, stream_residuals

PARENT = "egr_open_flaps_open"
COVERED = PARENT + PULSATION_SUFFIX


def _ratio(n: np.ndarray, x: np.ndarray) -> dict[str, np.ndarray]:
    """The true transfer ratio: log-amplitude and phase change [deg CA] per harmonic."""
    return {"maf_amp": -1.2 * x + 3e-4 * (n - 2200.0) * x, "maf_phase": 20.0 * x,
            "p2_amp": -0.8 * x, "p2_phase": -15.0 * x + 0.005 * (n - 2200.0) * x}


def _closed(n: np.ndarray, rho2: np.ndarray) -> dict[str, np.ndarray]:
    """The true EGR-closed harmonics."""
    return {"maf_amp": 10.0 + 0.004 * n + 4.0 * (rho2 - 1.2), "maf_phase": -30.0 + 0.01 * n,
            "p2_amp": 500.0 + 0.1 * n + 100.0 * (rho2 - 1.2), "p2_phase": 10.0 + 0.005 * n}


def _engine(n_seg: int, seed: int, noise: bool = True,
            noise_seed: int | None = None) -> dict[str, np.ndarray]:
    """Operating points (of ``seed``) held 4.5-6 s with the valve closed, then as long open
    at the same speed, load and vanes (the ECU's passes: the EGR-open points within the base
    maps); sensor noise of ``noise_seed`` (default: ``seed``)."""
    rng = np.random.default_rng(seed)
    parts: dict[str, list] = {k: [] for k in ("n", "fuel", "vgt", "egr_cmd", "T2")}
    k = 0
    while k < n_seg:
        m = int(rng.integers(300, 420))
        n0, f0 = rng.uniform(1200, 3200), rng.uniform(8, 35)
        vgt, t2 = rng.uniform(0.1, 0.9), rng.uniform(315, 360)
        for egr in (0.0, rng.uniform(0.1, 0.6)):
            parts["n"].append(np.full(m, n0))
            parts["fuel"].append(np.full(m, f0))
            parts["vgt"].append(np.full(m, vgt))
            parts["egr_cmd"].append(np.full(m, egr))
            parts["T2"].append(np.full(m, t2))
            k += m
    cols = {x: np.concatenate(v)[:n_seg] for x, v in parts.items()}
    rng = np.random.default_rng(seed if noise_seed is None else noise_seed)
    e = (lambda sd: rng.normal(0, sd, n_seg)) if noise else (lambda sd: np.zeros(n_seg))
    n, fuel, T2 = cols["n"] + e(3.0), cols["fuel"], cols["T2"] + e(0.05)
    p2 = 1.0e5 + 1.5e3 * fuel
    rho2 = p2 / (287.0 * T2)
    d = {"n": n, "rho2": rho2, "p2": p2, "T2": T2, "T2_rate": e(0.2), "fuel": fuel,
         "vgt": cols["vgt"], "egr_cmd": cols["egr_cmd"], "swirl_cmd": np.zeros(n_seg),
         "t": np.arange(n_seg) * SEG}
    et = _eta_tot(n, rho2)
    opened = d["egr_cmd"] > 0
    f = TRUTH.flows(d, et)
    d["x_egr"] = np.where(opened, f["m_egr"] / f["m_cyl"], 0.0)
    d["eta_v"] = np.where(opened, TRUTH.eta_fresh(d, et), et) + e(0.001)
    ratio, closed = _ratio(n, d["x_egr"]), _closed(n, rho2)
    for k, sd in (("maf_amp", 0.05), ("p2_amp", 2.0)):
        d[k] = closed[k] * np.exp(ratio[k]) + e(sd)
    for k in ("maf_phase", "p2_phase"):
        d[k] = closed[k] + ratio[k] + e(0.2)
    return d


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    res = identify_regime_models(_engine(30000, 3), config=IdentificationConfig(
        max_models=6, storage_correction=False))
    path = tmp_path_factory.mktemp("pulsation") / "models"
    res.models.save(path)
    return res.models, ReferenceModelSet._load(path)


def test_the_ratio_is_recovered_and_the_covered_regime_tried_first(models):
    """The covered regime comes before its parent and holds the EGR-open segments its maps
    cover (and only those: the others are the parent's, judged on eta_V); there its
    harmonics are the true ones (the identification's operating points without noise: a
    random run's points fall mostly outside the few passes' coverage)."""
    ms, _ = models
    assert [r.regime for r in ms.regimes] == [COVERED, PARENT]
    cov = ms.regimes[0]
    assert isinstance(cov.models["maf_amp"], PulsationRatio)
    assert cov.info["judged_outputs"] == list(JUDGED)
    seed = 3
    d = _engine(12000, seed, noise=False)
    R, valid, regime = parity(ms, d)
    opened = d["egr_cmd"] > 0
    X = np.column_stack([d[k] for k in cov.inputs])
    covered = cov.predict(d["n"], d["rho2"], phases=False,
                          extra={k: d[k] for k in cov.extra_inputs})[1]
    mine = valid & (regime == COVERED)
    assert mine.sum() > 500, (seed, mine.sum())
    np.testing.assert_array_equal(mine, valid & opened & covered)
    assert not (valid & (regime == PARENT) & covered).any(), seed
    ref, _ = cov.predict(d["n"][mine], d["rho2"][mine],
                         extra={k: d[k][mine] for k in cov.extra_inputs})
    for k in ("maf_amp", "p2_amp"):
        rel = ref[k] / d[k][mine] - 1.0
        assert np.sqrt(np.mean(rel ** 2)) < 0.02, (seed, k, np.sqrt(np.mean(rel ** 2)))
    for k in ("maf_phase", "p2_phase"):
        err = (ref[k] - d[k][mine] + 90.0) % 180.0 - 90.0
        assert np.sqrt(np.mean(err ** 2)) < 0.5, (seed, k, np.sqrt(np.mean(err ** 2)))
    # the share the ratio maps read is the exhaust side's (the flow model identified)
    x = ratio_inputs(cov.models["eta_v"], X[mine], cov.inputs)[:, 1]
    assert np.sqrt(np.mean((x - d["x_egr"][mine]) ** 2)) < 0.02, seed


def test_judged_flags_transients_and_a_load(models):
    """Thresholds judge the covered regime on eta_V, both amplitudes and the p2 phase; its
    transients are its parent's; the loaded set gives the same residuals and regimes (the
    identification's operating points with fresh noise, seed printed)."""
    ms, loaded = models
    assert transient_regime(COVERED) == PARENT + "/transient"
    assert transient_regime(PARENT) == PARENT + "/transient"
    seed = random.randrange(2**32)
    cfg = calibrate_from_fault_free(loaded, [_fvs(_engine(30000, 3))[:15000],
                                             _fvs(_engine(8000, 3, noise_seed=seed))])
    assert cfg.regimes[COVERED]["judged"] == (True, True, False, True, True)
    feats = _fvs(_engine(6000, 3, noise_seed=seed + 1))
    a = stream_residuals(ms, feats, config=cfg)
    b = stream_residuals(loaded, feats, config=cfg)
    assert any(x.valid and x.regime == COVERED for x in a), seed
    for x, y in zip(a, b):
        assert (x.valid, x.status, x.regime) == (y.valid, y.status, y.regime)
        np.testing.assert_allclose(y.values, x.values, rtol=1e-9, atol=1e-12)
