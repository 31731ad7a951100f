"""Replayer: publishes a bag's messages with their original timing (or ``rate`` x faster),
driving ``/clock`` with the bag's time. Serialized messages are published as stored (no
re-encoding). By default it replays the plant side (sensor blocks and fault ground truth), so
preprocessor, residual generators and supervisor run again on recorded measurements.

Parameters: ``bag`` (required), ``rate`` (1.0; 0 = as fast as the graph acknowledges; a live
change applies from that moment on), ``topics`` (default: /fdi/sensor_block, /fdi/fault_truth),
``publish_clock``, ``max_ahead_s`` (1.0: the data waits while it is that far ahead of the
diagnosis on ``/fdi/diagnosis``; 0: never), and the start gate of every source
(:class:`fdi_ros.nodes.startup.SourceGate`:
``min_subscribers`` matched readers, ``wait_for_ready`` the supervisor's ``/fdi/ready``,
``start_delay_s``).

When the bag is exhausted it publishes one end-of-data event on ``/fdi/end_of_data``
(``std_msgs/msg/Header``, transient-local: late joiners see it too; ``stamp`` = the bag time of
the last message, ``frame_id`` = ``"end_of_data <sensor blocks sent>"``).
"""

from __future__ import annotations

import time
from typing import Any

from rclpy.node import Node

from fdi_ros import bag as bagio
from fdi_ros import msgs
from fdi_ros.core.pacing import Pacer
from fdi_ros.nodes.common import (
    DATA_QOS,
    LATCHED_QOS,
    ClockOut,
    Param,
    declare_params,
    follow_rate,
    required,
    run_node,
)
from fdi_ros.nodes.recorder_node import _msg_class
from fdi_ros.nodes.startup import SOURCE_PARAMS, DiagnosisHold, SourceGate

PARAMS = (
    Param("bag", "", "bag directory to replay (rosbag2, MCAP); required", read_only=True,
          check=required),
    Param("rate", 1.0, "bag seconds per wall second; 0 = as fast as the readers acknowledge; "
          "a change applies from that moment on", range=(0.0, 1000.0)),
    Param("topics", ["/fdi/sensor_block", "/fdi/fault_truth"], "topics of the bag to publish",
          read_only=True),
    Param("publish_clock", True, "publish the bag's time on /clock", read_only=True),
    *SOURCE_PARAMS,
)


class ReplayerNode(Node):
    def __init__(self) -> None:
        super().__init__("fdi_replayer")
        declare_params(self, PARAMS)
        path = self.get_parameter("bag").value
        topics = list(self.get_parameter("topics").value)
        available = bagio.topics(path)
        self._pubs: dict[str, Any] = {}
        for t in topics:
            if t not in available:
                self.get_logger().warn(f"bag has no topic {t}")
                continue
            qos = LATCHED_QOS if t.startswith("/fdi/fault_") else DATA_QOS
            self._pubs[t] = self.create_publisher(_msg_class(available[t][0]), t, qos)
        self._clock_out = ClockOut(self, bool(self.get_parameter("publish_clock").value))
        self._last_ns = 0  # bag time of the last message published [ns]
        self._it = bagio.read(path, list(self._pubs), raw=True)
        self._next: tuple | None = next(self._it, None)  # the first message: its time starts
        self._t0_s = self._next[2] * 1e-9 if self._next is not None else 0.0  # the pacer
        self._pacer = Pacer(float(self.get_parameter("rate").value))
        follow_rate(self, self._pacer, "rate", lambda: self._last_ns * 1e-9, "bag time")
        self._gate = SourceGate(self, self._pubs.get("/fdi/sensor_block"))
        self.count = self.blocks = 0
        self._hold = DiagnosisHold(self)
        self.done = False
        self.create_timer(0.005, self._tick)
        self.get_logger().info(f"replaying {path} ({', '.join(self._pubs)}) at rate "
                               f"{self._pacer.rate or 'max'}")

    def _tick(self) -> None:
        if self.done or not self._gate.check(time.monotonic(), self._pacer, self._t0_s):
            return  # nothing published into the void (see SourceGate)
        for _ in range(200):
            if self._next is None:
                self._next = next(self._it, None)
                if self._next is None:
                    self.done = True
                    self._gate.end(self._last_ns, self.blocks)
                    n = self._hold.core.held
                    self.get_logger().info(f"replay finished: {self.count} messages" + (
                        f" (held back for the diagnosis {n} times)" if n else ""))
                    return
            topic, _typ, t_ns, data = self._next
            if topic == "/fdi/sensor_block" and self._hold.held(
                    msgs.raw_header_stamp(bytes(data)), self._pacer, t_ns * 1e-9, "rate"):
                return
            if self._pacer.rate > 0:
                if t_ns * 1e-9 > self._pacer.target(time.monotonic()):
                    return
            elif self.count % 20 == 19:
                for p in self._pubs.values():  # max rate: stay within what readers acknowledge
                    p.wait_for_all_acked()
            self._pubs[topic].publish(bytes(data))
            self._clock_out.publish(divmod(t_ns, 1_000_000_000))
            self.count += 1
            self.blocks += topic == "/fdi/sensor_block"
            self._last_ns = t_ns
            self._next = None


def main(args: list[str] | None = None) -> int:
    return run_node(ReplayerNode, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
