"""A tiny third plant, written as a wing from outside the package: a first-order tank
(level ``h``, inflow command ``u``) whose level sensor can take an offset.

    tau dh/dt = K u - h,    y = h + offset + noise

Channels ``u, y``, one feature vector per sample. Two residual-model kinds: ``tank_level``
(parallel model driven by ``u``: r = y - h_model) and ``tank_offset`` (the same with the
sensor offset estimated over a sliding window and removed). Nothing in fdi_ros knows it: it is
found through ``FDI_ROS_WINGS=tank=tank_wing`` (or :func:`fdi_ros.plants.register_wing`).
"""

from __future__ import annotations

from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from fdi_ros.core.plant_api import FaultQueue, SampledRunner
from fdi_ros.core.residual_models import register_residual_model
from fdi_ros.core.types import FaultEvent, FeatureVector, ResidualVector, SampleBlock
from fdi_ros.plants import Wing

TS = 0.05       # s, sample time
TAU = 2.0       # s
GAIN = 1.0      # m per unit command
NOISE = 0.005   # m, sensor noise
CHANNELS = ("u", "y")
UNITS = ("1", "m")
OFFSET_LIMIT = 1.0  # m


def command(t: float) -> float:
    """The scenario's inflow command: a slow square wave."""
    return 0.5 + 0.2 * np.sign(np.sin(2 * np.pi * t / 8.0))


def validate_fault(ev: FaultEvent) -> None:
    if ev.fault not in ("", "sensor_offset"):
        raise ValueError(f"unknown tank fault {ev.fault!r}; known: ['sensor_offset']")
    if ev.fault and not (np.isfinite(ev.size) and abs(ev.size) <= OFFSET_LIMIT):
        raise ValueError(f"sensor offset {ev.size} outside +-{OFFSET_LIMIT} m")


class TankRunner(SampledRunner):
    plant = "tank"
    channels = CHANNELS
    units = UNITS

    def __init__(self, scenario: Any = None, *, seed: int | None = None,
                 block_samples: int = 10) -> None:
        sc = scenario if isinstance(scenario, dict) else \
            (yaml.safe_load(Path(scenario).read_text()) if scenario else {})
        self.duration_s = float(sc.get("duration_s", 20.0))
        self._rng = np.random.default_rng(int(sc.get("seed", 0) if seed is None else seed))
        self._per_block = int(block_samples)
        super().__init__(ts=TS)
        self._faults = FaultQueue()
        self._offset = 0.0
        self._h = GAIN * command(0.0)
        for f in sc.get("faults", []):
            self.inject(FaultEvent(t=float(f["t"]), fault=f["fault"], size=float(f["size"]),
                                   size_unit="m"))

    @property
    def done(self) -> bool:
        return self._k * TS >= self.duration_s

    def inject(self, event: FaultEvent) -> None:
        validate_fault(event)
        self._faults.add(event)
        self._truth.add(event)

    def next_block(self) -> SampleBlock:
        n = self._per_block
        t = self._times(n)
        vals = np.empty((2, n))
        for j, tj in enumerate(t):
            for ev in self._faults.due(tj):
                self._offset = ev.size if ev.fault and ev.active else 0.0
            u = command(tj)
            vals[0, j] = u
            vals[1, j] = self._h + self._offset + self._rng.normal(0.0, NOISE)
            self._h += TS / TAU * (GAIN * u - self._h)
        return self._emit(t, vals)


class TankPreprocessor:
    def __init__(self, **options: Any) -> None:
        if options:
            raise ValueError(f"the tank preprocessor takes no options, got {sorted(options)}")
        self._index = 0

    def push(self, block: SampleBlock) -> list[FeatureVector]:
        u, y = block.channel("u"), block.channel("y")
        out = []
        for j, t in enumerate(block.t):
            v = np.array([u[j], y[j]])
            ok = bool(np.all(np.isfinite(v)))
            out.append(FeatureVector(plant="tank", index=self._index, t_start=float(t),
                                     t_end=float(t), alpha_start=0.0, valid=ok,
                                     status="ok" if ok else "missing_sample", names=CHANNELS,
                                     units=UNITS, values=v))
            self._index += 1
        return out

    def mark_gap(self) -> None:
        pass


class TankLevelModel:
    """r = y - h_model - offset_estimate; the nominal model does not estimate an offset."""

    def __init__(self, model_id: str, *, threshold: float, window: int = 0) -> None:
        self.model_id, self.threshold, self.window = model_id, threshold, window
        self.reset()

    def reset(self) -> None:
        self._h: float | None = None
        self._err: deque[float] = deque(maxlen=max(self.window, 1))

    def residuals(self, fv: FeatureVector) -> ResidualVector:
        u, y = fv.get("u"), fv.get("y")
        if self._h is None:
            self._h = y  # start the parallel model on the first measurement
        r = y - self._h
        self._h += TS / TAU * (GAIN * u - self._h)
        if self.window:
            self._err.append(r)
            r -= float(np.mean(self._err))
        return ResidualVector(self.model_id, fv.index, fv.t_end, fv.valid, fv.status, ("r_y",),
                              ("m",), np.array([r]), abs(r) / self.threshold)


@register_residual_model("tank_level")
def _level(spec: dict, *, base_dir: Path, model_id: str) -> TankLevelModel:
    return TankLevelModel(model_id, threshold=float(spec.get("threshold", 0.03)))


@register_residual_model("tank_offset")
def _offset(spec: dict, *, base_dir: Path, model_id: str) -> TankLevelModel:
    return TankLevelModel(model_id, threshold=float(spec.get("threshold", 0.03)),
                          window=int(spec.get("window", 20)))


WING = Wing(name="tank", runner=TankRunner, preprocessor=TankPreprocessor,
            kinds={__name__: ("tank_level", "tank_offset")}, faults=("sensor_offset",),
            validate_fault=validate_fault)
