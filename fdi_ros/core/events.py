"""A diagnosis stream as a list of events: what ``fdi-ros diagnose --json`` and
``fdi-ros launch --json`` both write, so offline and live runs compare line by line."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from fdi_ros.core.types import Diagnosis


def diagnosis_events(diagnoses: Iterable[Diagnosis]) -> list[dict[str, Any]]:
    """One event per change of state (with the model and candidates at that segment) and one
    per change of the models on line (a bank switch), in stream order."""
    events: list[dict[str, Any]] = []
    last_state, last_online = None, None
    for d in diagnoses:
        if d.state != last_state:
            events.append({"t": round(d.t, 4), "index": d.index, "state": d.state,
                           "min_residual_model": d.min_residual_model,
                           "fault_model": d.fault_model,
                           "candidate_faults": list(d.candidate_faults)})
            last_state = d.state
        online = tuple(d.models_online)
        if online != last_online:
            if last_online is not None:
                events.append({"t": round(d.t, 4), "index": d.index, "bank_switch":
                               {"models_online": list(online)}})
            last_online = online
    return events
