"""Expert supervisor node: residuals of the bank -> symptoms -> diagnosis -> bank switching.

The decisions are all in :class:`fdi_ros.core.diagnoser.Diagnoser` (pure, shared with offline
``fdi-ros diagnose``). This node only

* collects the residuals of every on-line model for one feature index (a step is processed when
  every live on-line model has answered, or when the features are ``lag_segments`` ahead, so a
  slow or dead model delays a step by at most that much and never stops the supervisor);
* publishes ``/fdi/symptoms``, ``/fdi/diagnosis`` and a ``diagnostic_msgs/DiagnosticArray`` on
  ``/diagnostics`` (every ``diagnostics_period_s`` and at once on a change);
* drives the bank's residual nodes through the standard lifecycle services
  (``/<node>/change_state``, then ``/<node>/get_state`` to confirm), with async calls only:
  the executor never blocks on a service. A node that does not answer within
  ``node_timeout_s``, or whose state is not the one requested, is reported on ``/diagnostics``
  and left out; the rest of the bank goes on.

Parameters: ``graph_config`` (path to config/<plant>.yaml, required), ``silent_s`` (0.5 s of
plant time without residuals from an active model: reported, and not waited for),
``lag_segments`` (40),
``diagnostics_period_s`` (1.0).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node

from fdi_ros import msgs
from fdi_ros.nodes.common import DATA_QOS, run_node

TIMEOUT = "lifecycle service did not answer within"
# The first get_state to a new node is repeated this often [s] until it answers (a request or
# its answer can be lost while DDS matches the service endpoints); only node_timeout_s without
# any answer counts as a failure.
FIRST_CONTACT_RETRY_S = 1.0
# lifecycle_msgs State ids
UNCONFIGURED, INACTIVE, ACTIVE = 1, 2, 3
STATE_LABEL = {0: "unknown", 1: "unconfigured", 2: "inactive", 3: "active", 4: "finalized"}


@dataclass
class ModelNode:
    """What the supervisor knows of one residual-generator node."""

    model_id: str
    node: str
    change: Any
    get: Any
    state: int = 0  # last confirmed lifecycle state id (0 = not known yet)
    want: int = INACTIVE
    busy: bool = False  # a transition is in flight
    busy_since: float = 0.0
    first_asked: float = 0.0  # wall time of the first get_state to this node
    failed: str = ""  # why the node is out of the bank ("" = healthy)
    silent: bool = False  # active, alive, but no residuals for a while (frozen or overloaded)
    last_residual_t: float = -math.inf
    history: list[str] = field(default_factory=list)


class SupervisorNode(Node):
    def __init__(self) -> None:
        super().__init__("fdi_supervisor")
        ro = ParameterDescriptor(read_only=True)
        self.declare_parameter("graph_config", "", ro)
        self.declare_parameter("lag_segments", 40, ro)
        self.declare_parameter("diagnostics_period_s", 1.0, ro)
        from diagnostic_msgs.msg import DiagnosticArray
        from fdi_msgs.msg import Diagnosis, Features, Residuals, Symptoms
        from lifecycle_msgs.srv import ChangeState, GetState

        from fdi_ros.core.diagnoser import Diagnoser
        from fdi_ros.core.graphconfig import load_graph_config

        path = self.get_parameter("graph_config").value
        if not path:
            raise ValueError("parameter 'graph_config' is required")
        self.cfg = load_graph_config(path)
        self.diag = Diagnoser(self.cfg)
        self.lag = int(self.get_parameter("lag_segments").value)
        self.declare_parameter("silent_s", 0.5, ro)
        self.silent_s = float(self.get_parameter("silent_s").value)
        self._last_t = -math.inf  # plant time of the last processed step
        self._online_since = -math.inf  # plant time of the last bank switch
        self._fac = msgs.MessageFactory("rclpy")
        self._ChangeState, self._GetState = ChangeState, GetState
        self.models: dict[str, ModelNode] = {}
        for e in self.cfg.bank:
            self.models[e.id] = ModelNode(
                model_id=e.id, node=e.node_name,
                change=self.create_client(ChangeState, f"/{e.node_name}/change_state"),
                get=self.create_client(GetState, f"/{e.node_name}/get_state"))
        self._apply_wanted()
        self._pending: dict[int, dict[str, Any]] = {}
        self._symptoms: dict[int, Any] = {}
        self._feature_t: dict[int, float] = {}
        self._latest_feature = -1
        self._next_index: int | None = None
        self._last_state = ""
        self.pub_sym = self.create_publisher(Symptoms, "/fdi/symptoms", DATA_QOS)
        self.pub_diag = self.create_publisher(Diagnosis, "/fdi/diagnosis", DATA_QOS)
        self.pub_ros_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._DiagnosticArray = DiagnosticArray
        self.create_subscription(Residuals, "/fdi/residuals", self._on_residuals, DATA_QOS)
        self.create_subscription(Features, "/fdi/features", self._on_features, DATA_QOS)
        # One thread: service answers, data and timers never run concurrently, so the bank
        # state needs no locks; every service call is async, so nothing blocks the executor.
        self.create_timer(0.05, self._drive_bank)
        self.create_timer(float(self.get_parameter("diagnostics_period_s").value),
                          self._publish_diagnostics)
        self.last_diagnosis: Any = None
        self.get_logger().info(f"bank of {len(self.models)} models; on line: "
                               f"{', '.join(self.diag.models_online)}")

    # -- bank management (lifecycle services, async) ----------------------------------------
    def _apply_wanted(self) -> None:
        online = set(self.diag.models_online)
        for m in self.models.values():
            m.want = ACTIVE if m.model_id in online else INACTIVE

    def _drive_bank(self) -> None:
        from lifecycle_msgs.msg import Transition

        now = time.monotonic()
        for m in self.models.values():
            if m.failed and not m.failed.startswith(TIMEOUT):
                continue  # refused or dead: out of the bank
            if m.busy:
                waited = now - m.busy_since
                if m.state == 0 and not m.failed and waited > FIRST_CONTACT_RETRY_S:
                    # The first get_state of a new node: a request or its answer can be lost
                    # while DDS matches the service endpoints, so ask again; only
                    # node_timeout_s without any answer is a failure.
                    if now - m.first_asked > self.cfg.node_timeout_s:
                        self._fail(m, f"{TIMEOUT} {self.cfg.node_timeout_s} s")
                    m.busy = False
                elif waited > self.cfg.node_timeout_s:
                    if not m.failed:
                        self._fail(m, f"{TIMEOUT} {self.cfg.node_timeout_s} s")  # once
                    # Do not wait on a call that may be lost: ask for the state again
                    # (idempotent); an answer brings the node back into the bank.
                    m.busy, m.state = False, 0
                continue
            if m.state == m.want:
                continue
            if not m.change.service_is_ready() or not m.get.service_is_ready():
                continue  # not up yet (or gone: residual staleness reports it)
            if m.state == 0:
                self._call_get(m)
                continue
            if m.state == UNCONFIGURED:
                tid, goal = Transition.TRANSITION_CONFIGURE, INACTIVE
            elif m.state == INACTIVE and m.want == ACTIVE:
                tid, goal = Transition.TRANSITION_ACTIVATE, ACTIVE
            elif m.state == ACTIVE and m.want == INACTIVE:
                tid, goal = Transition.TRANSITION_DEACTIVATE, INACTIVE
            else:
                self._fail(m, f"in state {STATE_LABEL.get(m.state, m.state)}, cannot reach "
                              f"{STATE_LABEL[m.want]}")
                continue
            req = self._ChangeState.Request()
            req.transition.id = tid
            m.busy, m.busy_since = True, now
            fut = m.change.call_async(req)
            fut.add_done_callback(lambda f, m=m, goal=goal: self._changed(m, goal, f))

    def _call_get(self, m: ModelNode, expect: int | None = None) -> None:
        m.busy, m.busy_since = True, time.monotonic()
        if not m.first_asked:
            m.first_asked = m.busy_since
        fut = m.get.call_async(self._GetState.Request())
        fut.add_done_callback(lambda f, m=m, e=expect: self._got_state(m, e, f))

    def _recover(self, m: ModelNode) -> None:
        """A late answer from a node reported as not answering: it is back in the bank."""
        if m.failed.startswith(TIMEOUT):
            m.failed = ""
            self.get_logger().info(f"model {m.model_id!r} ({m.node}) answers again")
            self._publish_diagnostics()

    def _changed(self, m: ModelNode, goal: int, fut: Any) -> None:
        m.busy = False
        self._recover(m)
        try:
            ok = fut.result().success
        except Exception as exc:
            self._fail(m, f"change_state raised {exc}")
            return
        if not ok:
            self._fail(m, f"transition to {STATE_LABEL[goal]} refused")
            return
        self._call_get(m, expect=goal)  # confirm with get_state, as the rules require

    def _got_state(self, m: ModelNode, expect: int | None, fut: Any) -> None:
        m.busy = False
        self._recover(m)
        try:
            sid = fut.result().current_state.id
        except Exception as exc:
            self._fail(m, f"get_state raised {exc}")
            return
        m.state = sid
        if expect is not None:
            if sid != expect:
                self._fail(m, f"get_state says {STATE_LABEL.get(sid, sid)}, expected "
                              f"{STATE_LABEL[expect]}")
                return
            m.history.append(STATE_LABEL[sid])
            self.get_logger().info(f"model {m.model_id!r} ({m.node}) is {STATE_LABEL[sid]}")
            self._publish_diagnostics()

    def _fail(self, m: ModelNode, why: str, *, busy: bool = False) -> None:
        m.busy = busy
        m.failed = why
        self.get_logger().error(f"model {m.model_id!r} ({m.node}): {why}; going on without it")
        self._publish_diagnostics()

    # -- data ---------------------------------------------------------------------------------
    def _on_features(self, m: Any) -> None:
        idx = int(m.index)
        self._feature_t[idx] = float(m.t_end_s)
        self._latest_feature = max(self._latest_feature, idx)
        if self._next_index is None:
            self._next_index = idx
            self._online_since = float(m.t_end_s)
        self._process_ready()

    def _on_residuals(self, m: Any) -> None:
        rv = msgs.to_residuals(m)
        node = self.models.get(rv.model_id)
        if node is None:
            return
        node.last_residual_t = rv.t
        if node.silent:
            node.silent = False
            self.get_logger().info(f"model {node.model_id!r} answers again")
            self._publish_diagnostics()
        if self._next_index is not None and rv.index < self._next_index:
            return  # too late: that step was decided without it
        self._pending.setdefault(rv.index, {})[rv.model_id] = rv
        if rv.model_id == self.diag.reference_id and rv.index not in self._symptoms:
            # Symptoms need only the reference model: publish them at once.
            s = self.diag.symptoms_of(rv)
            self._symptoms[rv.index] = s
            self._publish_symptoms(rv.index, rv.t, s)
        self._process_ready()

    def _expected(self) -> list[str]:
        return [mid for mid in self.diag.models_online
                if not self.models[mid].failed and not self.models[mid].silent
                and self.models[mid].state == ACTIVE]

    def _process_ready(self) -> None:
        while self._next_index is not None and self._next_index in self._feature_t:
            k = self._next_index
            got = self._pending.get(k, {})
            complete = all(mid in got for mid in self._expected())
            if not complete and self._latest_feature < k + self.lag:
                return
            self._step(k, self._feature_t.pop(k), self._pending.pop(k, {}))
            self._next_index = k + 1
            for old in [i for i in self._pending if i < self._next_index]:
                del self._pending[old]
            for old in [i for i in self._symptoms if i < self._next_index]:
                del self._symptoms[old]

    def _publish_symptoms(self, k: int, t: float, s: Any) -> None:
        self.pub_sym.publish(self._fac.symptoms(
            index=k, t=t, valid=s.valid, status=s.status, names=s.names, levels=s.levels,
            residuals=s.residuals, threshold_low=s.threshold_low,
            threshold_high=s.threshold_high, threshold_intense=s.threshold_intense))

    def _step(self, k: int, t: float, residuals: dict[str, Any]) -> None:
        self._last_t = t
        done = self._symptoms.pop(k, None)
        step = self.diag.update(k, t, residuals, symptoms=done)
        d = step.diagnosis
        self.last_diagnosis = d
        if done is None and step.symptoms is not None:
            self._publish_symptoms(k, t, step.symptoms)
        self.pub_diag.publish(self._fac.diagnosis(d))
        if d.state != self._last_state:
            self.get_logger().info(
                f"t = {t:.3f} s segment {k}: {d.state}; I* = {d.min_residual_model or '-'}, "
                f"F* = {d.fault_model}, candidates {list(d.candidate_faults)}, isolated "
                f"{list(d.isolated_faults)}")
            self._last_state = d.state
            self._publish_diagnostics()
        if step.switched:
            self.get_logger().info(f"bank switch at t = {t:.3f} s: off line {list(step.removed)}"
                                   f", on line {list(step.added)}")
            self._online_since = t  # new models get time to come on line
            self._apply_wanted()

    # -- /diagnostics ---------------------------------------------------------------------------
    def _publish_diagnostics(self) -> None:
        from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

        arr = self._DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        d = self.last_diagnosis
        st = DiagnosticStatus(name="fdi_supervisor: diagnosis", hardware_id=self.cfg.plant)
        if d is None:
            st.level, st.message = DiagnosticStatus.OK, "waiting for data"
        else:
            st.level = {"no_fault": DiagnosticStatus.OK, "not_valid": DiagnosticStatus.WARN,
                        "detected": DiagnosticStatus.WARN,
                        "isolated": DiagnosticStatus.ERROR}.get(d.state, DiagnosticStatus.WARN)
            st.message = {"no_fault": "no fault", "not_valid": "not valid here (operating "
                          "point outside the identified region)",
                          "detected": "fault detected, isolating",
                          "isolated": f"fault isolated: {', '.join(d.isolated_faults)}"
                          }.get(d.state, d.state)
            st.values = [KeyValue(key=k, value=str(v)) for k, v in [
                ("t_s", f"{d.t:.3f}"), ("state", d.state),
                ("min_residual_model", d.min_residual_model), ("fault_model", d.fault_model),
                ("candidate_faults", ",".join(d.candidate_faults)),
                ("isolated_faults", ",".join(d.isolated_faults)),
                ("models_online", ",".join(d.models_online)),
                ("detection_time_s", f"{d.detection_time:.3f}"),
                ("isolation_time_s", f"{d.isolation_time:.3f}")]]
        arr.status.append(st)
        for m in self.models.values():
            ms = DiagnosticStatus(name=f"fdi_supervisor: model {m.model_id}",
                                  hardware_id=m.node)
            if m.failed:
                ms.level, ms.message = DiagnosticStatus.ERROR, f"node failed: {m.failed}"
            elif m.silent:
                ms.level = DiagnosticStatus.WARN
                ms.message = (f"silent: no residuals since t = {m.last_residual_t:.3f} s "
                              "(frozen or overloaded); diagnosing without it")
            elif m.state == 0:
                ms.level, ms.message = DiagnosticStatus.WARN, "node not seen yet"
            else:
                ms.level = DiagnosticStatus.OK
                ms.message = f"{STATE_LABEL.get(m.state, m.state)} (wanted {STATE_LABEL[m.want]})"
            ms.values = [KeyValue(key="state", value=STATE_LABEL.get(m.state, str(m.state))),
                         KeyValue(key="wanted", value=STATE_LABEL[m.want]),
                         KeyValue(key="transitions", value=",".join(m.history))]
            arr.status.append(ms)
        self.pub_ros_diag.publish(arr)

    # -- liveness -------------------------------------------------------------------------------
    def check_liveness(self) -> None:
        """Mark active models whose node left the graph (process died) as failed, and those
        that stay in the graph but stopped answering (no residuals for ``silent_s`` of plant
        time while the features go on) as silent, until they answer again."""
        names = {n for n, _ in self.get_node_names_and_namespaces()}
        latest = self._feature_t.get(self._latest_feature, self._last_t)
        changed = False
        for m in self.models.values():
            if m.failed or m.state != ACTIVE or m.model_id not in self.diag.models_online:
                continue
            if m.node not in names:
                self._fail(m, "node vanished from the graph (process died?)")
            elif not m.silent and latest - max(m.last_residual_t, self._online_since) \
                    > self.silent_s:
                m.silent = True
                changed = True
                self.get_logger().warn(f"model {m.model_id!r} ({m.node}) silent: no residuals "
                                       f"since t = {m.last_residual_t:.3f} s")
        if changed:
            self._publish_diagnostics()


def _make() -> SupervisorNode:
    node = SupervisorNode()
    node.create_timer(0.5, node.check_liveness)
    return node


def main(args: list[str] | None = None) -> int:
    return run_node(_make, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
