"""Discrepancy discovery: what a model gets wrong in measured data, why, and the held-out gain.

Entry point: :func:`discover` (measured record + baseline model -> result + extended model).
The pieces: :mod:`.context` (what an effect sees), :mod:`.effects` (the catalogue),
:mod:`.engine` (held-out blocks, tests, ranking), :mod:`.model` (extended model, save/load),
:mod:`.diagnostics` (error map, order spectrum, correlations) and :mod:`.report` (figures).
"""

from __future__ import annotations

from dataclasses import replace

from fdi_ros.core.discrepancy.context import ChannelContext, LeakSpec, build_contexts
from fdi_ros.core.discrepancy.effects import CATALOGUE, EFFECT_TYPES, Effect
from fdi_ros.core.discrepancy.engine import (DiscrepancyConfig, DiscrepancyResult, Finding,
                                             analyse, apply_chain, merge_results)
from fdi_ros.core.discrepancy.model import ExtendedModel, baseline_from_dict
from fdi_ros.core.measured import Measured, segment_means

__all__ = ["CATALOGUE", "EFFECT_TYPES", "ChannelContext", "DiscrepancyConfig",
           "DiscrepancyResult", "Effect", "ExtendedModel", "Finding", "LeakSpec", "analyse",
           "baseline_from_dict", "build_contexts", "discover"]


def discover(data: Measured, model, *, config: DiscrepancyConfig | None = None,
             progress=None) -> tuple[DiscrepancyResult, ExtendedModel]:
    """Analyse ``data`` against the baseline ``model``; return the result and extended model.

    Crank-angle resolved data and a model that predicts the pulsation (``model.orders``) are
    analysed in two views: every effect but ``missing_harmonic`` on 180 deg CA segment means
    (the pulsation averages out, the mean-value model's errors remain), then
    ``missing_harmonic`` on the crank-resolved samples with the first view's extensions
    already applied. Both views share the time base, so one chain of extensions results.
    """
    cfg = config or DiscrepancyConfig()
    if data.alpha is None or not getattr(model, "orders", ()):
        res = analyse(build_contexts(data, model), config=cfg, progress=progress)
        return res, ExtendedModel(baseline=model, chains=res.chains, source=data.source)
    mean_model = model.without_pulsation()
    cfg_a = replace(cfg, effects=tuple(e for e in cfg.effects if e != "missing_harmonic"))
    res_a = analyse(build_contexts(segment_means(data), mean_model), config=cfg_a,
                    progress=progress)
    if "missing_harmonic" not in cfg.effects:
        return res_a, ExtendedModel(baseline=model, chains=res_a.chains, source=data.source)
    ctx_b = build_contexts(data, model)
    for ch, ctx in ctx_b.items():
        ctx.yhat = apply_chain(ctx, res_a.chains.get(ch, []))
    res_b = analyse(ctx_b, config=replace(cfg, effects=("missing_harmonic",)),
                    progress=progress)
    res = merge_results(res_a, res_b, b_suffix=" (crank-resolved)")
    return res, ExtendedModel(baseline=model, chains=res.chains, source=data.source)
