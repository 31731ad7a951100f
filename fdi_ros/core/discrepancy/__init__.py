"""Discrepancy discovery: what a model gets wrong in measured data, why, and the held-out gain.

Entry point: :func:`discover` (measured record + baseline model -> result + extended model).
The pieces: :mod:`.context` (what an effect sees), :mod:`.effects` (the catalogue),
:mod:`.engine` (held-out blocks, tests, ranking), :mod:`.model` (extended model, save/load),
:mod:`.diagnostics` (error map, order spectrum, correlations) and :mod:`.report` (figures).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from fdi_ros.core.discrepancy.context import ChannelContext, LeakSpec, build_contexts
from fdi_ros.core.discrepancy.effects import CATALOGUE, EFFECT_TYPES, Effect
from fdi_ros.core.discrepancy.engine import (
    DiscrepancyConfig,
    DiscrepancyResult,
    Finding,
    analyse,
    apply_chain,
    merge_results,
)
from fdi_ros.core.discrepancy.model import ExtendedModel, baseline_from_dict
from fdi_ros.core.discrepancy.ties import input_gain_ties
from fdi_ros.core.measured import Measured, segment_means

__all__ = ["CATALOGUE", "EFFECT_TYPES", "ChannelContext", "DiscrepancyConfig",
           "DiscrepancyResult", "Effect", "ExtendedModel", "Finding", "LeakSpec", "analyse",
           "baseline_from_dict", "build_contexts", "discover"]


# effects judged on crank-resolved samples when the data and the model have them
CRANK_VIEW = ("missing_harmonic", "sensor_lag", "dead_time")


def _tag_views(res: DiscrepancyResult) -> DiscrepancyResult:
    """Mark each finding with the view its held-out RMSE refers to."""
    res.findings = [replace(f, view="crank-resolved" if f.effect in CRANK_VIEW
                            else "segment means") for f in res.findings]
    return res


def discover(data: Measured, model: Any, *, config: DiscrepancyConfig | None = None,
             progress: Callable[[str], None] | None = None
             ) -> tuple[DiscrepancyResult, ExtendedModel]:
    """Analyse ``data`` against ``model`` (:func:`_discover`), then name honest ties.

    A gain error found on a channel that no input-sensor candidate was scored against (an
    analysis without sensor candidates) is checked against gains on each of the model's
    input sensors (:func:`.ties.input_gain_ties`); those the data cannot tell apart join the
    finding's alternatives with the measurement that would separate them.
    """
    res, ext = _discover(data, model, config=config, progress=progress)
    cfg = config or DiscrepancyConfig()
    sensor_kinds = cfg.sensor_effects if cfg.sensor_effects is not None else cfg.effects
    if "gain_error" in sensor_kinds:
        return res, ext  # input gains were candidates: ties come from the joint scores
    for i, f in enumerate(res.findings):
        if (f.effect != "gain_error" or "gain" not in f.params or "changes_s" in f.params
                or _is_sensor(f)):
            continue
        try:
            tied = input_gain_ties(data, model, f.channel, float(f.params["gain"]),
                                   f.params.get("onset_s"), alpha=cfg.alpha)
        except (ValueError, KeyError, FloatingPointError, np.linalg.LinAlgError) as exc:
            if progress:
                progress(f"input-gain tie check on {f.channel} skipped: {exc}")
            continue
        have = {a.get("channel") for a in f.alternatives if a.get("effect") == "gain_error"}
        tied = [a for a in tied if a["channel"] not in have]
        if tied:
            res.findings[i] = replace(f, alternatives=list(f.alternatives) + tied)
            if progress:
                progress(f"{f.label} on {f.channel} tied with "
                         + ", ".join(a["label"] for a in tied))
    return res, ext


def _is_sensor(f: Finding) -> bool:
    """A finding that is an error of an input sensor (seen on another channel's residual)."""
    return f.input_sensor or (bool(f.model_channel) and f.channel != f.model_channel
                              and not f.residuals)


def pulsation_views(data: Measured, model: Any) -> dict[str, ChannelContext]:
    """The crank-resolved residuals of a pulsating model with the mean of every 180 deg CA
    segment removed: what an error of the channel's sensor or of an input does to the
    pulsation (a gain of the channel scales it, an input's error moves the predicted
    pulsation), beside the segment means where the mean-value effects are found."""
    assert data.alpha is not None
    seg = np.floor((data.alpha - data.alpha[0]) / 180.0 + 1e-9).astype(np.int64)
    out = {}
    for ch, ctx in build_contexts(data, model).items():
        ctx.pulse = seg
        ctx.measured = ctx.signal
        ctx.quantum = 0.005  # lags and dead times to 0.5 %: a check, not a fit
        out[ch if ch.endswith("pulsation") else f"{ch} (pulsation)"] = ctx
    return out


def _without_checks(ctxs: dict[str, ChannelContext], model: Any) -> dict[str, ChannelContext]:
    """The residuals that propose explanations: those the model marks as checks left out."""
    checks = set(getattr(model, "checks", ()))
    return {k: c for k, c in ctxs.items() if k not in checks}


def _discover(data: Measured, model: Any, *, config: DiscrepancyConfig | None = None,
              progress: Callable[[str], None] | None = None
              ) -> tuple[DiscrepancyResult, ExtendedModel]:
    """Analyse ``data`` against the baseline ``model``; return the result and extended model.

    Crank-angle resolved data and a model that predicts the pulsation (``model.orders``) are
    analysed in two views, in three stages: sensor lag and dead time on the crank-resolved
    samples (they look alike on slowly varying means; on the pulsation they differ: a lag damps
    it, a delay shifts its phase); then the mean-value effects on 180 deg CA segment means
    (the pulsation averages out, the mean-value model's errors remain); then missing
    harmonics on the crank-resolved samples. Each stage starts from the model extended by the
    stages before; the views share the time base, so one chain of extensions results.
    """
    cfg = config or DiscrepancyConfig()
    view = "samples"
    if data.alpha is not None and not getattr(model, "orders", ()):
        # crank-resolved data, mean-value model: compare the means of the 180 deg CA segments
        data, view = segment_means(data), "segment means"
    if data.alpha is None or not getattr(model, "orders", ()):
        # mean-value data (no crank angle) and a pulsating model: the pulsation terms average
        # out, the mean-value relations are compared (the extended model keeps them all, as
        # ExtendedModel.predict drops them on such data)
        view_model = model.without_pulsation() if getattr(model, "orders", ()) else model
        ctxs = build_contexts(data, view_model, sensors=True)
        # residuals the model marks as checks score the leading explanations only
        checks = {k: ctxs.pop(k) for k in getattr(view_model, "checks", ()) if k in ctxs}
        res = analyse(ctxs, config=cfg, progress=progress, secondary=checks)
        res.findings = [replace(f, view=view) for f in res.findings]
        return res, ExtendedModel(baseline=model, chains=res.chains, source=data.source)
    mean_model = model.without_pulsation()
    stage1 = tuple(e for e in cfg.effects if e in ("sensor_lag", "dead_time"))
    stage3 = tuple(e for e in cfg.effects if e == "missing_harmonic")
    cfg_a = replace(cfg, effects=tuple(e for e in cfg.effects if e not in CRANK_VIEW),
                    sensor_effects=cfg.sensor_effects or cfg.effects)
    means = segment_means(data)

    def on_top(ctxs: dict[str, ChannelContext], before: DiscrepancyResult | None
               ) -> dict[str, ChannelContext]:
        for ctx in ctxs.values():
            if before is not None:
                ctx.yhat = apply_chain(ctx, before.chains.get(ctx.channel, []))
        return ctxs

    res_1 = None
    if stage1:
        res_1 = analyse(_without_checks(build_contexts(data, model), model),
                        config=replace(cfg, effects=stage1, max_findings=1),
                        progress=progress)
    res_a = analyse(on_top(build_contexts(means, mean_model, sensors=True), res_1),
                    config=cfg_a, progress=progress,
                    secondary=on_top(pulsation_views(data, model), res_1))
    if res_1 is not None and res_1.findings and res_a.findings:
        # Joint check: a sensor's error moves every part of the prediction made from that
        # sensor, the pulsation included (a speed sensor's gain shifts the pulsation's phase
        # as a dead time would). When the explanation found on the means alone (with the
        # pulsation as its check) also explains the crank-resolved view, the lag or dead time
        # found there first was its echo: the mean-value explanation is kept, the echo dropped.
        alone = analyse(build_contexts(means, mean_model, sensors=True), config=cfg_a,
                        progress=progress, secondary=pulsation_views(data, model))
        if alone.findings:
            again = analyse(on_top(_without_checks(build_contexts(data, model), model), alone),
                            config=replace(cfg, effects=stage1, max_findings=1),
                            progress=progress)
            if not again.findings:
                if progress:
                    progress("crank-view finding explained by "
                             f"{alone.findings[0].label}: dropped")
                res_1, res_a = None, alone
    if res_1 is not None:
        res_a = merge_results(res_1, res_a, b_suffix="", b_channels=False)
    if not stage3:
        return _tag_views(res_a), ExtendedModel(baseline=model, chains=res_a.chains,
                                                source=data.source)
    ctx_b = _without_checks(build_contexts(data, model), model)
    for ch, ctx in ctx_b.items():
        ctx.yhat = apply_chain(ctx, res_a.chains.get(ch, []))
    res_b = analyse(ctx_b, config=replace(cfg, effects=stage3), progress=progress)
    res = _tag_views(merge_results(res_a, res_b, b_suffix=" (crank-resolved)"))
    return res, ExtendedModel(baseline=model, chains=res.chains, source=data.source)
