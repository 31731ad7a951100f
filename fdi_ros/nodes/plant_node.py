"""Plant simulator node: publishes sensor blocks at the plant's pace and fault ground truth.

The plant (a wing of :mod:`fdi_ros.plants`), its scenario (inputs over time, scheduled faults) and
the block size come from :func:`fdi_ros.plants.make_runner`. A wall-clock timer advances plant time
by ``realtime_factor`` x the elapsed wall time (0 = as fast as the graph takes it; a live change
applies from that moment on, see :class:`fdi_ros.core.pacing.Pacer`); every block is published on
``/fdi/sensor_block`` and plant time on ``/clock`` (the other nodes may run on it with
``use_sim_time``; the plant itself keeps wall time). Every message is stamped in plant time.
Plant time starts at the source gate (:class:`fdi_ros.nodes.startup.SourceGate`: matched
readers, the supervisor's ``/fdi/ready``); at the scenario's end the plant publishes the
end-of-data event on ``/fdi/end_of_data``. A simulated plant waits while its data is
``max_ahead_s`` ahead of the last diagnosis (:class:`fdi_ros.nodes.startup.DiagnosisHold`; 0
for a plant that keeps real time whatever the graph does, as a real engine would).

Faults are injected at run time on ``/fdi/fault_inject`` (reliable, volatile: default and
transient-local publishers both match) and through the service ``/fdi/inject_fault``
(``fdi_msgs/srv/InjectFault``: accepted + reason); ``t_s`` <= 0 means "now". Each request is
checked against the plant's fault list and limits (:class:`fdi_ros.core.faultcheck.
FaultRequests`): a malformed one is refused with the reason (logged once, on ``/diagnostics``,
in the service reply) and the plant runs on. Each fault that takes effect is published on
``/fdi/fault_truth`` (transient-local, so late joiners and the recorder see it).
"""

from __future__ import annotations

import math
import time
from typing import Any

from rclpy.node import Node

from fdi_ros import msgs
from fdi_ros.core.faultcheck import FaultRequests, describe
from fdi_ros.core.pacing import CATCH_UP_S, Pacer
from fdi_ros.nodes.common import (
    DATA_QOS,
    LATCHED_QOS,
    REQUEST_QOS,
    ClockOut,
    Param,
    declare_params,
    follow_rate,
    run_node,
)
from fdi_ros.nodes.startup import SOURCE_PARAMS, DiagnosisHold, SourceGate
from fdi_ros.plants import fault_rules, make_runner


def _rate_check(v: float) -> str | None:
    return None if math.isfinite(v) and v >= 0 else "must be finite and >= 0 (0 = no limit)"


PARAMS = (
    Param("plant", "", "plant id of the plant registry (fdi_ros.plants)", read_only=True),
    Param("scenario", "", "scenario YAML (inputs over time, scheduled faults); '' = the plant's "
          "default", read_only=True),
    Param("seed", 0, "seed of the sensor noise (and plant variation)", read_only=True,
          range=(0, 2**31 - 1)),
    Param("realtime_factor", 1.0, "plant seconds per wall second; 0 = as fast as the graph "
          "takes it; a change applies from that moment on", range=(0.0, 1000.0),
          check=_rate_check),
    Param("publish_clock", True, "publish plant time on /clock", read_only=True),
    Param("max_blocks_per_tick", 50, "blocks published per 10 ms timer tick at most (bounds a "
          "burst when the plant falls behind)", range=(1, 100_000)),
    *SOURCE_PARAMS,
)


class PlantNode(Node):
    def __init__(self) -> None:
        super().__init__("fdi_plant")
        declare_params(self, PARAMS)
        from diagnostic_msgs.msg import DiagnosticArray
        from fdi_msgs.msg import FaultEvent, SensorBlock
        from fdi_msgs.srv import InjectFault

        p = self.get_parameter
        plant = p("plant").value
        self.runner = make_runner(plant, p("scenario").value or None, seed=int(p("seed").value))
        self._requests = FaultRequests(*fault_rules(plant))
        self._fac = msgs.MessageFactory("rclpy")
        self._pub = self.create_publisher(SensorBlock, "/fdi/sensor_block", DATA_QOS)
        self._truth = self.create_publisher(FaultEvent, "/fdi/fault_truth", LATCHED_QOS)
        self._clock_out = ClockOut(self, bool(p("publish_clock").value))
        self._diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_subscription(FaultEvent, "/fdi/fault_inject", self._on_inject, REQUEST_QOS)
        self.create_service(InjectFault, "/fdi/inject_fault", self._on_inject_service)
        self._pacer = Pacer(float(p("realtime_factor").value))
        follow_rate(self, self._pacer, "realtime_factor", lambda: self.runner.t, "t =")
        self._gate, self._hold = SourceGate(self, self._pub), DiagnosisHold(self)
        self._finished, self._sent = False, 0
        self.create_timer(0.01, self._tick)
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(f"plant {self.runner.plant!r} ready, scenario "
                               f"{p('scenario').value or '(default)'}")

    # -- fault injection (checked, counted and reported by core/faultcheck) ---------------------
    def _request(self, m: Any) -> tuple[bool, str]:
        ok, reason = self._requests.handle(m, now=self.runner.t, schedule=self.runner.inject)
        if ok:
            self.get_logger().info(f"fault injection {reason}")
        else:
            self.get_logger().error(self._requests.last)
        self._publish_diagnostics()
        return ok, reason

    def _on_inject(self, m: Any) -> None:
        self._request(m)

    def _on_inject_service(self, request: Any, response: Any) -> Any:
        response.accepted, response.reason = self._request(request.event)
        return response

    def _publish_diagnostics(self) -> None:
        e = self._requests.entry(f"{self.get_name()}: fault injection", self.runner.plant,
                                 t=self.runner.t, rate=self._pacer.rate)
        self._diag.publish(msgs.diagnostic_array([e], self.runner.t))

    # -- plant time -----------------------------------------------------------------------------
    def _tick(self) -> None:
        if self._finished:
            return
        now = time.monotonic()
        if not self._gate.check(now, self._pacer, self.runner.t):
            return  # nothing published into the void (see SourceGate)
        target = self._pacer.target_within(now, self.runner.t, CATCH_UP_S)  # no bursts
        for _ in range(int(self.get_parameter("max_blocks_per_tick").value)):
            if self.runner.done:
                self._finished = True
                self._gate.end(round(self.runner.t * 1e9), self._sent)
                self.get_logger().info(f"scenario finished at t = {self.runner.t:.3f} s")
                return
            if self.runner.t >= target or self._hold.held(self.runner.t, self._pacer,
                                                           self.runner.t, "realtime_factor"):
                break
            block = self.runner.next_block()
            for ev in self.runner.pop_truth():
                self._truth.publish(self._fac.fault_event(ev))
                self.get_logger().info(f"fault active: {describe(ev)}")
            self._pub.publish(self._fac.sensor_block(block))
            self._sent += 1
            self._clock_out.publish(msgs.stamp_fields(float(block.t[-1])))


def main(args: list[str] | None = None) -> int:
    return run_node(PlantNode, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
