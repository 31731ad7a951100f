"""The engine ECU's actuator schedule: EGR valve and swirl flaps over the speed-load map.

A passenger-car diesel of this class (2.0 L, 74 kW, EURO 3/4) recirculates exhaust gas over most
of its part-load map to lower NOx, and closes the EGR valve towards full load (smoke limit) and
at high speed; its swirl flaps close the filling ports at low speed and part load (more charge
motion for mixing and combustion) and open them at higher speed or load (filling). As maps of
speed ``n`` [rpm] and relative load ``fuel / fuel_full(n)``::

    egr_cmd   = egr_max * L(load) * S(n)      L: 1 below egr_load[0], 0 above egr_load[1],
                                               S: 1 below egr_speed[0], 0 above egr_speed[1],
                                               linear between
    swirl_cmd = 1 (filling ports closed) when n < swirl_open[0] and load < swirl_open[1],
                else 0

Scenarios use it with ``inputs.ecu:`` (settings below; ``{}`` takes the defaults); a point may
add a trim ``egr_trim`` to the scheduled EGR command (the closed-loop air-mass control of a real
ECU moves the valve around its map).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

__all__ = ["ACTUATOR_MOVE", "ACTUATOR_SETTLE_S", "GATED_ACTUATORS", "EcuSchedule",
           "actuator_status"]

# After an EGR or swirl command changes, the manifold's gas and the T2 sensor (time constant
# 0.8 s) take about three seconds to settle: the static maps do not hold meanwhile (a tip-in
# that closes the EGR valve otherwise reads as a leak for a second). Commands that moved by
# more than ACTUATOR_MOVE within the last ACTUATOR_SETTLE_S make a segment "not valid here"
# (0.5 % of the EGR valve is the area of a 1.8 mm hole).
ACTUATOR_SETTLE_S = 3.0
ACTUATOR_MOVE = 0.005
GATED_ACTUATORS = ("egr_cmd", "swirl_cmd")


def actuator_status(moved: Mapping[str, float], limit: float | None = None) -> str:
    """The "not valid" status of actuator commands that moved (name -> change) by more than
    ``limit`` (None: ACTUATOR_MOVE), "" if none."""
    limit = ACTUATOR_MOVE if limit is None else float(limit)
    big = {k: v for k, v in moved.items() if v > limit}
    if not big:
        return ""
    what = ", ".join(f"{k} by {v:.2f}" for k, v in big.items())
    return f"not valid here: actuators moved ({what} within {ACTUATOR_SETTLE_S:g} s)"


@dataclass(frozen=True)
class EcuSchedule:
    """EGR and swirl-flap maps (see the module docstring); full-load fuel [mg/stroke] over
    speed [rpm] as breakpoints ``full_n``, ``full_fuel``."""

    egr_max: float = 0.6
    # relative load below which the valve is at egr_max, above which it is closed
    egr_load: tuple[float, float] = (0.35, 0.75)
    # speed [rpm] up to which the valve is at its load map, above which it is closed
    egr_speed: tuple[float, float] = (3000.0, 3600.0)
    # flaps open (filling ports open) from this speed [rpm] or from this relative load on
    swirl_open: tuple[float, float] = (2000.0, 0.7)
    full_n: tuple[float, ...] = (800.0, 1200.0, 1600.0, 2000.0, 3000.0, 4000.0, 5000.0,
                                 5500.0)
    full_fuel: tuple[float, ...] = (26.0, 34.0, 42.0, 45.0, 42.0, 36.0, 30.0, 26.0)

    def __post_init__(self) -> None:
        for name in ("egr_load", "egr_speed", "swirl_open", "full_n", "full_fuel"):
            object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))
        if not 0.0 <= self.egr_max <= 1.0:
            raise ValueError("egr_max must be within 0..1")
        if len(self.egr_load) != 2 or not 0.0 <= self.egr_load[0] < self.egr_load[1]:
            raise ValueError("egr_load: need 0 <= open load < closed load")
        if len(self.egr_speed) != 2 or not 0.0 < self.egr_speed[0] < self.egr_speed[1]:
            raise ValueError("egr_speed: need 0 < full-map speed < closed speed")
        if len(self.swirl_open) != 2:
            raise ValueError("swirl_open: (speed, relative load)")
        if len(self.full_n) != len(self.full_fuel) or len(self.full_n) < 2 or \
                np.any(np.diff(self.full_n) <= 0) or min(self.full_fuel) <= 0:
            raise ValueError("full-load curve: increasing speeds, positive fuel, same length")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> EcuSchedule:
        d = dict(d or {})
        unknown = set(d) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"unknown ECU schedule settings {sorted(unknown)}")
        return cls(**d)

    def full_load_fuel(self, n: float) -> float:
        """Full-load fuel [mg/stroke] at speed ``n`` [rpm]: the torque limiter's (smoke and
        rated-power) curve; a torque demand above it gets this fuel."""
        return float(np.interp(n, self.full_n, self.full_fuel))

    def load(self, n: float, fuel: float) -> float:
        """Relative load: injected fuel over the full-load fuel at this speed."""
        return float(fuel) / self.full_load_fuel(n)

    def egr(self, n: float, fuel: float) -> float:
        """Scheduled EGR valve command [0..1] (0 = closed)."""
        (l_open, l_closed), (n_hi, n_off) = self.egr_load, self.egr_speed
        w_load = np.clip((l_closed - self.load(n, fuel)) / (l_closed - l_open), 0.0, 1.0)
        w_n = np.clip((n_off - n) / (n_off - n_hi), 0.0, 1.0)
        return float(self.egr_max * w_load * w_n)

    def swirl(self, n: float, fuel: float) -> float:
        """Scheduled swirl-flap command: 1 = filling ports closed, 0 = open."""
        n_open, load_open = self.swirl_open
        return 1.0 if n < n_open and self.load(n, fuel) < load_open else 0.0

    def commands(self, n: float, fuel: float, egr_trim: float = 0.0) -> tuple[float, float]:
        """(egr_cmd, swirl_cmd) at speed n [rpm] and fuel [mg/stroke], EGR trimmed (a trim
        never opens a valve the map keeps closed)."""
        e = self.egr(n, fuel)
        if e > 0.0:
            e = float(np.clip(e + egr_trim, 0.0, 1.0))
        return e, self.swirl(n, fuel)
