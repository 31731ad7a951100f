"""Fault injections that arrive at run time (a topic, a service, a terminal): checked before
they reach a plant, so a malformed request is refused with a reason and never breaks the plant.

:func:`check_fault_request` takes the request's raw fields (as a message carries them), the
plant's fault list and the plant's own check (units, size ranges), and returns the
:class:`~fdi_ros.core.types.FaultEvent` to schedule or raises :class:`FaultRejected` naming
what is wrong. The plant's part comes from its registry entry; nothing here names a plant.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from fdi_ros.core.supervision import OK, WARN, Entry
from fdi_ros.core.supervisor import fault_type
from fdi_ros.core.types import FaultEvent

PROFILES = ("step", "ramp")


class FaultRejected(ValueError):
    """A fault request the plant cannot apply; ``str(exc)`` is the reason for the user."""


def _finite(name: str, value: object) -> float:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise FaultRejected(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise FaultRejected(f"{name} must be finite, got {v}")
    return v


def check_fault_request(t: Any, fault: Any, size: Any = 0.0, size_unit: Any = "",
                        profile: Any = "", ramp_s: Any = 0.0, active: Any = True, *,
                        now: float, faults: Sequence[str] = (),
                        plant_check: Callable[[FaultEvent], None] | None = None
                        ) -> FaultEvent:
    """The event to schedule for a request at plant time ``now``, or :class:`FaultRejected`.

    Parameters
    ----------
    t, fault, size, size_unit, profile, ramp_s, active : the fields of a
        ``fdi_msgs/FaultEvent`` as received, not yet trusted. ``t`` <= 0 means "now" (a time
        before ``now`` but > 0 is refused: the plant cannot act in the past); ``profile`` ""
        means "step"; ``fault`` "" clears every fault.
    now : current plant time [s].
    faults : fault ids (or fault types: ``"hub"`` admits ``"hub_small"``) the plant knows;
        empty admits any name.
    plant_check : the plant's own check of a well-formed event (units, size limits); raises
        ValueError with the reason.
    """
    if not isinstance(fault, str):
        raise FaultRejected(f"fault must be a string, got {fault!r}")
    fault = fault.strip()
    if fault and faults and fault not in faults and fault_type(fault) not in faults:
        raise FaultRejected(f"unknown fault {fault!r}; known: {', '.join(faults)}")
    t = _finite("t_s", t)
    if t <= 0.0:
        t = now
    elif t < now:
        raise FaultRejected(f"t_s = {t:.3f} s lies in the past (plant time is {now:.3f} s); "
                            "t_s <= 0 means now")
    requested = profile
    profile = (str(profile) or "step").strip()
    if profile not in PROFILES:
        raise FaultRejected(f"unknown profile {requested!r}; known: {', '.join(PROFILES)}")
    ramp_s = _finite("ramp_s", ramp_s)
    if ramp_s < 0.0:
        raise FaultRejected(f"ramp_s must be >= 0, got {ramp_s}")
    if profile == "ramp" and ramp_s <= 0.0:
        raise FaultRejected("profile 'ramp' needs ramp_s > 0")
    size = _finite("size", size)
    if size < 0.0:
        raise FaultRejected(f"size must be >= 0, got {size}")
    event = FaultEvent(t=t, fault=fault, size=size, size_unit=str(size_unit).strip(),
                       profile=profile, ramp_s=ramp_s, active=bool(active))
    if plant_check is not None and fault:
        try:
            plant_check(event)
        except ValueError as exc:
            raise FaultRejected(str(exc)) from None
    return event


def describe(event: FaultEvent) -> str:
    """One line for logs and service replies: what an accepted event does."""
    if not event.fault:
        return f"all faults cleared at t = {event.t:.3f} s"
    if not event.active:
        return f"{event.fault} removed at t = {event.t:.3f} s"
    ramp = f", ramp over {event.ramp_s:g} s" if event.profile == "ramp" else ""
    size = f" {event.size:g} {event.size_unit}".rstrip() if event.size or event.size_unit else ""
    return f"{event.fault}{size} at t = {event.t:.3f} s{ramp}"


@dataclass
class FaultRequests:
    """The run-time fault requests of one plant: each checked, scheduled or refused, counted,
    and reported as one /diagnostics entry (the plant node only moves the messages).

    ``faults`` and ``plant_check`` as for :func:`check_fault_request`.
    """

    faults: Sequence[str] = ()
    plant_check: Callable[[FaultEvent], None] | None = None
    accepted: int = 0
    rejected: int = 0
    last: str = "none"  # the outcome of the last request, as logged
    ok: bool = True  # the last request was accepted (or there was none)

    def handle(self, m: Any, *, now: float, schedule: Callable[[FaultEvent], None]
               ) -> tuple[bool, str]:
        """Check request ``m`` (the fields of a ``fdi_msgs/FaultEvent``) at plant time ``now``
        and hand it to ``schedule``: (accepted, reason for the requester). :attr:`last` holds
        the line to log."""
        try:
            ev = check_fault_request(m.t_s, m.fault, m.size, m.size_unit, m.profile, m.ramp_s,
                                     m.active, now=now, faults=self.faults,
                                     plant_check=self.plant_check)
            schedule(ev)
        except ValueError as exc:  # FaultRejected, or the plant refusing to schedule
            self.rejected += 1
            self.last, self.ok = f"fault request {m.fault!r} refused: {exc}", False
            return False, str(exc)
        self.accepted += 1
        self.last, self.ok = f"scheduled: {describe(ev)}", True
        return True, self.last

    def entry(self, name: str, plant: str, *, t: float, rate: float) -> Entry:
        """The /diagnostics entry: WARN after a refused request, with the counts."""
        return Entry(OK if self.ok else WARN, name, self.last, plant,
                     (("plant_time_s", f"{t:.3f}"), ("realtime_factor", f"{rate:g}"),
                      ("accepted", str(self.accepted)), ("rejected", str(self.rejected))))
