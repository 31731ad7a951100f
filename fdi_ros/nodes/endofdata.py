"""The end of the data, passed down the pipeline: each stage says it once it has handled
everything before it.

``std_msgs/msg/Header`` events, transient-local (a late joiner still sees them), stamped with
the plant time the data ended: the source's ``"end_of_data <sensor blocks sent>"`` on
``/fdi/end_of_data`` (:meth:`fdi_ros.nodes.startup.SourceGate.end`), the preprocessor's
``"end_of_features <last feature index>"`` (-1: none) once it has every block
(:class:`EndOfFeatures`), the supervisor's ``"end_of_diagnosis <last diagnosed index>"`` once
that segment is diagnosed, or features or residuals that never came are given up (named in its
log; :meth:`fdi_ros.core.supervision.SupervisorCore.end_of_features`).
A run has ended when the end of the diagnosis has come and the diagnosis it names has been
seen (:func:`fdi_ros.graphwatch.run_ended`).
"""

from __future__ import annotations

import time
from typing import Any

from fdi_ros.nodes.common import LATCHED_QOS, wall_timer

END_OF_DATA_TOPIC = "/fdi/end_of_data"
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
        wall_timer(node, 0.25, self.check)

    def block(self, last_index: int) -> None:
        """A sensor block was handled; ``last_index``: the last feature index published. A
        block after the end was said is a new source's data (a second replay into a running
        graph): counted afresh, and its own end said again."""
        if self._said:
            self.blocks, self._end, self._said = 0, None, False
        self.blocks, self.last_index, self._wall = self.blocks + 1, last_index, time.monotonic()
        self.check()

    def _on_end(self, m: Any) -> None:
        if self._end is None and not self._said and \
                (end := read_end(m, "end_of_data")) is not None:
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
