"""What every fdi_ros node shares: QoS, parameters with descriptors, /clock and live rate
changes; the loopback guard and the main() wrapper (:mod:`fdi_ros.nodes.spin`, also importable
from here).

Nodes only translate parameters and messages and own timers and lifecycle; all numbers come
from :mod:`fdi_ros.core`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from fdi_ros.nodes.spin import DRAIN_S, ensure_loopback_env, run_node, wall_timer

__all__ = ["DATA_IN_QOS", "DATA_QOS", "DRAIN_S", "LATCHED_QOS", "REQUEST_QOS", "ClockOut",
           "Param", "declare_params", "ensure_loopback_env", "follow_rate", "required",
           "run_node", "wall_timer"]

# Data streams out: reliable, each writer keeps its last 500 messages for a reader behind.
DATA_QOS = QoSProfile(depth=500, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE)
# Data streams in: KEEP_ALL, so a reader that is busy (a snapshot written, a starved core)
# delays what it received and never drops it; a keep-last queue is shared by all writers of
# a topic (16 residual nodes filled 500 in 0.7 s and lost residuals). A reader stopped for
# good costs nothing: the writers' keep-last histories bound what waits for it.
DATA_IN_QOS = QoSProfile(depth=500, history=HistoryPolicy.KEEP_ALL,
                         reliability=ReliabilityPolicy.RELIABLE)
# Events that late joiners must still see (fault ground truth, injections).
LATCHED_QOS = QoSProfile(depth=50, history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
# Requests from users and scripts (fault injection): reliable and VOLATILE, which matches both
# a default publisher (`ros2 topic pub`) and a transient-local one. A volatile reader receives
# no history, so nothing published before this node (re)started is replayed into the plant.
REQUEST_QOS = QoSProfile(depth=50, history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)


@dataclass(frozen=True)
class Param:
    """One node parameter as ``ros2 param describe`` shows it.

    ``default`` fixes the type (float -> double, int -> integer, str, bool, list of str);
    ``range`` (inclusive) is enforced by rclpy on every set; ``check`` returns the reason a
    value is refused (None when fine) and runs on the start value and on every live change;
    ``read_only``: the node reads the value once (a live change could not apply).
    """

    name: str
    default: Any
    description: str
    read_only: bool = False
    range: tuple[float, float] | None = None
    check: Callable[[Any], str | None] | None = None


def required(value: Any) -> str | None:
    """A ``Param.check`` for a parameter that must be given (not empty)."""
    return None if value else "is required (no value given)"


def declare_params(node: Any, params: Sequence[Param]) -> None:
    """Declare ``params`` on ``node``, each with a descriptor of its own; refuse a bad live value
    through ``set_parameters`` with the reason, and a bad start value with ValueError.

    An integer sent for a double parameter (``ros2 param set /n realtime_factor 4``) is taken
    as that double.
    """
    doubles = set()
    for p in params:
        d = ParameterDescriptor(name=p.name, description=p.description, read_only=p.read_only)
        if p.range is not None:
            lo, hi = p.range
            if isinstance(p.default, float):
                d.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                             to_value=float(hi), step=0.0)]
            elif isinstance(p.default, int) and not isinstance(p.default, bool):
                d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
            else:
                raise TypeError(f"parameter {p.name}: a range needs a number default")
        if isinstance(p.default, float):
            doubles.add(p.name)
        node.declare_parameter(p.name, p.default, d)
    checks = {p.name: p.check for p in params if p.check is not None}
    for name, check in checks.items():
        reason = check(node.get_parameter(name).value)
        if reason:
            raise ValueError(f"parameter {name}: {reason}")

    def as_double(items: list[Parameter]) -> list[Parameter]:
        return [Parameter(q.name, Parameter.Type.DOUBLE, float(q.value))
                if q.name in doubles and q.type_ == Parameter.Type.INTEGER else q
                for q in items]

    def refuse(items: list[Parameter]) -> SetParametersResult:
        for q in items:
            check = checks.get(q.name)
            reason = check(q.value) if check is not None else None
            if reason:
                return SetParametersResult(successful=False, reason=f"{q.name}: {reason}")
        return SetParametersResult(successful=True)

    node.add_pre_set_parameters_callback(as_double)
    node.add_on_set_parameters_callback(refuse)


class ClockOut:
    """``/clock`` in plant or bag time, published by the node that owns time (or nothing when
    ``enabled`` is false)."""

    def __init__(self, node: Any, enabled: bool) -> None:
        from rosgraph_msgs.msg import Clock

        self._Clock = Clock
        self._pub = node.create_publisher(Clock, "/clock", 10) if enabled else None

    def publish(self, sec_nanosec: tuple[int, int]) -> None:
        if self._pub is not None:
            c = self._Clock()
            c.clock.sec, c.clock.nanosec = sec_nanosec
            self._pub.publish(c)


def follow_rate(node: Any, pacer: Any, name: str, now: Callable[[], float], what: str) -> None:
    """Apply a live change of the rate parameter ``name`` to ``pacer`` (a
    :class:`~fdi_ros.core.pacing.Pacer`) from the data time ``now()`` on, and log it."""

    def on_set(params: list[Any]) -> None:
        for q in params:
            if q.name == name:
                t = now()
                pacer.set_rate(float(q.value), time.monotonic(), t)
                node.get_logger().info(f"{name} {q.value:g} from {what} {t:.3f} s")

    node.add_post_set_parameters_callback(on_set)
