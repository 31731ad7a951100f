"""Discrepancy discovery: what a model gets wrong in measured data, why, and the held-out gain.

Entry point: :func:`discover` (measured record + baseline model -> result + extended model).
The pieces: :mod:`.context` (what an effect sees), :mod:`.effects` (the catalogue),
:mod:`.engine` (held-out blocks, tests, ranking), :mod:`.model` (extended model, save/load),
:mod:`.diagnostics` (error map, order spectrum, correlations) and :mod:`.report` (figures).
"""

from __future__ import annotations

from fdi_ros.core.discrepancy.context import ChannelContext, LeakSpec, build_contexts
from fdi_ros.core.discrepancy.effects import CATALOGUE, EFFECT_TYPES, Effect
from fdi_ros.core.discrepancy.engine import (DiscrepancyConfig, DiscrepancyResult, Finding,
                                             analyse)
from fdi_ros.core.discrepancy.model import ExtendedModel, baseline_from_dict
from fdi_ros.core.measured import Measured

__all__ = ["CATALOGUE", "EFFECT_TYPES", "ChannelContext", "DiscrepancyConfig",
           "DiscrepancyResult", "Effect", "ExtendedModel", "Finding", "LeakSpec", "analyse",
           "baseline_from_dict", "build_contexts", "discover"]


def discover(data: Measured, model, *, config: DiscrepancyConfig | None = None,
             progress=None) -> tuple[DiscrepancyResult, ExtendedModel]:
    """Analyse ``data`` against the baseline ``model``; return the result and extended model."""
    ctxs = build_contexts(data, model)
    res = analyse(ctxs, config=config, progress=progress)
    return res, ExtendedModel(baseline=model, chains=res.chains, source=data.source)
