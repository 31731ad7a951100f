"""Plants as configurations: one registry that the nodes and offline tools ask for a plant's
streaming simulator ("runner") and its preprocessor, by plant id.

A runner yields sensor blocks of a scenario one at a time (so the plant node can publish them
at the plant's pace) and accepts fault injections at run time; a preprocessor turns blocks into
feature vectors. Adding a plant means registering these two factories; no node changes.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from fdi_ros.core.types import FaultEvent, FeatureVector, SampleBlock

ROOT = Path(__file__).resolve().parents[2]


class PlantRunner(Protocol):
    plant: str

    @property
    def t(self) -> float: ...  # plant time of the last sample [s]

    @property
    def done(self) -> bool: ...  # the scenario is over

    def next_block(self) -> SampleBlock: ...

    def inject(self, event: FaultEvent) -> None: ...

    def pop_truth(self) -> list[FaultEvent]: ...  # faults that took effect since last call


class Preprocessor(Protocol):
    def push(self, block: SampleBlock) -> list[FeatureVector]: ...

    def mark_gap(self) -> None: ...  # blocks were lost before the next push


_RUNNERS: dict[str, Callable[..., PlantRunner]] = {}
_PREPROCESSORS: dict[str, Callable[..., Preprocessor]] = {}


def register_plant(name: str, *, runner: Callable[..., PlantRunner],
                   preprocessor: Callable[..., Preprocessor]) -> None:
    _RUNNERS[name] = runner
    _PREPROCESSORS[name] = preprocessor


def _known() -> list[str]:
    return sorted(set(_RUNNERS) | {"diesel", "turbofan"})


def make_runner(plant: str, scenario: str | Path | dict | None = None, *,
                seed: int | None = None) -> PlantRunner:
    """Streaming simulator of ``plant`` running ``scenario`` (YAML path or mapping)."""
    _ensure(plant)
    return _RUNNERS[plant](scenario, seed=seed)


def make_preprocessor(plant: str, **kwargs: Any) -> Preprocessor:
    _ensure(plant)
    return _PREPROCESSORS[plant](**kwargs)


def _ensure(plant: str) -> None:
    if plant in _RUNNERS:
        return
    if plant == "diesel":
        _register_diesel()
    elif plant == "turbofan":
        from fdi_ros.plants.turbofan import live  # registers itself

        del live
    elif plant.isidentifier():
        import importlib

        try:  # a plant wing registers itself in its ``live`` module
            importlib.import_module(f"fdi_ros.plants.{plant}.live")
        except ModuleNotFoundError:
            pass
    if plant not in _RUNNERS:
        raise ValueError(f"unknown plant {plant!r}; known: {_known()}")


class _PendingTruth:
    """Fault events, reported once when plant time reaches them."""

    def __init__(self) -> None:
        self._pending: list[FaultEvent] = []

    def add(self, ev: FaultEvent) -> None:
        self._pending.append(ev)
        self._pending.sort(key=lambda e: e.t)

    def due(self, t: float) -> list[FaultEvent]:
        out = [e for e in self._pending if e.t <= t]
        self._pending = [e for e in self._pending if e.t > t]
        return out


# -- diesel -------------------------------------------------------------------------------------
class DieselRunner:
    """The diesel intake plant running a scenario, one block of ``block_deg`` at a time."""

    plant = "diesel"

    def __init__(self, scenario: str | Path | dict | None = None, *,
                 seed: int | None = None) -> None:
        from fdi_ros.plants.diesel.plant import DieselIntakePlant
        from fdi_ros.plants.diesel.scenario import load_scenario

        sc = load_scenario(scenario if scenario is not None
                           else ROOT / "config" / "scenarios" / "diesel_paper_op.yaml")
        self.scenario = sc
        self.sim = DieselIntakePlant(params=sc.params, seed=sc.seed if seed is None else seed,
                                     dalpha_deg=sc.dalpha_deg)
        self.sim.set_input_profile(sc.inputs_at)
        self._truth = _PendingTruth()
        for ev in sc.faults:
            self.inject(ev)
        self._per_block = max(int(round(sc.block_deg / sc.dalpha_deg)), 1)
        self._t = 0.0

    @property
    def t(self) -> float:
        return self._t

    @property
    def done(self) -> bool:
        return self._t >= self.scenario.duration_s

    def next_block(self) -> SampleBlock:
        block = self.sim.advance(self._per_block)
        self._t = float(block.t[-1])
        return block

    def inject(self, event: FaultEvent) -> None:
        self.sim.inject(event)
        self._truth.add(event)

    def pop_truth(self) -> list[FaultEvent]:
        return self._truth.due(self._t)


class DieselPreprocessor:
    """Crank-synchronous segments (180 deg CA) of the diesel's sensor blocks.

    A lost block leaves a crank-angle gap that the segmenter itself detects: the segment across
    it is flagged invalid, so ``mark_gap`` has nothing to add.
    """

    def __init__(self, **kwargs: Any) -> None:
        from fdi_ros.core.crank import CrankSegmenter
        from fdi_ros.plants.diesel.plant import DieselParams

        p = DieselParams()
        kwargs.setdefault("V_D", p.V_D)
        kwargs.setdefault("R", p.R)
        self.seg = CrankSegmenter(**kwargs)

    def push(self, block: SampleBlock) -> list[FeatureVector]:
        return self.seg.push(block)

    def mark_gap(self) -> None:
        pass

    def reset(self) -> None:
        self.seg.reset()


def _register_diesel() -> None:
    register_plant("diesel", runner=DieselRunner, preprocessor=DieselPreprocessor)
