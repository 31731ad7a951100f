"""Plant simulator node: publishes sensor blocks at the plant's pace and fault ground truth.

The plant (a wing of :mod:`fdi_ros.plants`), its scenario (inputs over time, scheduled faults)
and the block size come from :func:`fdi_ros.plants.make_runner`. A wall-clock timer advances
plant time by ``realtime_factor`` x the elapsed wall time (0 = as fast as the graph takes it);
every block is published on ``/fdi/sensor_block`` and plant time on ``/clock`` (so other nodes
can run on sim time). Faults are injected at run time on ``/fdi/fault_inject`` (``t_s`` <= 0
means "now")
and by the scenario; each fault that takes effect is published on ``/fdi/fault_truth``
(transient-local, so late joiners and the recorder see it).

Parameters: ``plant``, ``scenario`` (YAML path), ``seed``, ``realtime_factor`` (1.0),
``publish_clock`` (true), ``max_blocks_per_tick`` (bounds a catch-up burst),
``min_subscribers`` (1: wait for the preprocessor before plant time starts),
``start_delay_s`` (0: further wall seconds before plant time starts).
"""

from __future__ import annotations

import time
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node

from fdi_ros import msgs
from fdi_ros.nodes.common import DATA_QOS, LATCHED_QOS, run_node


class PlantNode(Node):
    def __init__(self) -> None:
        super().__init__("fdi_plant")
        ro = ParameterDescriptor(read_only=True)
        self.declare_parameter("plant", "", ro)
        self.declare_parameter("scenario", "", ro)
        self.declare_parameter("seed", 0, ro)
        self.declare_parameter("realtime_factor", 1.0, ParameterDescriptor(
            description="plant seconds per wall second; 0 = as fast as possible"))
        self.declare_parameter("publish_clock", True, ro)
        self.declare_parameter("max_blocks_per_tick", 50, ro)
        self.declare_parameter("min_subscribers", 1, ParameterDescriptor(
            description="plant time starts once this many readers of /fdi/sensor_block are "
                        "matched (DDS discovery takes ~0.3-3 s; earlier blocks would be lost)"))
        from fdi_msgs.msg import FaultEvent, SensorBlock
        from rosgraph_msgs.msg import Clock

        from fdi_ros.plants import make_runner

        p = self.get_parameter
        self.runner = make_runner(p("plant").value, p("scenario").value or None,
                                  seed=int(p("seed").value))
        self._fac = msgs.MessageFactory("rclpy")
        self._pub = self.create_publisher(SensorBlock, "/fdi/sensor_block", DATA_QOS)
        self._truth = self.create_publisher(FaultEvent, "/fdi/fault_truth", LATCHED_QOS)
        self._clock_pub = (self.create_publisher(Clock, "/clock", 10)
                       if p("publish_clock").value else None)
        self._Clock = Clock
        self.create_subscription(FaultEvent, "/fdi/fault_inject", self._on_inject, LATCHED_QOS)
        self._wall0: float | None = None
        self._t0 = self.runner.t
        self._min_subs = int(p("min_subscribers").value)
        self.declare_parameter("start_delay_s", 0.0, ParameterDescriptor(
            description="wall seconds to wait, once the readers are matched, before plant time "
                        "starts (time for a large bank to come on line under `fdi-ros launch`)"))
        self._delay = float(p("start_delay_s").value)
        self._ready_at: float | None = None
        self._finished = False
        self.create_timer(0.01, self._tick)
        self.get_logger().info(f"plant {self.runner.plant!r} ready, scenario "
                               f"{p('scenario').value or '(default)'}")

    def _on_inject(self, m: Any) -> None:
        ev = msgs.to_fault_event(m)
        if ev.t <= 0.0:
            ev = type(ev)(**{**ev.__dict__, "t": self.runner.t})
        self.runner.inject(ev)
        self.get_logger().info(f"fault injection accepted: {ev.fault} {ev.size} {ev.size_unit} "
                               f"at t = {ev.t:.3f} s")

    def _tick(self) -> None:
        if self._finished:
            return
        if self._wall0 is None:
            if self._pub.get_subscription_count() < self._min_subs:
                return
            if self._ready_at is None:
                self._ready_at = time.monotonic() + self._delay
            if time.monotonic() < self._ready_at:
                return
        now = time.monotonic()
        if self._wall0 is None:
            self._wall0 = now
        rtf = float(self.get_parameter("realtime_factor").value)
        target = self._t0 + (now - self._wall0) * rtf if rtf > 0 else float("inf")
        for _ in range(int(self.get_parameter("max_blocks_per_tick").value)):
            if self.runner.done:
                self._finished = True
                self.get_logger().info(f"scenario finished at t = {self.runner.t:.3f} s")
                return
            if self.runner.t >= target:
                break
            block = self.runner.next_block()
            for ev in self.runner.pop_truth():
                self._truth.publish(self._fac.fault_event(ev))
                self.get_logger().info(f"fault active: {ev.fault} {ev.size} {ev.size_unit} "
                                       f"at t = {ev.t:.3f} s")
            self._pub.publish(self._fac.sensor_block(block))
            if self._clock_pub is not None:
                sec, nsec = msgs.stamp_fields(float(block.t[-1]))
                c = self._Clock()
                c.clock.sec, c.clock.nanosec = sec, nsec
                self._clock_pub.publish(c)


def main(args: list[str] | None = None) -> int:
    return run_node(PlantNode, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
