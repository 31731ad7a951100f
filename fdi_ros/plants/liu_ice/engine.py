"""The LiU-ICE engine's speed-density model for the discrepancy analysis.

A cubic eta_V(n, p_im) of the generic :class:`~fdi_ros.core.meanvalue.SpeedDensityModel` with
the filling of the manifold and charge-air volumes, identified on the fault-free windows.
"""

from __future__ import annotations

from fdi_ros.core.meanvalue import SpeedDensityModel
from fdi_ros.core.measured import Measured
from fdi_ros.plants.liu_ice import DISPLACEMENT_L, FAULT_FREE

# Names kept for the discrepancy tool's callers.
LIU_ICE_DISPLACEMENT_L = DISPLACEMENT_L
LIU_ICE_FAULT_FREE = FAULT_FREE


def liu_ice_model_template() -> SpeedDensityModel:
    """Speed-density model of the LiU-ICE engine: eta_V cubic in (n, p_im), filling of the
    manifold and the charge-air volume (intercooler pressure), leak to ambient."""
    return SpeedDensityModel(displacement_l=DISPLACEMENT_L, n="n", p="p_im", T="T_im",
                             channel="maf", flow_scale=3600.0, degree=3,
                             storage=("p_im", "p_ic"), derivative_window_s=0.1,
                             leak_p_amb="p_amb", leak_T_amb="T_amb", leak_cd=0.7)


def identify_liu_ice(records: list[Measured], *, fraction: float = 0.6) -> SpeedDensityModel:
    """Identify the LiU-ICE model on the first ``fraction`` of each fault-free record."""
    if not 0.1 <= fraction <= 1.0:
        raise ValueError("fraction must be within [0.1, 1]")
    parts = [r.window(r.t[0], r.t[0] + fraction * (r.t[-1] - r.t[0])) for r in records]
    return liu_ice_model_template().fit(parts)
