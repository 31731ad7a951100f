"""The start-up handshake and the end of the data, shared by the data sources (plant,
replayer) and the supervisor.

A source sends its first block only once every part that decides will see it: the readers of
its ``/fdi/sensor_block`` publisher *matched* (its own DDS matches, not a guess from timing)
and the supervisor's ready signal on ``/fdi/ready``, which the supervisor sends once the bank
is active and every reader of the features, residuals and diagnoses is there
(:meth:`fdi_ros.core.supervision.SupervisorCore.waiting_for`). Otherwise the first segments
would miss some reader, the filters' warm-up would end elsewhere than offline and a live run
would differ from ``fdi-ros diagnose``. At its end a source publishes the end-of-data event.
While it runs, a source waits whenever its data is ``max_ahead_s`` of plant time ahead of the
last diagnosis (:class:`DiagnosisHold`): a graph slower than the data holds the source back
instead of skipping segments, so a busy machine changes the pace, not the diagnosis.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor

from fdi_ros.core.handshake import readers_text
from fdi_ros.core.pacing import HoldBack
from fdi_ros.nodes.common import DATA_IN_QOS, LATCHED_QOS, Param
from fdi_ros.nodes.endofdata import END_OF_DATA_TOPIC, end_message

# The supervisor's "the graph is ready for data" signal: std_msgs/msg/Header, transient-local
# (a late joiner still sees it). The end of the data: fdi_ros.nodes.endofdata.
READY_TOPIC = "/fdi/ready"
SOURCE_PARAMS = (
    Param("min_subscribers", 1, "the data starts once this many readers of /fdi/sensor_block "
          "are matched (the preprocessor, the supervisor, a recorder; earlier blocks would be "
          "lost)", read_only=True, range=(0, 1000)),
    Param("wait_for_ready", False, "the data starts once the supervisor says on /fdi/ready that "
          "every reader that matters is matched and the bank is active", read_only=True),
    Param("start_delay_s", 0.0, "wall seconds to wait, once the above hold, before the data "
          "starts", read_only=True, range=(0.0, 3600.0)),
    Param("max_ahead_s", 1.0, "plant seconds (the blocks' stamps) the data may run ahead of "
          "the last diagnosis on /fdi/diagnosis: a graph slower than the data holds the source "
          "back instead of skipping segments (0: never wait, a source that keeps real time "
          "whatever the graph does)", range=(0.0, 3600.0)),
)


def ready_messages(subs: Mapping[str, Any], Header: Any) -> list[Any]:
    """What the supervisor sends on ``/fdi/ready`` when the graph is ready: who reads the
    features (:func:`fdi_ros.core.handshake.readers_text`), then ``"ready"``."""
    return [Header(frame_id=readers_text(subs)), Header(frame_id="ready")]


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


class DiagnosisHold:
    """The source side of :class:`fdi_ros.core.pacing.HoldBack`: follows ``/fdi/diagnosis`` and
    the source's ``max_ahead_s`` (changeable on line); :meth:`held` says whether the data of
    plant time ``t`` must wait. While it waits the source's pacer is anchored at ``anchor``
    (the waiting data's time on the pacer's clock), so once released the data goes on at its
    rate instead of racing to catch up."""

    def __init__(self, node: Any) -> None:
        from fdi_msgs.msg import Diagnosis

        self._node, self.core = node, HoldBack()
        self._sub = node.create_subscription(Diagnosis, "/fdi/diagnosis", lambda m: (
            self.core.diagnosis(float(m.t_s), time.monotonic())), DATA_IN_QOS)

    def held(self, t: float, pacer: Any, anchor: float, rate_name: str) -> bool:
        self.core.ahead_s = float(self._node.get_parameter("max_ahead_s").value)
        now = time.monotonic()
        if not self.core.hold(t, now, self._sub.get_publisher_count() > 0):
            return False
        pacer.start(now, anchor)
        if self.core.held == 1:
            self._node.get_logger().warn(
                f"the graph is slower than {rate_name} {pacer.rate or 'max'}: the data waits "
                f"for the diagnosis ({self.core.ahead_s:g} s ahead)")
        return True


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
