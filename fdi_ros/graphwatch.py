"""A watcher in the caller's own process: subscribes to the graph's outputs and waits on them.

Used by ``fdi-ros demo``, ``fdi-ros bench graph`` and the graph tests: every wait spins on
messages and lifecycle states with a deadline, never a fixed sleep.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from fdi_ros import msgs
from fdi_ros.nodes.common import DATA_IN_QOS, LATCHED_QOS, ensure_loopback_env


@dataclass
class Seen:
    """Everything the watcher received, with the wall time of arrival."""

    diagnoses: list[tuple[float, Any]] = field(default_factory=list)
    symptoms: list[tuple[float, Any]] = field(default_factory=list)
    truth: list[tuple[float, Any]] = field(default_factory=list)
    diagnostics: list[tuple[float, Any]] = field(default_factory=list)
    features: list[tuple[float, Any]] = field(default_factory=list)
    blocks: list[tuple[float, Any]] = field(default_factory=list)
    end_of_data: list[tuple[float, Any]] = field(default_factory=list)
    end_of_diagnosis: list[tuple[float, tuple[float, int]]] = field(default_factory=list)


def run_ended(seen: Seen) -> bool:
    """The one rule for "this run's data is fully diagnosed": the supervisor has said the end
    of the diagnosis (it says so only once the source's data ended and every segment that
    reached it is diagnosed, see :mod:`fdi_ros.nodes.endofdata`) and the last diagnosis it
    names has reached this watcher too (-1: none). Plant-time facts only: no wall-clock lull
    decides it."""
    if not seen.end_of_diagnosis:
        return False
    last = seen.end_of_diagnosis[-1][1][1]
    return last < 0 or any(d.index >= last for _, d in reversed(seen.diagnoses))


class GraphWatcher:
    """An rclpy context + node of its own that records the graph's topics.

    ``watch_blocks`` / ``watch_features`` also record the high-rate streams (only the header
    times are kept, for latency measurements); ``watch_end`` the source's end-of-data event
    and the supervisor's end of the diagnosis.
    """

    def __init__(self, name: str = "fdi_watcher", *, watch_features: bool = False,
                 watch_blocks: bool = False, watch_end: bool = True) -> None:
        ensure_loopback_env()
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from fdi_msgs.msg import Diagnosis, FaultEvent, Features, SensorBlock, Symptoms
        from rclpy.experimental import EventsExecutor

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = EventsExecutor(context=self.context)  # as the node processes
        self.executor.add_node(self.node)
        self.seen = Seen()
        now = time.monotonic
        sub = self.node.create_subscription
        sub(Diagnosis, "/fdi/diagnosis",
            lambda m: self.seen.diagnoses.append((now(), msgs.to_diagnosis(m))), DATA_IN_QOS)
        sub(Symptoms, "/fdi/symptoms", lambda m: self.seen.symptoms.append((now(), m)),
            DATA_IN_QOS)
        sub(FaultEvent, "/fdi/fault_truth",
            lambda m: self.seen.truth.append((now(), msgs.to_fault_event(m))), LATCHED_QOS)
        sub(DiagnosticArray, "/diagnostics",
            lambda m: self.seen.diagnostics.append((now(), m)), 50)

        def on_features(m: Any) -> None:
            self.seen.features.append((now(), (int(m.index), float(m.t_end_s))))

        def on_block(m: Any) -> None:
            self.seen.blocks.append((now(), float(m.stamp_s[-1])))

        if watch_features:
            sub(Features, "/fdi/features", on_features, DATA_IN_QOS)
        if watch_blocks:
            sub(SensorBlock, "/fdi/sensor_block", on_block, DATA_IN_QOS)
        if watch_end:
            from std_msgs.msg import Header

            from fdi_ros.nodes.endofdata import END_OF_DATA_TOPIC, END_OF_DIAGNOSIS_TOPIC, read_end

            def on_end(m: Any) -> None:
                if (e := read_end(m, "end_of_diagnosis")) is not None:
                    self.seen.end_of_diagnosis.append((now(), e))

            sub(Header, END_OF_DATA_TOPIC,
                lambda m: self.seen.end_of_data.append((now(), m)), LATCHED_QOS)
            sub(Header, END_OF_DIAGNOSIS_TOPIC, on_end, LATCHED_QOS)
        self._diag_pub = self.node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._inject_cli: Any = None
        self._fac = msgs.MessageFactory("rclpy")

    def spin_until(self, cond: Callable[[], Any], timeout: float, what: str,
                   alive: Callable[[], bool] | None = None) -> Any:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            v = cond()
            if v:
                return v
            if alive is not None and not alive():
                raise RuntimeError(f"the graph stopped while waiting for {what}")
            self.executor.spin_once(timeout_sec=0.05)
        raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what}")

    def inject(self, event: Any, timeout: float = 10.0) -> tuple[bool, str]:
        """Inject a fault through the plant's /fdi/inject_fault service: (accepted, reason).

        A service call is answered: a topic message sent before the plant's (volatile) reader
        has matched this publisher would be lost."""
        from fdi_msgs.srv import InjectFault

        if self._inject_cli is None:
            self._inject_cli = self.node.create_client(InjectFault, "/fdi/inject_fault")
        if not self._inject_cli.wait_for_service(timeout_sec=timeout):
            raise TimeoutError(f"/fdi/inject_fault not available after {timeout:.0f} s")
        fut = self._inject_cli.call_async(InjectFault.Request(
            event=self._fac.fault_event(event)))
        self.spin_until(fut.done, timeout, "the answer of /fdi/inject_fault")
        res = fut.result()
        return bool(res.accepted), str(res.reason)

    def lifecycle_state(self, node_name: str, timeout: float = 10.0) -> str:
        """Label of a lifecycle node's current state, via its get_state service.

        The request is re-sent (it changes nothing) while no answer came: a server whose
        response writer has not yet matched this client's reader drops its reply, and
        ``wait_for_service`` sees only the request side of the match."""
        from lifecycle_msgs.srv import GetState

        cli = self.node.create_client(GetState, f"/{node_name}/get_state")
        try:
            deadline = time.monotonic() + timeout
            if not cli.wait_for_service(timeout_sec=timeout):
                return "unreachable"
            wait = 1.0
            while True:
                fut = cli.call_async(GetState.Request())
                left = deadline - time.monotonic()
                try:
                    self.spin_until(fut.done, max(min(wait, left), 0.05),
                                    f"get_state of {node_name}")
                    return str(fut.result().current_state.label)
                except TimeoutError:
                    cli.remove_pending_request(fut)
                    if time.monotonic() >= deadline:
                        raise TimeoutError(f"no answer from /{node_name}/get_state in "
                                           f"{timeout:.0f} s") from None
                    wait = min(2 * wait, 4.0)
        finally:
            self.node.destroy_client(cli)

    def report(self, name: str, level: int, message: str, hardware_id: str = "",
               timeout: float = 2.0) -> None:
        """Publish one /diagnostics status (``level``: 0 OK, 1 WARN, 2 ERROR) and wait until
        the readers acknowledged it (at most ``timeout`` s), e.g. a dead node seen by the
        launcher before it stops the graph. Stamped with the last diagnosed plant time."""
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
        from rclpy.duration import Duration

        d = self.last_diagnosis()
        arr = DiagnosticArray(status=[DiagnosticStatus(
            level=bytes([level]), name=name, message=message, hardware_id=hardware_id)])
        arr.header.stamp.sec, arr.header.stamp.nanosec = msgs.stamp_fields(
            d.t if d is not None else 0.0)
        self._diag_pub.publish(arr)
        self._diag_pub.wait_for_all_acked(Duration(seconds=timeout))

    def last_diagnosis(self) -> Any:
        return self.seen.diagnoses[-1][1] if self.seen.diagnoses else None

    def diagnostic_status(self, name: str) -> Any:
        """The newest /diagnostics status with this name, or None."""
        for _, arr in reversed(self.seen.diagnostics):
            for st in arr.status:
                if st.name == name:
                    return st
        return None

    def close(self) -> None:
        import rclpy

        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)
