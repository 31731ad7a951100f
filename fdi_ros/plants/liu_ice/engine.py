"""The LiU-ICE air path's residuals for the discrepancy analysis.

Three relations, identified on the fault-free windows (:class:`~fdi_ros.core.residualset.
ResidualSet`):

* ``maf``: speed density, a cubic eta_V(n, p_im) with the filling of the manifold and
  charge-air volumes (:class:`~fdi_ros.core.meanvalue.SpeedDensityModel`); reads n, p_im,
  T_im, p_ic;
* ``p_ic``: the boost pressure over ambient as a quadratic map of speed, air flow and
  wastegate position with a first-order lag (the turbocharger's inertia); reads p_amb, n,
  maf, wastegate;
* ``maf_throttle``: the same air flow through the throttle (orifice flow from p_ic to p_im
  through an effective area cubic in the throttle position); reads throttle, p_ic, p_im,
  T_im. Its effective area differs by a few percent between test runs (the position sensor
  near idle), so it proposes nothing: it checks the leading explanations (a gain of the air
  flow sensor moves it, a gain of the speed sensor does not; a leak behind the throttle
  leaves it alone).

An error of a sensor is scored on every relation that reads the sensor
(:mod:`fdi_ros.core.discrepancy.joint`): the air-mass flow in all three, the boost pressure
in the boost map and the throttle, the manifold pressure in speed density and throttle, the
speed in speed density and the boost map.
"""

from __future__ import annotations

from fdi_ros.core.meanvalue import SpeedDensityModel
from fdi_ros.core.measured import Measured
from fdi_ros.core.residualset import PressureMapModel, ResidualSet, ThrottleFlowModel
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


def liu_ice_residuals_template() -> ResidualSet:
    """The three relations of the module docstring, not identified yet."""
    return ResidualSet(models=(liu_ice_model_template(),
                               PressureMapModel(channel="p_ic", reference="p_amb",
                                                regressors=("n", "maf", "wastegate"),
                                                degree=2, max_lag_s=3.0),
                               ThrottleFlowModel(name="maf_throttle", channel="maf",
                                                 position="throttle", p_up="p_ic",
                                                 p_down="p_im", T="T_im", degree=3)),
                       checks=("maf_throttle",))


def identify_liu_ice(records: list[Measured], *, fraction: float = 0.6,
                     speed_density_only: bool = False) -> SpeedDensityModel | ResidualSet:
    """Identify the LiU-ICE relations on the first ``fraction`` of each fault-free record
    (``speed_density_only``: the speed-density relation alone)."""
    if not 0.1 <= fraction <= 1.0:
        raise ValueError("fraction must be within [0.1, 1]")
    parts = [r.window(r.t[0], r.t[0] + fraction * (r.t[-1] - r.t[0])) for r in records]
    if speed_density_only:
        return liu_ice_model_template().fit(parts)
    return liu_ice_residuals_template().fit(parts)
