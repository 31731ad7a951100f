"""Expert supervisor node, the ROS edge of :class:`fdi_ros.core.supervision.SupervisorCore`:
parameters, subscriptions (features, residuals, block stamps, each bank node's transitions),
lifecycle clients, fault services, ``/fdi/ready``, the end of the diagnosis, timers. The bank's
vectors: a sensor block per message, or one per message (``batched``, :mod:`.bankio`)."""

from __future__ import annotations

import time
from functools import partial
from typing import Any, cast

from diagnostic_msgs.msg import DiagnosticArray
from fdi_msgs.msg import Diagnosis, SensorBlock, Symptoms
from fdi_msgs.srv import ClearFaults, GetFaults
from lifecycle_msgs.msg import TransitionEvent
from lifecycle_msgs.srv import ChangeState as CS
from lifecycle_msgs.srv import GetState as GS
from rcl_interfaces.msg import SetParametersResult
from rclpy.logging import get_logger
from rclpy.node import Node
from std_msgs.msg import Header

from fdi_ros import bag, msgs
from fdi_ros.core.bankdriver import ChangeState, GetState, Note
from fdi_ros.core.supervision import FEATURE_TOPICS, GATE_TOPICS, PARAMS, Publish, SupervisorCore
from fdi_ros.nodes import bankio
from fdi_ros.nodes import endofdata as eod
from fdi_ros.nodes import startup as su
from fdi_ros.nodes.common import DATA_IN_QOS, DATA_QOS, LATCHED_QOS, run_node, wall_timer


