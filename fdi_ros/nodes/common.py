"""What every fdi_ros node shares: QoS, parameters with descriptors, the loopback guard, and a
main() wrapper.

Nodes only translate parameters and messages and own timers and lifecycle; all numbers come
from :mod:`fdi_ros.core`.
"""

from __future__ import annotations

import math
import os
import signal
import sys
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
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

# Data streams: reliable with a deep queue, so a busy 2-core machine delays rather than drops.
DATA_QOS = QoSProfile(depth=500, history=HistoryPolicy.KEEP_LAST,
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


def declare_table(node: Any, table: Mapping[str, tuple]) -> dict[str, Any]:
    """Declare parameters given as ``{name: (default, description, read_only, (min, max) or
    None)}`` (the form a pure core module can hold); returns their start values."""
    out = {}
    for name, (default, text, ro, rng) in table.items():
        d = ParameterDescriptor(name=name, description=text, read_only=ro)
        if rng is not None:
            d.floating_point_range = [FloatingPointRange(from_value=rng[0], to_value=rng[1])]
        value = node.declare_parameter(name, default, d).value
        out[name] = float(value) if isinstance(default, float) else value
    return out


# After a stop signal, keep executing callbacks this long for data already delivered.
DRAIN_S = 0.3


def ensure_loopback_env() -> None:
    """Keep DDS discovery on this machine unless the user chose otherwise explicitly."""
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def run_node(make_node: Callable[[], Any], *, executor_threads: int = 1,
             on_shutdown: Callable[[Any], None] | None = None,
             args: list[str] | None = None) -> int:
    """Initialise rclpy, spin one node until SIGINT/SIGTERM, shut down cleanly.

    SIGTERM is turned into the same orderly shutdown as SIGINT, so a node killed by the
    launcher still runs ``on_shutdown`` (the recorder closes its bag there).
    """
    ensure_loopback_env()
    import rclpy
    from rclpy.executors import (
        ExternalShutdownException,
        MultiThreadedExecutor,
        SingleThreadedExecutor,
    )
    from rclpy.signals import SignalHandlerOptions

    # Our own SIGINT/SIGTERM handling: stop spinning, then drain what DDS already delivered
    # (a recorder must not lose acknowledged messages), then shut down.
    rclpy.init(args=args if args is not None else sys.argv,
               signal_handler_options=SignalHandlerOptions.NO)
    node = None
    stopping = {"flag": False}

    def _stop(signum: int, frame: Any) -> None:
        stopping["flag"] = True

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    code = 0
    try:
        node = make_node()
        ex = (MultiThreadedExecutor(num_threads=executor_threads) if executor_threads > 1
              else SingleThreadedExecutor())
        ex.add_node(node)
        while not stopping["flag"] and rclpy.ok():
            ex.spin_once(timeout_sec=0.1)
        deadline = time.monotonic() + DRAIN_S
        while rclpy.ok() and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.02)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        traceback.print_exc()
        code = 1
    finally:
        if node is not None:
            if on_shutdown is not None:
                try:
                    on_shutdown(node)
                except Exception:
                    traceback.print_exc()
                    code = 1
            try:
                node.destroy_node()
            except Exception:
                pass
        rclpy.try_shutdown()
    return code


# The supervisor's "the graph is ready for data" signal, and a source's "no more data" event:
# std_msgs/msg/Header, transient-local (a late joiner still sees them).
READY_TOPIC = "/fdi/ready"
END_OF_DATA_TOPIC = "/fdi/end_of_data"
SOURCE_PARAMS = (
    Param("min_subscribers", 1, "the data starts once this many readers of /fdi/sensor_block "
          "are matched (the preprocessor, the supervisor, a recorder; earlier blocks would be "
          "lost)", read_only=True, range=(0, 1000)),
    Param("wait_for_ready", False, "the data starts once the supervisor says on /fdi/ready that "
          "every reader that matters is matched and the bank is active", read_only=True),
    Param("start_delay_s", 0.0, "wall seconds to wait, once the above hold, before the data "
          "starts", read_only=True, range=(0.0, 3600.0)),
)


class SourceGate:
    """When a data source (plant, replayer) may publish its first block: once ``min_subscribers``
    readers of its ``/fdi/sensor_block`` publisher are *matched* (its own DDS matches, not a
    guess from timing), the supervisor's ready signal has come (with ``wait_for_ready``) and
    ``start_delay_s`` has passed (``pub`` None: no reader to wait for). Until then it logs every
    few seconds what it waits for. Publishes the end-of-data event too (:meth:`end`)."""

    def __init__(self, node: Any, pub: Any) -> None:
        from std_msgs.msg import Header

        p = node.get_parameter
        self._node, self._pub, self._Header = node, pub, Header
        self._min = int(p("min_subscribers").value)
        self._delay = float(p("start_delay_s").value)
        self.ready = not p("wait_for_ready").value
        self.open = False
        self._at: float | None = None
        self._said = -math.inf
        self._end = node.create_publisher(Header, END_OF_DATA_TOPIC, LATCHED_QOS)
        if not self.ready:
            node.create_subscription(Header, READY_TOPIC, self._on_ready, LATCHED_QOS)

    def _on_ready(self, m: Any) -> None:
        if not self.ready and m.frame_id == "ready":
            self.ready = True
            self._node.get_logger().info("the supervisor says the graph is ready")

    def check(self, now: float) -> bool:
        """True once the data may flow (and from then on)."""
        if self.open:
            return True
        n = self._pub.get_subscription_count() if self._pub is not None else self._min
        waiting = ([f"{n}/{self._min} readers of /fdi/sensor_block matched"]
                   if n < self._min else []) + ([] if self.ready else ["/fdi/ready"])
        if waiting:
            self._at = None
            if now - self._said > 5.0:
                self._said = now
                self._node.get_logger().info(f"data waits for: {'; '.join(waiting)}")
            return False
        if self._at is None:
            self._at = now + self._delay
        self.open = now >= self._at
        if self.open:
            self._node.get_logger().info(f"data starts: {n} readers matched")
        return self.open

    def end(self, t_ns: int, count: int) -> None:
        """The end-of-data event: ``stamp`` = time of the last data, ``frame_id`` =
        ``"end_of_data <count>"``."""
        m = self._Header(frame_id=f"end_of_data {count}")
        m.stamp.sec, m.stamp.nanosec = divmod(int(t_ns), 1_000_000_000)
        self._end.publish(m)
