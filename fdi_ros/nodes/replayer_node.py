"""Replayer: publishes a bag's messages with their original timing (or ``rate`` x faster),
driving ``/clock`` with the bag's time. Serialized messages are published as stored (no
re-encoding). By default it replays the plant side (sensor blocks and fault ground truth), so
preprocessor, residual generators and supervisor run again on recorded measurements.

Parameters: ``bag`` (required), ``rate`` (1.0; 0 = as fast as the graph acknowledges; a live
change applies from that moment on), ``topics`` (default: /fdi/sensor_block, /fdi/fault_truth),
``min_subscribers`` (1: readers of /fdi/sensor_block matched before the replay starts),
``start_delay_s``, ``publish_clock``.

When the bag is exhausted it publishes one end-of-data event on ``/fdi/end_of_data``
(``std_msgs/msg/Header``, transient-local: late joiners see it too; ``stamp`` = the bag time of
the last message, ``frame_id`` = ``"end_of_data <count>"``).
"""

from __future__ import annotations

import time
from typing import Any

from rclpy.node import Node

from fdi_ros import bag as bagio
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

PARAMS = (
    Param("bag", "", "bag directory to replay (rosbag2, MCAP); required", read_only=True,
          check=required),
    Param("rate", 1.0, "bag seconds per wall second; 0 = as fast as the readers acknowledge; "
          "a change applies from that moment on", range=(0.0, 1000.0)),
    Param("topics", ["/fdi/sensor_block", "/fdi/fault_truth"], "topics of the bag to publish",
          read_only=True),
    Param("start_delay_s", 0.0, "wall seconds before the replay starts", read_only=True,
          range=(0.0, 3600.0)),
    Param("min_subscribers", 1, "readers of /fdi/sensor_block matched before the replay starts",
          read_only=True, range=(0, 1000)),
    Param("publish_clock", True, "publish the bag's time on /clock", read_only=True),
)

END_OF_DATA_TOPIC = "/fdi/end_of_data"


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
        from std_msgs.msg import Header

        self._Header = Header
        self._end_pub = self.create_publisher(Header, END_OF_DATA_TOPIC, LATCHED_QOS)
        self._last_ns = 0  # bag time of the last message published [ns]
        self._it = bagio.read(path, list(self._pubs), raw=True)
        self._next: tuple | None = None
        self._pacer = Pacer(float(self.get_parameter("rate").value))
        follow_rate(self, self._pacer, "rate", lambda: self._last_ns * 1e-9, "bag time")
        self._start = time.monotonic() + float(self.get_parameter("start_delay_s").value)
        self._min_subs = int(self.get_parameter("min_subscribers").value)
        self.count = 0
        self.done = False
        self.create_timer(0.005, self._tick)
        self.get_logger().info(f"replaying {path} ({', '.join(self._pubs)}) at rate "
                               f"{self._pacer.rate or 'max'}")

    def _tick(self) -> None:
        if self.done or time.monotonic() < self._start:
            return
        if not self._pacer.started and any(p.get_subscription_count() < self._min_subs
                                        for t, p in self._pubs.items()
                                        if t == "/fdi/sensor_block"):
            return  # wait until the readers are matched (nothing published into the void)
        for _ in range(200):
            if self._next is None:
                self._next = next(self._it, None)
                if self._next is None:
                    self.done = True
                    end = self._Header()
                    end.stamp.sec, end.stamp.nanosec = divmod(self._last_ns, 1_000_000_000)
                    end.frame_id = f"end_of_data {self.count}"
                    self._end_pub.publish(end)
                    self.get_logger().info(f"replay finished: {self.count} messages")
                    return
            topic, _typ, t_ns, data = self._next
            if not self._pacer.started:
                self._pacer.start(time.monotonic(), t_ns * 1e-9)
            if self._pacer.rate > 0:
                if t_ns * 1e-9 > self._pacer.target(time.monotonic()):
                    return
            elif self.count % 20 == 19:
                for p in self._pubs.values():  # max rate: stay within what readers acknowledge
                    p.wait_for_all_acked()
            self._pubs[topic].publish(bytes(data))
            self._clock_out.publish(divmod(t_ns, 1_000_000_000))
            self.count += 1
            self._last_ns = t_ns
            self._next = None


def main(args: list[str] | None = None) -> int:
    return run_node(ReplayerNode, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
