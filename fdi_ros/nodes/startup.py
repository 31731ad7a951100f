"""The start-up handshake and the end of the data, shared by the data sources (plant,
replayer) and the supervisor.

A source sends its first block only once every part that decides will see it: the readers of
its ``/fdi/sensor_block`` publisher *matched* (its own DDS matches, not a guess from timing)
and the supervisor's ready signal on ``/fdi/ready``, which the supervisor sends once the bank
is active and every reader of the features, residuals and diagnoses is there
(:meth:`fdi_ros.core.supervision.SupervisorCore.waiting_for`). Otherwise the first segments
would miss some reader, the filters' warm-up would end elsewhere than offline and a live run
would differ from ``fdi-ros diagnose``. At its end a source publishes the end-of-data event.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor

from fdi_ros.nodes.common import LATCHED_QOS, Param

# The supervisor's "the graph is ready for data" signal, and a source's "no more data" event:
# std_msgs/msg/Header, transient-local (a late joiner still sees them).
READY_TOPIC = "/fdi/ready"
END_OF_DATA_TOPIC = "/fdi/end_of_data"
# The end passed down the pipeline, each stage once it has handled everything before it:
# the source's "end_of_data <sensor blocks sent>", the preprocessor's
# "end_of_features <last feature index>" (-1: none) once it has every block, the supervisor's
# "end_of_diagnosis <last feature index>" once that segment is diagnosed. ``stamp``: the
# plant time the data ended. A run has ended when the end of the diagnosis has come and the
# diagnosis it names has been seen (:func:`fdi_ros.graphwatch.run_ended`).
END_OF_FEATURES_TOPIC = "/fdi/end_of_features"
END_OF_DIAGNOSIS_TOPIC = "/fdi/end_of_diagnosis"


def end_message(kind: str, t_s: float, n: int) -> Any:
    """A ``std_msgs/Header`` end event ``"<kind> <n>"`` stamped with plant time ``t_s``."""
    from std_msgs.msg import Header

    m = Header(frame_id=f"{kind} {int(n)}")
    m.stamp.sec, m.stamp.nanosec = divmod(max(0, round(float(t_s) * 1e9)), 1_000_000_000)
    return m


def read_end(m: Any, kind: str) -> tuple[float, int] | None:
    """(plant time, n) of an end event of ``kind``; None for anything else."""
    word, _, n = str(m.frame_id).partition(" ")
    try:
        return (m.stamp.sec + m.stamp.nanosec * 1e-9, int(n)) if word == kind else None
    except ValueError:
        return None
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
        self._said = -math.inf
        self._end = node.create_publisher(Header, END_OF_DATA_TOPIC, LATCHED_QOS)
        if not self.ready:
            node.create_subscription(Header, READY_TOPIC, self._on_ready, LATCHED_QOS)

    def _on_ready(self, m: Any) -> None:
        if not self.ready and m.frame_id == "ready":
            self.ready = True
            self._node.get_logger().info("the supervisor says the graph is ready")

    def check(self, now: float, pacer: Any, t_data: float) -> bool:
        """True once the data may flow (and from then on): starts ``pacer`` (a
        :class:`~fdi_ros.core.pacing.Pacer`) at data time ``t_data`` when the gate opens."""
        if pacer.started:
            return True
        n = self._pub.get_subscription_count() if self._pub is not None else self._min
        waiting = ([f"{n}/{self._min} readers of /fdi/sensor_block matched"]
                   if n < self._min else []) + ([] if self.ready else ["/fdi/ready"])
        if waiting and now - self._said > 5.0:
            self._said = now
            self._node.get_logger().info(f"data waits for: {'; '.join(waiting)}")
        if not pacer.start_when_ready(now, t_data, readers_ok=not waiting, delay_s=self._delay):
            return False
        self._node.get_logger().info(f"data starts: {n} readers matched")
        return True

    def end(self, t_ns: int, blocks: int) -> None:
        """The end-of-data event: ``stamp`` = time of the last data, ``frame_id`` =
        ``"end_of_data <sensor blocks sent>"``."""
        self._end.publish(end_message("end_of_data", t_ns * 1e-9, blocks))


class EndOfFeatures:
    """The preprocessor's part of the end: count the sensor blocks received and, once the
    source's end event says no more will come and all of them are here, publish
    ``end_of_features <last feature index>``. Blocks lost on the way are waited for
    ``wait_s`` wall seconds of silence (health only), then named and not waited for."""

    def __init__(self, node: Any, wait_s: float = 2.0) -> None:
        from std_msgs.msg import Header

        self._node, self._wait_s = node, wait_s
        self.blocks, self.last_index, self._wall = 0, -1, time.monotonic()
        self._end: tuple[float, int] | None = None
        self._said = False
        self._pub = node.create_publisher(Header, END_OF_FEATURES_TOPIC, LATCHED_QOS)
        node.create_subscription(Header, END_OF_DATA_TOPIC, self._on_end, LATCHED_QOS)
        node.create_timer(0.25, self.check)

    def block(self, last_index: int) -> None:
        """A sensor block was handled; ``last_index``: the last feature index published."""
        self.blocks, self.last_index, self._wall = self.blocks + 1, last_index, time.monotonic()
        self.check()

    def _on_end(self, m: Any) -> None:
        if self._end is None and (end := read_end(m, "end_of_data")) is not None:
            self._end, self._wall = end, max(self._wall, time.monotonic())
            self.check()

    def check(self) -> None:
        if self._end is None or self._said:
            return
        t, sent = self._end
        if self.blocks < sent:
            if time.monotonic() - self._wall <= self._wait_s:
                return
            self._node.get_logger().warn(f"end of data: {sent - self.blocks} of {sent} sensor "
                                         "blocks never arrived")
        self._said = True
        self._pub.publish(end_message("end_of_features", t, self.last_index))
        self._node.get_logger().info(f"end of data at t = {t:.3f} s: {self.blocks} blocks, "
                                     f"last features {self.last_index}")


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
