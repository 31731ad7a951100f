"""The turbo-diesel intake plant (Schwarte & Isermann 2002) and its scenarios.

``plant``     :class:`DieselIntakePlant`, :class:`DieselParams`, fault ids and channel names
``scenario``  YAML scenarios, :func:`simulate` and :class:`SimResult`
``reference`` / ``symptoms``  reference models and symptom logic (identification side)
"""

from fdi_ros.plants.diesel.plant import (
                                       CHANNELS,
                                       FAULT_IDS,
                                       FAULT_UNITS,
                                       PLANT_ID,
                                       UNITS,
                                       DieselIntakePlant,
                                       DieselParams,
                                       boost_setpoint,
                                       eta_true,
                                       fuel_for_torque,
)
from fdi_ros.plants.diesel.scenario import (
                                       Scenario,
                                       SimResult,
                                       iter_simulate,
                                       load_cases,
                                       load_scenario,
                                       simulate,
)

__all__ = ["CHANNELS", "FAULT_IDS", "FAULT_UNITS", "PLANT_ID", "UNITS", "DieselIntakePlant",
           "DieselParams", "Scenario", "SimResult", "boost_setpoint", "eta_true",
           "fuel_for_torque", "iter_simulate", "load_cases", "load_scenario", "simulate"]
