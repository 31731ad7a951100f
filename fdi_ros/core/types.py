"""Data records shared by the core, the nodes and the bag tools.

They mirror the fdi_msgs messages (``msg_defs/fdi_msgs/msg``) one to one, as plain numpy
records, so the numerical core never needs a ROS type. ``fdi_ros.msgs`` converts both ways.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class SampleBlock:
    """A block of sensor samples (mirrors ``fdi_msgs/SensorBlock``).

    Attributes
    ----------
    plant : plant configuration id ("diesel", "turbofan").
    index : running block counter of the producer (a gap means a dropped block).
    t : (n,) sample times [s], plant time.
    alpha : (n,) unwrapped crank angle [deg CA], or an empty array for time-sampled plants.
    channels, units : channel names and their units, e.g. ("n", "p2") and ("rpm", "Pa").
    values : (n_channels, n) sample values; NaN marks a missing sample.
    """

    plant: str
    index: int
    t: np.ndarray
    alpha: np.ndarray
    channels: tuple[str, ...]
    units: tuple[str, ...]
    values: np.ndarray

    def __post_init__(self) -> None:
        n = self.t.shape[0]
        if self.values.shape != (len(self.channels), n):
            raise ValueError(
                f"values shape {self.values.shape} != "
                f"(channels {len(self.channels)}, samples {n})")
        if len(self.units) != len(self.channels):
            raise ValueError("one unit per channel is required")
        if self.alpha.size not in (0, n):
            raise ValueError("alpha must be empty or have one entry per sample")

    def channel(self, name: str) -> np.ndarray:
        """Samples of one channel by name."""
        try:
            row: np.ndarray = self.values[self.channels.index(name)]
        except ValueError:
            raise KeyError(f"channel {name!r} not in block (has {self.channels})") from None
        return row


# position of each name in a FeatureVector's names (by the names tuple): get() is asked per
# segment, bank model and feature
_POSITIONS: dict[tuple[str, ...], dict[str, int]] = {}


@dataclass(frozen=True)
class FeatureVector:
    """One feature vector: a 180 deg CA segment, or one sample (mirrors ``fdi_msgs/Features``)."""

    plant: str
    index: int
    t_start: float
    t_end: float
    alpha_start: float
    valid: bool
    status: str
    names: tuple[str, ...]
    units: tuple[str, ...]
    values: np.ndarray

    def get(self, name: str) -> float:
        """One feature value by name."""
        at = _POSITIONS.get(self.names)
        if at is None:
            if len(_POSITIONS) >= 64:  # a stream has one or two name sets: a bound, not a cache
                _POSITIONS.clear()
            at = _POSITIONS[self.names] = {k: i for i, k in enumerate(self.names)}
        try:
            return float(self.values[at[name]])
        except KeyError:
            raise KeyError(f"feature {name!r} not in {self.names}") from None

    def as_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in zip(self.names, self.values)}


@dataclass(frozen=True)
class ResidualVector:
    """Residuals of one bank model for one feature vector (mirrors ``fdi_msgs/Residuals``)."""

    model_id: str
    index: int
    t: float
    valid: bool
    status: str
    names: tuple[str, ...]
    units: tuple[str, ...]
    values: np.ndarray
    norm: float
    #: the operating regime whose models (and thresholds) gave these residuals; "" when the
    #: model knows one regime only (see :class:`fdi_ros.core.symptoms.SymptomConfig`)
    regime: str = ""


@dataclass(frozen=True)
class FaultEvent:
    """A fault injection or ground-truth event (mirrors ``fdi_msgs/FaultEvent``).

    ``fault`` is a plant fault id ("" clears all faults); ``size`` is in ``size_unit``
    (e.g. 5.0 "mm" for a leak diameter); ``profile`` is "step" or "ramp" (see
    :meth:`size_at`).
    """

    t: float
    fault: str
    size: float = 1.0
    size_unit: str = "1"
    profile: str = "step"
    ramp_s: float = 0.0
    active: bool = True

    def __post_init__(self) -> None:
        if self.profile not in ("step", "ramp"):
            raise ValueError(f"profile must be 'step' or 'ramp', not {self.profile!r}")
        if self.profile == "ramp" and not self.ramp_s > 0:
            raise ValueError("a ramp needs ramp_s > 0")

    def size_at(self, t: float, before: float = 0.0) -> float:
        """The one meaning of the profiles: the fault's size at time ``t`` >= ``self.t``, given
        its size ``before`` the event. "step": the event's size at once; "ramp": linear from
        ``before`` to the event's size over ``ramp_s``."""
        if self.profile != "ramp":
            return self.size
        return before + ramp_fraction(t, self.t, self.ramp_s) * (self.size - before)


def ramp_fraction(t: float, t_event: float, ramp_s: float) -> float:
    """How far a ramp that started at ``t_event`` has come at ``t`` (1 at once if ramp_s <= 0)."""
    return 1.0 if ramp_s <= 0 else min((t - t_event) / ramp_s, 1.0)


@dataclass(frozen=True)
class Diagnosis:
    """The supervisor's state after one feature vector (mirrors ``fdi_msgs/Diagnosis``)."""

    index: int
    t: float
    state: str  # "no_fault" | "detected" | "isolated" | "not_valid"
    min_residual_index: int = -1
    min_residual_model: str = ""
    fault_index: int = -1
    fault_model: str = ""
    candidate_faults: tuple[str, ...] = ()
    isolated_faults: tuple[str, ...] = ()
    models_online: tuple[str, ...] = ()
    detection_time: float = float("nan")
    isolation_time: float = float("nan")
    extra: dict[str, Any] = field(default_factory=dict)
