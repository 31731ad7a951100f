"""The extended model as a bank residual model (registry kind ``discrepancy_extended``).

Spec (``residual_model.yaml`` next to the saved model, written by ``fdi-ros discrepancy
--save-model``)::

    type: discrepancy_extended
    module: fdi_ros.core.discrepancy.residual
    path: extended_model.json
    history_s: 3.0

Per feature vector (one 180 deg CA segment: ``n``, ``p2``, ``T2``, ``maf`` ...) it predicts
every channel of the model with all fitted extensions and returns ``measured - predicted``.
Extensions with memory (sensor lag, dead time, the filling term's derivative, drift) need the
recent past: the model keeps the last ``history_s`` seconds of features of its stream
(``reset()`` clears them). A feature vector that is invalid, lacks an input, or lies outside
the identified region gives ``valid=False`` with the reason in ``status``.
"""

from __future__ import annotations

from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from fdi_ros.core.discrepancy.model import ExtendedModel, signals_read
from fdi_ros.core.measured import Measured
from fdi_ros.core.types import FeatureVector, ResidualVector


class ExtendedResidualModel:
    """Residuals of an :class:`ExtendedModel` on a stream of feature vectors."""

    def __init__(self, model: ExtendedModel, *, model_id: str, history_s: float = 3.0) -> None:
        if not history_s > 0:
            raise ValueError("history_s must be > 0")
        self.model = model
        self.model_id = model_id
        self.history_s = float(history_s)
        self._hist: deque[FeatureVector] = deque()

    def reset(self) -> None:
        self._hist.clear()

    def _invalid(self, fv: FeatureVector, status: str) -> ResidualVector:
        names = tuple(f"r_{c}" for c in self.model.channels)
        return ResidualVector(model_id=self.model_id, index=fv.index, t=fv.t_end, valid=False,
                              status=status, names=names, units=tuple("" for _ in names),
                              values=np.full(len(names), np.nan), norm=float("nan"))

    def residuals(self, fv: FeatureVector) -> ResidualVector:
        if not fv.valid:
            return self._invalid(fv, fv.status or "invalid features")
        missing = [k for k in signals_read(self.model.baseline) if k not in fv.names]
        if missing:
            return self._invalid(fv, f"features lack {missing}")
        t = 0.5 * (fv.t_start + fv.t_end)
        if self._hist and t <= 0.5 * (self._hist[-1].t_start + self._hist[-1].t_end):
            self._hist.clear()  # time went backwards: a new stream
        self._hist.append(fv)
        while t - 0.5 * (self._hist[0].t_start + self._hist[0].t_end) > self.history_s:
            self._hist.popleft()
        if len(self._hist) < 2:
            return self._invalid(fv, "warming up (history)")
        ts = np.array([0.5 * (h.t_start + h.t_end) for h in self._hist])
        sig = {k: np.array([h.get(k) for h in self._hist]) for k in fv.names}
        data = Measured(t=ts, signals=sig, units=dict(zip(fv.names, fv.units)),
                        source="features", mapped=tuple(fv.names))
        pred = self.model.predict(data)
        measures = dict(getattr(self.model.baseline, "measures", None) or {})
        names, vals = [], []
        for ch in self.model.channels:
            names.append(f"r_{ch}")
            vals.append(float(sig[measures.get(ch, ch)][-1] - pred[ch][-1]))
        v = np.array(vals)
        if not np.all(np.isfinite(v)):
            return self._invalid(fv, "outside the identified region")
        units = tuple(fv.units[fv.names.index(measures.get(c, c))] for c in self.model.channels)
        return ResidualVector(model_id=self.model_id, index=fv.index, t=fv.t_end, valid=True,
                              status="", names=tuple(names), units=units, values=v,
                              norm=float(np.linalg.norm(v)))


def make_residual_model(spec: dict[str, Any], *, base_dir: Path,
                        model_id: str) -> ExtendedResidualModel:
    """The bank model of kind ``discrepancy_extended`` (registered by
    :data:`fdi_ros.core.residual_models.KINDS`)."""
    unknown = set(spec) - {"path", "history_s"}
    if unknown:
        raise ValueError(f"discrepancy_extended: unknown keys {sorted(unknown)}")
    if "path" not in spec:
        raise ValueError("discrepancy_extended needs 'path' (the extended model JSON)")
    model = ExtendedModel.load(Path(base_dir) / spec["path"])
    return ExtendedResidualModel(model, model_id=model_id,
                                 history_s=float(spec.get("history_s", 3.0)))


def write_spec(model_path: Path, *, history_s: float = 3.0) -> Path:
    """Write ``residual_model.yaml`` next to a saved extended model; returns its path."""
    import yaml

    spec = {"type": "discrepancy_extended", "module": __name__,
            "path": Path(model_path).name, "history_s": history_s}
    out = Path(model_path).parent / "residual_model.yaml"
    out.write_text(yaml.safe_dump(spec, sort_keys=False))
    return out
