"""A toy plant for the core's unit tests: one feature ``y`` and a bank of ``toy_offset``
residual models (residual ``y - offset``, norm ``|residual|``), one per fault hypothesis."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from fdi_ros.core.residual_models import register_residual_model
from fdi_ros.core.types import FeatureVector, ResidualVector

# (model id, faults, offset): the nominal model and one model per single fault
BANK = (("nominal", (), 0.0), ("a", ("a",), 1.0), ("b", ("b",), -1.0))


def toy_config(t0_s: float, bank: Sequence[tuple[str, Sequence[str], float]] = BANK,
               tail: str = "") -> str:
    """A graph configuration (YAML) of the toy bank with hold time ``t0_s``; ``tail``: more
    top-level YAML."""
    rows = "".join(f"    - {{id: {mid}, faults: [{', '.join(faults)}], "
                   f"model: {{type: toy_offset, offset: {off}}}}}\n"
                   for mid, faults, off in bank)
    return f"fdi_graph:\n  plant: toy\n  t0_s: {t0_s}\n  bank:\n{rows}{tail}"


class ToyOffset:
    """Residual y - offset of one feature 'y'; norm = |residual|."""

    def __init__(self, offset: float, model_id: str) -> None:
        self.offset, self.model_id, self.resets = offset, model_id, 0

    def residuals(self, fv: FeatureVector) -> ResidualVector:
        r = fv.get("y") - self.offset
        return ResidualVector(self.model_id, fv.index, fv.t_end, fv.valid, fv.status, ("r",),
                              ("1",), np.array([r]), abs(r))

    def reset(self) -> None:
        self.resets += 1


@register_residual_model("toy_offset")
def _toy(spec: dict, *, base_dir: Path, model_id: str) -> ToyOffset:
    return ToyOffset(float(spec["offset"]), model_id)
