"""Operating regimes of the diesel reference models on a synthetic engine with known maps (no
plant needed): the T2 sensor's time constant recovered, each regime's maps where its actuator
commands say, the residuals of a stream the same segment by segment, as arrays and in the
offline batch path (with transient segments as a regime of their own), and a point outside
every regime "not valid here" with each regime's reason."""

from __future__ import annotations

import numpy as np
import pytest

from fdi_ros.core.types import FeatureVector
from fdi_ros.plants.diesel.reference import (
    REGIMES,
    IdentificationConfig,
    identify_regime_models,
    regime_labels,
)
from fdi_ros.plants.diesel.symptoms import (
    ReferenceResidualModel,
    calibrate_from_fault_free,
    parity,
    stream_residuals,
)

TAU = 0.6          # the synthetic T2 sensor's time constant [s]
NAMES = ("n", "rho2", "p2", "T2", "T2_rate", "eta_v", "maf_amp", "maf_phase", "p2_amp",
         "p2_phase", "fuel", "egr_cmd", "swirl_cmd", "vgt")


def _engine(n_seg: int, seed: int, dt: float = 0.015) -> dict[str, np.ndarray]:
    """Segment features of a synthetic engine: slow speed and load waves, the EGR valve open
    in stretches (its map differs there), a first-order T2 sensor (time constant TAU) whose
    true temperature jumps when the valve moves, and the T2_rate feature over 8 segments."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_seg) * dt
    n = 2000 + 900 * np.sin(2 * np.pi * t / 97.0) + rng.normal(0, 5, n_seg)
    fuel = 18 + 12 * np.sin(2 * np.pi * t / 41.0)
    vgt = 0.5 + 0.3 * np.sin(2 * np.pi * t / 23.0)
    open_ = np.sin(2 * np.pi * t / 60.0) > 0.0
    egr = np.where(open_, 0.3 + 0.2 * np.sin(2 * np.pi * t / 13.0), 0.0)
    T_true = 320 + 40 * egr
    T2 = np.empty(n_seg)       # the sensor: first-order lag of the true temperature
    T2[0] = T_true[0]
    a = 1 - np.exp(-dt / TAU)
    for k in range(1, n_seg):
        T2[k] = T2[k - 1] + a * (T_true[k] - T2[k - 1])
    T2 = T2 + rng.normal(0, 0.01, n_seg)
    rate = np.full(n_seg, np.nan)
    rate[8:] = (T2[8:] - T2[:-8]) / (t[8:] - t[:-8])
    p2 = 1.2e5 + 2.0e3 * fuel
    rho_true = p2 / (287.05 * T_true)
    eta_true = 0.85 + 0.02 * np.sin(n / 700) - 0.05 * (rho_true - 1.3) - 0.4 * egr * (1 + vgt)
    m_th_ratio = T2 / T_true   # eta and rho2 from the sensor's T2: off by T_true / T2
    d = {"n": n, "p2": p2, "T2": T2, "T2_rate": rate, "fuel": fuel, "vgt": vgt,
         "egr_cmd": egr, "swirl_cmd": np.zeros(n_seg),
         "rho2": rho_true / m_th_ratio, "eta_v": eta_true * m_th_ratio,
         "maf_amp": 10 + 0.004 * n + 8 * egr + rng.normal(0, 0.1, n_seg),
         "maf_phase": -30 + 0.01 * n + 10 * egr + rng.normal(0, 0.3, n_seg),
         "p2_amp": 500 + 0.1 * n - 300 * egr + rng.normal(0, 5, n_seg),
         "p2_phase": 10 + 0.005 * n + rng.normal(0, 0.3, n_seg), "t": t}
    d["eta_v"] = d["eta_v"] + rng.normal(0, 0.001, n_seg)
    return d


def _fvs(d: dict[str, np.ndarray]) -> list[FeatureVector]:
    m = d["n"].size
    return [FeatureVector(plant="diesel", index=i, t_start=float(d["t"][i]) - 0.015,
                          t_end=float(d["t"][i]), alpha_start=180.0 * i, valid=True, status="",
                          names=NAMES, units=("",) * len(NAMES),
                          values=np.array([d[k][i] for k in NAMES])) for i in range(m)]


@pytest.fixture(scope="module")
def regimes():
    data = {k: v[8:] for k, v in _engine(16000, 0).items()}   # rows with a T2 rate
    cfg = IdentificationConfig(max_models=6, storage_correction=False)
    res = identify_regime_models(data, config=cfg)
    return res.models


def test_sensor_lag_recovered_and_regimes_identified(regimes):
    ms = regimes
    assert ms.regime == REGIMES[0][0]
    assert [r.regime for r in ms.regimes] == ["egr_open_flaps_open"]
    assert ms.t2_tau == pytest.approx(TAU, abs=0.15)
    assert ms.regimes[0].inputs[:3] == ("n", "rho2", "egr_cmd")
    fresh = {k: v[8:] for k, v in _engine(3000, 5).items()}
    R, valid, regime = parity(ms, fresh)
    labels = regime_labels(fresh)
    assert list(regime[valid]) == list(labels[valid])
    assert valid.mean() > 0.5       # the rest: operating points outside the maps' coverage
    # the maps hold in both regimes: residuals small against the effects the valve has
    for name in ("egr_closed_flaps_open", "egr_open_flaps_open"):
        rows = valid & (regime == name)
        assert np.sqrt(np.mean(R[rows, 0] ** 2)) < 0.01       # eta_V (the valve: 0.1-0.4)


def test_outside_every_regime_not_valid_with_each_regimes_reason(regimes):
    fresh = {k: v[8:200] for k, v in _engine(3000, 6).items()}
    fresh["swirl_cmd"] = np.ones(fresh["n"].size)     # flaps closed: no regime has them
    _, valid, _ = parity(regimes, fresh)
    assert not valid.any()
    fv = _fvs(fresh)[50]
    rv = stream_residuals(regimes, [fv])[0]
    assert not rv.valid and "no operating regime covers it" in rv.status
    assert "egr_open_flaps_open: swirl_cmd = 1 outside" in rv.status


def test_step_wise_array_and_batch_paths_equal_with_transient_regimes(regimes):
    from fdi_ros.plants.diesel.batch import _Stream

    feats = _fvs(_engine(2500, 7))
    cfg = calibrate_from_fault_free(regimes, _fvs(_engine(6000, 8)), transients="regime",
                                    max_rates={"T2_rate": 3.0})
    assert cfg.knows("egr_open_flaps_open") and cfg.transients == "regime"
    arr = stream_residuals(regimes, feats, config=cfg)
    one = ReferenceResidualModel(models=regimes, config=cfg, window=1)
    step = [one.residuals(fv) for fv in feats]
    model = ReferenceResidualModel(models=regimes, config=cfg, window=1)
    batch = model.batch(feats, {})
    assert not isinstance(batch, ReferenceResidualModel)      # the array path was taken
    assert isinstance(batch.stream, _Stream)
    got = [batch.residuals(fv) for fv in feats]
    for a, b, c in zip(arr, step, got):
        assert (a.valid, a.status, a.regime) == (b.valid, b.status, b.regime) \
            == (c.valid, c.status, c.regime)
        np.testing.assert_allclose(a.values, b.values, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(c.values, b.values, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(c.norm, b.norm, rtol=1e-9)
    kinds = {rv.regime for rv in arr if rv.valid}
    assert {"egr_closed_flaps_open", "egr_closed_flaps_open/transient",
            "egr_open_flaps_open"} <= kinds
    # transients are diagnosed in the base regime only: elsewhere no thresholds, not valid
    other = [rv for rv in arr if rv.regime == "egr_open_flaps_open/transient"]
    assert other and not any(rv.valid for rv in other)
    assert "no thresholds for regime 'egr_open_flaps_open/transient'" in other[0].status
