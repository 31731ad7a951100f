"""Joint hypotheses: one error of one signal, seen in every residual that reads the signal.

A measured signal can be read by several residuals: as the measurement a residual compares
with its model (the air-mass flow in a speed-density relation and in a throttle relation;
the crank-resolved pulsation of the same sensor), or as an input of a model (the manifold
pressure in both relations). An error of the signal (offset, gain, drift, lag, dead time, a
dependence on a measured column) moves every one of these residuals, each in its own way,
with **one** set of parameters; an effect of one model (a missing harmonic, a local region,
a leak, a missing input dependence) moves that model's residual only.

:func:`hypotheses` groups the per-residual candidates of the catalogue
(:func:`~fdi_ros.core.discrepancy.effects.candidates`) into such hypotheses, one member
effect per residual the hypothesis moves; :func:`fit_hypothesis` fits the signal error where
the signal is measured and puts the same error into every other residual that reads it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from fdi_ros.core.discrepancy.context import ChannelContext
from fdi_ros.core.discrepancy.effects import (
    SENSOR_KINDS,
    DeadTime,
    Drift,
    Effect,
    GainError,
    Offset,
    SensorError,
    SensorLag,
    candidates,
)

_LINEAR = ("offset", "gain_error", "drift", "input_dependence")  # fitted as beta * D
# parameter of each kind (the size of the signal's error: reading - truth, or reading / truth)
_KEY = {k: v[1] for k, v in SENSOR_KINDS.items()}


@dataclass(frozen=True)
class Hypothesis:
    """One candidate explanation and the effect it puts on each residual it moves.

    ``carrier`` is the signal whose error it is (a signal error), or the residual whose model
    lacks something (a model effect); ``members`` pairs a residual with the catalogue effect
    acting on it, the first member being where the shape of the effect is fitted.
    """

    effect: str
    label: str
    carrier: str
    members: tuple[tuple[str, Effect], ...]
    signal: bool  # an error of a measured signal (else an effect of one model)

    @property
    def n_params(self) -> int:
        return self.members[0][1].n_params

    @property
    def views(self) -> tuple[str, ...]:
        return tuple(v for v, _ in self.members)

    @property
    def primary(self) -> str:
        return self.members[0][0]


def _signature(eff: Effect, ctx: ChannelContext) -> tuple[Any, ...] | None:
    """What makes two per-residual effects the same error of one signal (None: a model
    effect of this residual alone)."""
    if isinstance(eff, SensorError):
        return (eff.kind, eff.sensor, eff.onset, False, eff.column)
    if isinstance(eff, (Offset, GainError)):
        return (eff.id, ctx.signal, eff.onset, eff.piecewise, "")
    if isinstance(eff, (Drift, SensorLag, DeadTime)):
        return (eff.id, ctx.signal, False, False, "")
    return None


def _member(sig: tuple[Any, ...], ctx: ChannelContext) -> Effect | None:
    """The effect that the signal error ``sig`` puts on the residual of ``ctx`` (None: the
    residual does not read the signal)."""
    kind, sensor, onset, piecewise, column = sig
    if sensor == ctx.signal:
        if kind == "offset":
            return Offset(onset=onset, piecewise=piecewise)
        if kind == "gain_error":
            return GainError(onset=onset, piecewise=piecewise)
        if kind == "drift":
            return Drift()
        if kind == "sensor_lag":
            return SensorLag()
        if kind == "dead_time":
            return DeadTime()
        return None  # a dependence of the reading itself is a model effect of its residual
    if sensor in ctx.uses and not piecewise and ctx.source is not None:
        return SensorError(sensor=sensor, kind=kind, column=column, onset=onset)
    return None


def hypotheses(contexts: dict[str, ChannelContext], *, effects: tuple[str, ...],
               onset: bool = True, sensor_effects: tuple[str, ...] | None = None,
               secondary: dict[str, ChannelContext] | None = None) -> list[Hypothesis]:
    """Every candidate of every residual in ``contexts``, errors of one signal joined over
    the residuals that read it (also those of ``secondary``, which only check a hypothesis:
    no candidate originates there)."""
    out: list[Hypothesis] = []
    seen: set[tuple[Any, ...]] = set()
    every = dict(contexts)
    every.update(secondary or {})
    for name, ctx in contexts.items():
        for eff in candidates(ctx, effects=effects, onset=onset, sensor_effects=sensor_effects):
            sig = _signature(eff, ctx)
            if sig is None:
                out.append(Hypothesis(effect=eff.id, label=eff.label, carrier=name,
                                      members=((name, eff),), signal=False))
                continue
            if sig in seen:
                continue
            seen.add(sig)
            own = [(v, m) for v, c in every.items() if c.signal == sig[1]
                   if (m := _member(sig, c)) is not None]
            other = [(v, m) for v, c in every.items() if c.signal != sig[1]
                     if (m := _member(sig, c)) is not None]
            # the first member: where the signal is measured, else where it was proposed
            members = own + other
            first = next((i for i, (v, _) in enumerate(members) if v in contexts and (
                own or v == name)), 0)
            members.insert(0, members.pop(first))
            lead = members[0][1]
            out.append(Hypothesis(effect=lead.id, label=lead.label, carrier=str(sig[1]),
                                  members=tuple(members), signal=True))
    return out


def physical(eff: Effect, params: dict[str, Any]) -> dict[str, Any]:
    """The signal error as fitted on one member: its size, onset or change times."""
    kind = eff.id
    key = _KEY.get(kind, "")
    out = {k: params[k] for k in (key, "onset_s", "changes_s", "values", "input")
           if k in params}
    if kind == "input_dependence" and "coef" in params:
        c = params["coef"]
        out["coef"] = float(c[0] if isinstance(c, (list, tuple)) else c)
    return out


def member_params(eff: Effect, ctx: ChannelContext, phys: dict[str, Any]) -> dict[str, Any]:
    """The parameters of member ``eff`` (on the residual of ``ctx``) for the signal error
    ``phys`` (:func:`physical`)."""
    kind = eff.id
    key = _KEY[kind]
    v = phys[key]
    if isinstance(eff, SensorError):
        out: dict[str, Any] = {key: v, "sensor": eff.sensor}
        if kind in _LINEAR:
            value = float(v)
            out["beta"] = (1.0 / value - 1.0 if kind == "gain_error" else -value)
        if eff.onset:
            out["onset_s"] = phys.get("onset_s")
        if kind == "drift":
            out["t_ref_s"] = ctx.t_ref
        if kind == "input_dependence":
            out["input"] = eff.column
        return out
    if "changes_s" in phys:
        return {key: v, "changes_s": list(phys["changes_s"]), "values": list(phys["values"])}
    if kind == "drift":
        return {key: v, "t_ref_s": ctx.t_ref}
    if kind in ("offset", "gain_error"):
        return {key: v, "onset_s": phys.get("onset_s")}
    return {key: v}


def fit_hypothesis(h: Hypothesis, contexts: dict[str, ChannelContext],
                   bases: dict[str, np.ndarray], trains: dict[str, np.ndarray], *,
                   refine: bool = False) -> list[dict[str, Any]]:
    """Parameters of every member of ``h``, fitted on the training samples of its first member.

    The first member (the residual that measures the signal, else the one that proposed the
    hypothesis) fits the error's shape and size with its own
    :meth:`~fdi_ros.core.discrepancy.effects.Effect.fit`; every other member takes the same
    signal error (:func:`physical`, :func:`member_params`). The size is not refitted on the
    other residuals: their models are approximations of their own, and a residual that reads
    the signal only as an input would pull the size towards what its model's errors prefer;
    the other residuals judge the hypothesis' consequences on held-out data instead.
    """
    v0, e0 = h.members[0]
    p0 = e0.fit(contexts[v0], bases[v0], trains[v0], refine=refine)
    if len(h.members) == 1:
        return [p0]
    phys = physical(e0, p0)
    return [p0] + [member_params(e, contexts[v], phys) for v, e in h.members[1:]]