class SupervisorNode(Node):
    def __init__(self) -> None:
        super().__init__("fdi_supervisor")
        p = su.declare_table(self, PARAMS)
        self.core = SupervisorCore.from_params(p)
        self.add_on_set_parameters_callback(self._on_set)
        self._fac = msgs.MessageFactory("rclpy")
        # one logger instance per severity: rclpy refuses two severities from one call site
        self._loggers = {lv: get_logger(self.get_name()) for lv in ("info", "warn", "error")}
        self.clients_ = {}
        for e in self.core.cfg.bank:
            self.clients_[e.id] = (self.create_client(CS, f"/{e.node_name}/change_state"),
                                   self.create_client(GS, f"/{e.node_name}/get_state"))
            self.create_subscription(TransitionEvent, f"/{e.node_name}/transition_event",
                                     partial(self._on_transition, e.id), 10)
        self.pub = {"symptoms": self.create_publisher(Symptoms, "/fdi/symptoms", DATA_QOS),
                    "diagnosis": self.create_publisher(Diagnosis, "/fdi/diagnosis", DATA_QOS),
                    "ros": self.create_publisher(DiagnosticArray, "/diagnostics", 10),
                    "ready": self.create_publisher(Header, su.READY_TOPIC, LATCHED_QOS),
                    "end": self.create_publisher(Header, eod.END_OF_DIAGNOSIS_TOPIC, LATCHED_QOS)}
        self.create_subscription(Header, eod.END_OF_FEATURES_TOPIC, self._on_end, LATCHED_QOS)
        ins = bankio.supervisor_inputs(self.core.batched)  # the bank's vectors (see bankio)
        self._subs = {t: self.create_subscription(c, t, bankio.fed(
            self.get_logger(), f, self.core.residual if r else self.core.features, self._do),
            DATA_IN_QOS) for t, c, f, r in ins}
        self.create_subscription(SensorBlock, "/fdi/sensor_block", lambda raw: self.core.block(
            msgs.raw_header_stamp(cast(bytes, raw)), time.monotonic()), DATA_IN_QOS, raw=True)
        self.create_service(GetFaults, "/fdi/get_faults", lambda q, r: GetFaults.Response(
            faults=msgs.fault_records(self.core.memory.records.values())))
        self.create_service(ClearFaults, "/fdi/clear_faults", self._clear_faults)
        self._gate: tuple[float, list] | None = (
            time.monotonic() + p["ready_timeout_s"], list(p["wait_for_readers"]))
        wall_timer(self, 0.05, self._tick)
        wall_timer(self, p["diagnostics_period_s"], self._publish_diagnostics)
        self.get_logger().info(f"fault memory {self.core.store.path} ({len(self.core.memory.records)} records)")  # noqa: E501

    def _tick(self) -> None:
        now = time.monotonic()
        self._do(self.core.tick(now, {i: c.service_is_ready() and g.service_is_ready() for i, (
            c, g) in self.clients_.items()}, {n for n, _ in self.get_node_names_and_namespaces()}))
        if self._gate is not None:  # the start-up handshake, until the source may start
            mine = {f"/fdi/{k}": self.pub[k].get_subscription_count()
                    for k in ("diagnosis", "symptoms")}
            pubs, subs = ({t: {i.node_name for i in f(t)} for t in {
                *GATE_TOPICS, *self._subs, *FEATURE_TOPICS, *mine}} for f in (
                    self.get_publishers_info_by_topic, self.get_subscriptions_info_by_topic))
            self.core.waiting = self.core.waiting_for(pubs, subs, {
                t: s.get_publisher_count() for t, s in self._subs.items()}, self._gate[1], mine)
            if not self.core.waiting or now > self._gate[0]:
                self.get_logger().info("graph ready" if not self.core.waiting else "ready after "
                                       f"ready_timeout_s without: {'; '.join(self.core.waiting)}")
                for m in su.ready_messages({t: subs[t] for t in FEATURE_TOPICS}, Header):
                    self.pub["ready"].publish(m)
                self._gate = None

    def _on_end(self, m: Any) -> None:
        if (e := eod.read_end(m, "end_of_features")) is not None:
            self._do(self.core.end_of_features(e[0], e[1], time.monotonic()))

    def _on_set(self, params: list) -> SetParametersResult:
        try:
            for q in params:
                self.core.set(q.name, q.value)
        except (ValueError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _on_transition(self, model_id: str, m: Any) -> None:
        self._do(self.core.driver.on_transition_event(model_id, m.start_state.id,
                                                      m.goal_state.id, time.monotonic()))

    def _do(self, actions: list[object]) -> None:
        for a in actions:
            if isinstance(a, (ChangeState, GetState)):
                cli = self.clients_[a.model_id][isinstance(a, GetState)]
                req = (GS if isinstance(a, GetState) else CS).Request()
                if isinstance(a, ChangeState):
                    req.transition.id = a.transition
                cli.call_async(req).add_done_callback(lambda f, a=a: self._done(f, a))
            elif isinstance(a, Note):
                getattr(self._loggers[a.level], a.level)(a.text)
                if a.level != "info" or a.model_id:
                    self._publish_diagnostics()
            elif isinstance(a, Publish) and a.what == "confirmed":
                self.get_logger().info(bag.write_snapshot(self.core.snapshot_path(a.value),
                                                          self.core.ring))
            elif isinstance(a, Publish) and a.what == "end":
                self.pub["end"].publish(eod.end_message("end_of_diagnosis", *a.value[:2]))
            elif isinstance(a, Publish):  # diagnosis, symptoms
                self.pub[a.what].publish(self._fac.diagnosis(a.value) if a.what == "diagnosis"
                                         else self._fac.symptom_state(*a.value))

    def _done(self, fut: Any, a: Any) -> None:
        try:
            r, err = fut.result(), ""
        except Exception as exc:  # a failed call is reported, never fatal
            r, err = None, str(exc)
        self._do(self.core.driver.on_answer(a, r, time.monotonic(), err))

    def _clear_faults(self, req: Any, res: Any) -> Any:
        res.success, res.message, cleared = self.core.clear_request(list(req.faults))
        res.cleared = msgs.fault_records(cleared)
        return res

    def _publish_diagnostics(self) -> None:
        self.core.store.save(self.core.memory.records.values())  # last_t_s, once a second
        t = self.core.last.t if self.core.last is not None else 0.0
        self.pub["ros"].publish(msgs.diagnostic_array(self.core.entries(time.monotonic()), t))


def main(args: list[str] | None = None) -> int:
    return run_node(SupervisorNode, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
