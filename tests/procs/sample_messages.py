"""One fully populated message of every fdi_msgs type (plus a DiagnosticArray), as core
records converted by a MessageFactory of either flavour, for round-trip tests."""

from __future__ import annotations

from typing import Any

import numpy as np

from fdi_ros.core.types import Diagnosis, FaultEvent, FeatureVector, ResidualVector, SampleBlock


def sample_records(fac: Any) -> dict[str, Any]:
    """Topic -> message object built by ``fac`` (fdi_ros.msgs.MessageFactory)."""
    rng = np.random.default_rng(7)
    n = 12
    block = SampleBlock(plant="diesel", index=41, t=1.5 + np.arange(n) * 1e-4,
                        alpha=720.0 + np.arange(n, dtype=float),
                        channels=("n", "p2", "T2", "maf"), units=("rpm", "Pa", "K", "kg/h"),
                        values=rng.normal(size=(4, n)))
    feats = FeatureVector(plant="diesel", index=7, t_start=1.5, t_end=1.515, alpha_start=720.0,
                          valid=False, status="NaN sample at 731 deg CA",
                          names=("n", "rho2", "eta_v"), units=("rpm", "kg/m^3", "1"),
                          values=np.array([2000.0, 1.63, float("nan")]))
    res = ResidualVector(model_id="nominal", index=7, t=1.515, valid=True, status="",
                         names=("r_eta", "r_Am"), units=("1", "kg/h"),
                         values=np.array([-0.031, 2.5]), norm=1.75)
    diag = Diagnosis(index=7, t=1.515, state="isolated", min_residual_index=2,
                     min_residual_model="leak_ic_engine", fault_index=2,
                     fault_model="leak_ic_engine", candidate_faults=("leak_ic_engine",),
                     isolated_faults=("leak_ic_engine",),
                     models_online=("nominal", "leak_ic_engine"), detection_time=1.2,
                     isolation_time=float("nan"))
    fault = FaultEvent(t=1.0, fault="leak_ic_engine", size=5.0, size_unit="mm", profile="ramp",
                       ramp_s=0.5, active=True)
    feats2 = FeatureVector(plant="diesel", index=8, t_start=1.515, t_end=1.53, alpha_start=900.0,
                           valid=True, status="", names=feats.names, units=feats.units,
                           values=np.array([2001.0, 1.64, 0.87]))
    res2 = ResidualVector(model_id="nominal", index=8, t=1.53, valid=False,
                          status="not valid here: settling", names=res.names, units=res.units,
                          values=np.array([float("nan"), 0.5]), norm=float("nan"), regime="egr")
    return {
        "/fdi/sensor_block": fac.sensor_block(block),
        "/fdi/feature_blocks": fac.feature_blocks([feats, feats2], block_index=41)[0],
        "/fdi/residual_blocks": fac.residual_blocks([res, res2])[0],
        "/fdi/features": fac.features(feats),
        "/fdi/residuals": fac.residuals(res),
        "/fdi/symptoms": fac.symptoms(index=7, t=1.515, valid=True, status="",
                                      names=["s_eta", "s_Am"], levels=[-1, 2],
                                      residuals=[-0.031, 2.5], threshold_low=[-0.02, -1.0],
                                      threshold_high=[0.02, 1.0], threshold_intense=[0.05, 2.0]),
        "/fdi/diagnosis": fac.diagnosis(diag),
        "/fdi/fault_truth": fac.fault_event(fault),
    }
