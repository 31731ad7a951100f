"""Turbofan settings (``turbofan:`` section of ``config/turbofan.yaml``) and scenario files.

The graph configuration keeps the bank under ``fdi_graph:``; the plant, grid, training and
study settings of the turbofan live in a ``turbofan:`` section of the same file (a section
without ``ros__parameters``, which the launcher ignores).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from fdi_ros.plants.turbofan import plant as tfp
from fdi_ros.plants.turbofan.bank import Scenario
from fdi_ros.plants.turbofan.models import GridSpec

DEFAULT_CONFIG = Path("config/turbofan.yaml")


@dataclass(frozen=True)
class TurbofanSettings:
    """Validated ``turbofan:`` section (unknown keys rejected)."""

    model_path: str = "build/turbofan/global_model.npz"
    grid: GridSpec = field(default_factory=GridSpec)
    n_rules: int = 3
    training_seed: int = 0
    training_duration_s: float = 20.0
    max_nfev: int = 40
    condition: tuple = tfp.PAPER_CONDITION
    deterioration: float = 0.1
    manufacturing: tuple = tuple(tfp.PAPER_MANUFACTURING)
    xnh_weight: float = 0.25
    t0_s: float = 1.2
    fault_free_runs: int = 50
    fault_free_seed: int = 7
    fault_free_deterioration: tuple = (0.0, 0.3)
    fault_free_manufacturing_sigma: float = 0.05e-2
    t0_sweep: tuple = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0, 1.2, 1.5)
    scenarios: tuple = ()

    def __post_init__(self) -> None:
        tfp.check_condition(np.asarray(self.condition, dtype=float))
        if not 0 <= self.deterioration <= 1:
            raise ValueError("deterioration must be in [0, 1]")
        if len(self.manufacturing) != 10:
            raise ValueError("manufacturing variation needs 10 values")
        if self.xnh_weight < 0 or self.t0_s < 0 or self.fault_free_runs < 1:
            raise ValueError("xnh_weight and t0_s must be >= 0 and fault_free_runs >= 1")
        if self.n_rules < 1 or self.max_nfev < 1:
            raise ValueError("n_rules and max_nfev must be >= 1")


def _read_yaml(p: Path, what: str):
    if not p.is_file():
        raise FileNotFoundError(f"{what} {p} not found")
    try:
        return yaml.safe_load(p.read_text())
    except yaml.YAMLError as exc:
        raise ValueError(f"{p}: not valid YAML: {exc}") from exc


def load_settings(path: str | Path = DEFAULT_CONFIG) -> TurbofanSettings:
    """Read the ``turbofan:`` section of a graph configuration file."""
    p = Path(path)
    doc = _read_yaml(p, "turbofan configuration")
    if not isinstance(doc, dict) or not isinstance(doc.get("turbofan"), dict):
        raise ValueError(f"{p}: no 'turbofan:' section")
    sec = dict(doc["turbofan"])
    known = set(TurbofanSettings.__dataclass_fields__)
    unknown = set(sec) - known
    if unknown:
        raise ValueError(f"{p}: unknown key(s) in turbofan: {sorted(unknown)}")
    if "grid" in sec:
        sec["grid"] = GridSpec.from_dict(sec["grid"])
    for key in ("condition", "manufacturing", "fault_free_deterioration", "t0_sweep",
                "scenarios"):
        if key in sec:
            sec[key] = tuple(sec[key])
    return TurbofanSettings(**sec)


def load_scenario(path: str | Path, settings: TurbofanSettings) -> Scenario:
    """A scenario file: ``name, duration_s, events: [{t, faults: {fan: small}}], paper: {...}``;
    optional ``condition``, ``deterioration``, ``manufacturing``, ``seed`` override the
    settings."""
    p = Path(path)
    doc = _read_yaml(p, "scenario")
    known = {"name", "description", "duration_s", "events", "paper", "condition",
             "deterioration", "manufacturing", "seed"}
    if not isinstance(doc, dict) or set(doc) - known:
        raise ValueError(f"{p}: a scenario is a mapping with keys from {sorted(known)}")
    events = []
    for e in doc.get("events") or []:
        if not isinstance(e, dict) or "t" not in e or not isinstance(e.get("faults"), dict):
            raise ValueError(f"{p}: each event needs 't' and 'faults: {{type: size}}'")
        events.append((float(e["t"]), dict(e["faults"])))
    return Scenario(
        name=str(doc.get("name", p.stem)), events=tuple(events),
        duration_s=float(doc.get("duration_s", 20.0)),
        condition=tuple(doc.get("condition", settings.condition)),
        deterioration=float(doc.get("deterioration", settings.deterioration)),
        manufacturing=np.asarray(doc.get("manufacturing", settings.manufacturing), dtype=float),
        seed=int(doc.get("seed", 0)), paper=dict(doc.get("paper") or {}))
