"""The turbofan wing: streaming runner and per-sample preprocessor (:mod:`.live`), the
``turbofan_ts`` residual-model kind (:mod:`.bank`) and the bank builder (training the global
Takagi-Sugeno model), registered as plant ``"turbofan"`` in :mod:`fdi_ros.plants`."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fdi_ros.core.graphconfig import GraphConfig
from fdi_ros.core.plant_api import PlantRunner, Preprocessor
from fdi_ros.core.types import FaultEvent
from fdi_ros.plants import Wing
from fdi_ros.plants.turbofan.plant import FAULT_DIRECTIONS


def _runner(scenario: Any = None, **options: Any) -> PlantRunner:
    from fdi_ros.plants.turbofan.live import TurbofanRunner

    return TurbofanRunner(scenario, **options)


def _preprocessor(**options: Any) -> Preprocessor:
    from fdi_ros.plants.turbofan.live import TurbofanPreprocessor

    return TurbofanPreprocessor(**options)


def validate_fault(event: FaultEvent) -> None:
    """Raise ValueError on a fault type or size word the turbofan does not know."""
    if not event.fault:
        return
    from fdi_ros.plants.turbofan.live import _event_units

    _event_units(event)


def build_bank(cfg: GraphConfig, *, progress: bool = True, seed: int = 0,
               log: Callable[[str], None] = print) -> list[str]:
    """Train the global TS model if a bank model's file is missing (one global model serves
    every bank model: it interpolates over the fault sizes); returns the ids it serves."""
    todo = []
    for e in cfg.bank:
        spec = cfg.resolve_spec(e.model)
        if isinstance(spec, dict) and spec.get("type") == "turbofan_ts" \
                and not Path(spec["path"]).exists():
            todo.append(e.id)
    if not todo:
        return []
    from fdi_ros.plants.turbofan.settings import load_settings
    from fdi_ros.plants.turbofan.train import train

    t0 = time.perf_counter()
    log(f"[bank] training the turbofan's Takagi-Sugeno node models (for {', '.join(todo)})")
    train(load_settings(cfg.path), progress=progress)
    log(f"[bank] turbofan models: {time.perf_counter() - t0:.1f} s")
    return todo


WING = Wing(
    name="turbofan",
    runner=_runner,
    preprocessor=_preprocessor,
    kinds={"fdi_ros.plants.turbofan.bank": ("turbofan_ts",)},
    faults=tuple(FAULT_DIRECTIONS),
    validate_fault=validate_fault,
    build_bank=build_bank,
    reproduce="reproduce turbofan",
    figures="reproduce turbofan --figures DIR",
)
