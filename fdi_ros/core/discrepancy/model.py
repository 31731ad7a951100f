"""Baseline models for the analysis and the extended model it produces (save, load, predict).

A baseline model is any object with

* ``inputs``: measured signals it uses (the others are candidate explanations),
* ``channels``: the signals it predicts,
* ``predict(data: Measured) -> {channel: (N,) array}`` (NaN = no valid prediction),
* ``region(data) -> {axis: (N,) array}``: operating-region coordinates for the error map,
* optionally ``leaks``: :class:`~fdi_ros.core.discrepancy.context.LeakSpec` per flow channel,
* ``to_dict()`` with a ``type`` key registered in :data:`BASELINE_TYPES` (for saving).

:class:`ExtendedModel` is a baseline plus, per channel, the chain of catalogue effects found
by the analysis with their fitted parameters. It predicts like the baseline, is saved as JSON
and loaded back with :meth:`ExtendedModel.load`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fdi_ros.core.discrepancy.context import build_contexts
from fdi_ros.core.discrepancy.effects import Effect, effect_from_dict
from fdi_ros.core.kinds import Kinds
from fdi_ros.core.measured import Measured

FORMAT = "fdi_ros.discrepancy.extended_model/1"


# Baseline model types by name: the core's own, and those of the wings (found on first use).
BASELINES: Kinds[Any] = Kinds("baseline model",
                              {"speed_density": "fdi_ros.core.meanvalue:SpeedDensityModel",
                               "throttle_flow": "fdi_ros.core.residualset:ThrottleFlowModel",
                               "pressure_map": "fdi_ros.core.residualset:PressureMapModel",
                               "pulsation_map": "fdi_ros.core.residualset:PulsationMapModel",
                               "residual_set": "fdi_ros.core.residualset:ResidualSet"})


def signals_read(model: Any) -> tuple[str, ...]:
    """Every measured signal a baseline model reads: its inputs and the signals its residuals
    measure (``model.measures``, default: the channel of that name)."""
    measures = dict(getattr(model, "measures", None) or {})
    return tuple(dict.fromkeys(tuple(model.inputs)
                               + tuple(measures.get(c, c) for c in model.channels)))


def baseline_from_dict(d: dict[str, Any]) -> Any:
    """Rebuild a baseline model saved with its ``to_dict()``."""
    return BASELINES.get(str(d.get("type"))).from_dict(d)


@dataclass(frozen=True)
class ExtendedModel:
    """Baseline model + the effect chains of the findings (fitted parameters included)."""

    baseline: Any
    chains: dict[str, list[tuple[Effect, dict[str, Any]]]]
    source: str = ""

    @property
    def inputs(self) -> tuple[str, ...]:
        return tuple(self.baseline.inputs)

    @property
    def channels(self) -> tuple[str, ...]:
        return tuple(self.baseline.channels)

    @property
    def leaks(self) -> tuple[Any, ...]:
        return getattr(self.baseline, "leaks", ())

    @property
    def measures(self) -> dict[str, str]:
        return dict(getattr(self.baseline, "measures", None) or {})

    @property
    def uses(self) -> dict[str, tuple[str, ...]]:
        return dict(getattr(self.baseline, "uses", None) or {})

    def region(self, data: Measured) -> dict[str, np.ndarray]:
        return dict(self.baseline.region(data))

    def predict(self, data: Measured) -> dict[str, np.ndarray]:
        """Baseline prediction with every fitted extension applied, per channel."""
        base = self.baseline
        if data.alpha is None and bool(getattr(base, "orders", None)):
            # mean-value data (segment means): the pulsation terms average out
            base = base.without_pulsation()
        ctxs = build_contexts(data, base)
        out = {}
        for ch, ctx in ctxs.items():
            pred = ctx.yhat
            for eff, params in self.chains.get(ch, []):
                if eff.id == "missing_harmonic" and ctx.alpha is None:
                    continue
                pred = eff.apply(ctx, pred, params)
            out[ch] = pred
        return out

    def to_dict(self) -> dict[str, Any]:
        from fdi_ros.core.discrepancy.engine import _jsonable

        out: dict[str, Any] = _jsonable({
            "format": FORMAT,
            "type": "discrepancy_extended",
            "source": self.source,
            "baseline": self.baseline.to_dict(),
            "extensions": {ch: [{"spec": e.to_dict(), "params": p} for e, p in chain]
                           for ch, chain in self.chains.items()},
        })
        return out

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_dict(), indent=1))
        return path

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ExtendedModel:
        if d.get("format") != FORMAT:
            raise ValueError(f"not an extended model file (format {d.get('format')!r}, "
                             f"expected {FORMAT!r})")

        def params(p: dict[str, Any]) -> dict[str, Any]:
            out = dict(p)
            if "region" in out:  # JSON has no infinity: restore open box edges
                out["region"] = {k: [float(v) for v in lohi] for k, lohi in
                                 out["region"].items()}
            return out

        chains = {ch: [(effect_from_dict(x["spec"]), params(x["params"])) for x in lst]
                  for ch, lst in d["extensions"].items()}
        return cls(baseline=baseline_from_dict(d["baseline"]), chains=chains,
                   source=d.get("source", ""))

    @classmethod
    def load(cls, path: str | Path) -> ExtendedModel:
        from fdi_ros.core.files import read_document

        return cls.from_dict(read_document(path, "extended model", fmt="json"))
