"""The bank driver: which lifecycle transitions the supervisor requests of its model nodes.

A pure state machine (no rclpy, no clock of its own): the ROS node feeds it events (service
answers, ``transition_event`` messages, service readiness, node presence, wall time) and
executes the actions it returns (``change_state`` / ``get_state`` calls). It keeps, per model
node, the *desired* lifecycle state (from the bank rules) and the *observed* one (from
``get_state`` answers and transition events), as nav2's lifecycle manager does, and in addition

* confirms every transition it requested with ``get_state``;
* times out a request after ``node_timeout_s`` (wall time: health, never diagnosis) and asks
  again; a first ``get_state`` is repeated every ``first_contact_retry_s`` (DDS may lose a
  request while it matches the service endpoints);
* tells its own transitions from *external* ones (a terminal, another manager, a node restart):
  an external change is reported, and with ``policy="reconcile"`` undone after
  ``reconcile_after_s``; with ``"respect"`` it is accepted. While a node is away from its
  desired state its residuals take no part in the diagnosis (:meth:`BankDriver.live`).

Times are wall seconds (monotonic), used only to report and drive health.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

# lifecycle_msgs/State primary state ids and lifecycle_msgs/Transition ids
UNKNOWN, UNCONFIGURED, INACTIVE, ACTIVE, FINALIZED = 0, 1, 2, 3, 4
CONFIGURE, ACTIVATE, DEACTIVATE = 1, 3, 4
LABEL = {UNKNOWN: "unknown", UNCONFIGURED: "unconfigured", INACTIVE: "inactive",
         ACTIVE: "active", FINALIZED: "finalized"}
TIMEOUT = "lifecycle service did not answer within"
POLICIES = ("reconcile", "respect")


def label(state: int) -> str:
    return LABEL.get(state, str(state))


@dataclass(frozen=True)
class DriverPolicy:
    """How the driver treats slow, silent and externally changed nodes (validated)."""

    node_timeout_s: float = 2.0
    first_contact_retry_s: float = 1.0
    policy: str = "reconcile"
    reconcile_after_s: float = 2.0
    # a node missing from the ROS graph listing this long is gone (a busy machine's discovery
    # can drop a live node from one listing)
    absent_s: float = 1.0

    def __post_init__(self) -> None:
        if self.policy not in POLICIES:
            raise ValueError(f"policy must be one of {POLICIES}, not {self.policy!r}")
        for name in ("node_timeout_s", "first_contact_retry_s", "reconcile_after_s",
                     "absent_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a finite time >= 0 s, not {v}")


@dataclass(frozen=True)
class ChangeState:
    """Action: call ``/<node>/change_state`` with ``transition``, expecting ``goal``."""

    model_id: str
    node: str
    transition: int
    goal: int


@dataclass(frozen=True)
class GetState:
    """Action: call ``/<node>/get_state``."""

    model_id: str
    node: str


@dataclass(frozen=True)
class Note:
    """Action: something to log and to show on /diagnostics (level: info, warn, error)."""

    level: str
    model_id: str
    text: str


@dataclass
class NodeView:
    """What the driver knows of one model node."""

    model_id: str
    node: str
    observed: int = UNKNOWN
    desired: int = INACTIVE
    absent_since: float = math.nan  # wall time it was first missing from the graph listing
    listed: bool = False  # seen in the graph listing at least once
    pending: str = ""  # "" | "change" | "get": a request in flight
    sent_at: float = 0.0
    first_asked: float = math.nan
    failed: str = ""  # why the node is out of the bank ("" = healthy)
    external_since: float = math.nan  # wall time of an unrequested change not yet undone
    external_count: int = 0
    external_text: str = ""
    expected_goals: list[tuple[int, float]] = field(default_factory=list)
    history: list[str] = field(default_factory=list)

    @property
    def external(self) -> bool:
        return not math.isnan(self.external_since)


class BankDriver:
    """Desired vs observed lifecycle state of every model node; actions to converge."""

    def __init__(self, nodes: Iterable[tuple[str, str]], policy: DriverPolicy | None = None):
        self.policy = policy or DriverPolicy()
        self.nodes: dict[str, NodeView] = {}
        for mid, node in nodes:
            if mid in self.nodes:
                raise ValueError(f"duplicate model id {mid!r}")
            self.nodes[mid] = NodeView(mid, node)
        self.by_node = {v.node: v for v in self.nodes.values()}

    # -- queries ----------------------------------------------------------------------------
    def live(self, model_id: str) -> bool:
        """The model's residuals count in the diagnosis: wanted and confirmed active, healthy,
        not moved by someone else."""
        v = self.nodes[model_id]
        return (v.desired == ACTIVE and v.observed == ACTIVE and not v.failed
                and not v.external)

    def converged(self) -> bool:
        return all(v.observed == v.desired or v.failed for v in self.nodes.values())

    # -- inputs -----------------------------------------------------------------------------
    def set_desired(self, online: Iterable[str]) -> None:
        on = set(online)
        for v in self.nodes.values():
            v.desired = ACTIVE if v.model_id in on else INACTIVE

    def tick(self, now: float, ready: Mapping[str, bool]) -> list[object]:
        """Time-outs, retries and the next transition of every node (``ready``: the node's
        lifecycle services are available)."""
        out: list[object] = []
        p = self.policy
        for v in self.nodes.values():
            if v.failed and not v.failed.startswith(TIMEOUT):
                continue  # refused, dead or in a state we cannot leave: out of the bank
            v.expected_goals = [(g, t) for g, t in v.expected_goals
                                if now - t <= 2 * p.node_timeout_s]
            if v.pending:
                waited = now - v.sent_at
                if v.observed == UNKNOWN and not v.failed and waited > p.first_contact_retry_s:
                    if now - v.first_asked > p.node_timeout_s:
                        out += self._fail(v, f"{TIMEOUT} {p.node_timeout_s:g} s")
                    v.pending = ""  # ask again below
                elif waited > p.node_timeout_s:
                    if not v.failed:
                        out += self._fail(v, f"{TIMEOUT} {p.node_timeout_s:g} s")
                    v.pending, v.observed = "", UNKNOWN  # a late answer brings it back
                else:
                    continue
            if v.observed == v.desired and v.observed != UNKNOWN:
                out += self._settle(v)  # the bank may have switched to where it was moved
                continue
            if v.external and v.observed != UNKNOWN and (
                    p.policy == "respect" or now - v.external_since < p.reconcile_after_s):
                continue
            if not ready.get(v.model_id, False):
                continue
            if v.observed == UNKNOWN:
                out.append(self._send(v, now, "get", GetState(v.model_id, v.node)))
                if math.isnan(v.first_asked):
                    v.first_asked = now
                continue
            if v.observed == UNCONFIGURED:
                tid, goal = CONFIGURE, INACTIVE
            elif v.observed == INACTIVE and v.desired == ACTIVE:
                tid, goal = ACTIVATE, ACTIVE
            elif v.observed == ACTIVE and v.desired == INACTIVE:
                tid, goal = DEACTIVATE, INACTIVE
            else:
                out += self._fail(v, f"in state {label(v.observed)}, cannot reach "
                                     f"{label(v.desired)}")
                continue
            v.expected_goals.append((goal, now))
            out.append(self._send(v, now, "change", ChangeState(v.model_id, v.node, tid, goal)))
        return out

    def on_change_result(self, model_id: str, success: bool | None, now: float,
                         goal: int, error: str = "") -> list[object]:
        """A change_state answer (``success`` None: the call raised ``error``)."""
        v = self.nodes[model_id]
        v.pending = ""
        out = self._recover(v)
        if success is None:
            return out + self._fail(v, f"change_state raised {error}")
        if not success:
            return out + self._fail(v, f"transition to {label(goal)} refused")
        out.append(self._send(v, now, "get", GetState(v.model_id, v.node)))
        return out

    def on_answer(self, action: ChangeState | GetState, answer: Any, now: float,
                  error: str = "") -> list[object]:
        """The answer to ``action`` (a ChangeState or GetState response; None: the call raised
        ``error``)."""
        if isinstance(action, ChangeState):
            return self.on_change_result(action.model_id, None if answer is None else
                                         bool(answer.success), now, action.goal, error)
        return self.on_get_result(action.model_id, None if answer is None else
                                  int(answer.current_state.id), now, error)

    def on_get_result(self, model_id: str, state: int | None, now: float,
                      error: str = "") -> list[object]:
        """A get_state answer: the observed state (``state`` None: the call raised)."""
        v = self.nodes[model_id]
        v.pending = ""
        out = self._recover(v)
        if state is None:
            return out + self._fail(v, f"get_state raised {error}")
        changed = state != v.observed
        v.observed = int(state)
        if changed and v.observed in LABEL and v.observed != UNKNOWN:
            v.history.append(label(v.observed))
            out.append(Note("info", model_id, f"{v.node} is {label(v.observed)}"))
        out += self._settle(v)
        return out

    def on_transition_event(self, model_id: str, start: int, goal: int,
                            now: float) -> list[object]:
        """A ``transition_event`` of the node. Events into transition states (configuring,
        activating, ...) only announce the primary state that follows, and are ignored."""
        v = self.nodes[model_id]
        if goal not in LABEL or goal == UNKNOWN:
            return []
        ours = v.pending == "change" or any(g == goal for g, _ in v.expected_goals)
        for i, (g, _) in enumerate(v.expected_goals):
            if g == goal:
                del v.expected_goals[i]
                break
        if v.observed != goal:
            v.history.append(label(goal))
        v.observed = goal
        out: list[object] = []
        if not ours and goal != v.desired:
            v.external_since = now
            v.external_count += 1
            v.external_text = (f"external transition of {v.node}: {label(start)} -> "
                               f"{label(goal)} (not requested; wanted {label(v.desired)}, "
                               f"policy {self.policy.policy})")
            out.append(Note("warn", model_id, v.external_text))
        out += self._settle(v)
        return out

    def on_presence(self, model_id: str, present: bool, now: float) -> list[object]:
        """The node left the ROS graph (process died) or came (back)."""
        v = self.nodes[model_id]
        if present:
            v.absent_since, v.listed = math.nan, True
        elif math.isnan(v.absent_since):
            v.absent_since = now
        # before its first listing a node answering its services is not "gone": the listing
        # (discovery info) can come seconds after the services on a busy machine
        if not present and v.listed and not v.failed and v.observed != UNKNOWN \
                and now - v.absent_since >= self.policy.absent_s:
            return self._fail(v, "node vanished from the graph (process died?)")
        if present and v.failed.startswith("node vanished"):
            v.failed, v.observed, v.pending = "", UNKNOWN, ""
            v.first_asked = math.nan
            v.external_since, v.external_count = now, v.external_count + 1
            v.external_text = f"external: {v.node} restarted; bringing it back"
            return [Note("warn", model_id, v.external_text)]
        return []

    # -- internals --------------------------------------------------------------------------
    def _settle(self, v: NodeView) -> list[object]:
        if v.external and v.observed == v.desired:
            v.external_since = math.nan
            return [Note("info", v.model_id, f"{v.node} back in {label(v.observed)} after an "
                                             "external transition")]
        return []

    def _send(self, v: NodeView, now: float, kind: str, action: object) -> object:
        v.pending, v.sent_at = kind, now
        return action

    def _recover(self, v: NodeView) -> list[object]:
        if v.failed.startswith(TIMEOUT):
            v.failed = ""
            return [Note("info", v.model_id, f"{v.node} answers again")]
        return []

    def _fail(self, v: NodeView, why: str) -> list[object]:
        v.pending = ""
        v.failed = why
        return [Note("error", v.model_id, f"{v.node}: {why}; going on without it")]
