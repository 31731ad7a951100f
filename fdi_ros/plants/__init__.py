"""Plant wings and their registry: the one place where plant names map to plant code.

A wing is one sub-package per plant (simulator or measured-data source, scenarios,
preprocessor, residual-model kinds, identification, bank builder, fault-symptom table, figures,
reproduction). Each wing module defines ``WING = Wing(...)``; this module finds it by name from
:data:`TABLE` (the wings shipped here), from the ``fdi_ros.plants`` entry-point group (wings of
other packages: ``name = "package.module"``), from the environment variable ``FDI_ROS_WINGS``
(``name=module,...``: every process of a graph sees the same wings without installing a
package) or from :func:`register_wing` (this process only). The core (``fdi_ros.core``), nodes
and launcher ask this registry and name no plant.

Importing this module is cheap: wing modules are imported on first use, and a wing's heavy
parts (simulator, identification) only when the corresponding factory is called.
"""

from __future__ import annotations

import functools
import importlib
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fdi_ros.core import kinds, residual_models
from fdi_ros.core.plant_api import PlantRunner, Preprocessor
from fdi_ros.core.types import FaultEvent

if TYPE_CHECKING:
    from fdi_ros.core.graphconfig import GraphConfig

__all__ = ["ROOT", "TABLE", "Wing", "ensure_bank", "get_wing", "known_plants",
           "load_residual_model", "make_preprocessor", "make_runner", "register_wing",
           "validate_fault"]

ROOT = Path(__file__).resolve().parents[2]  # the repository (config/, bags/, build/)
ENTRY_POINT_GROUP = "fdi_ros.plants"
ENV_VAR = "FDI_ROS_WINGS"

# The wings shipped with fdi_ros: plant name -> module defining ``WING``.
TABLE: dict[str, str] = {
    "diesel": "fdi_ros.plants.diesel.wing",
    "turbofan": "fdi_ros.plants.turbofan.wing",
    "liu_ice": "fdi_ros.plants.liu_ice.wing",
}

Log = Callable[[str], None]


@dataclass(frozen=True)
class Wing:
    """Everything the generic graph and tools need from one plant.

    runner(scenario, seed=...)       streaming simulator (:class:`PlantRunner`)
    preprocessor(**options)          sensor blocks -> feature vectors (:class:`Preprocessor`)
    kinds                            module -> names of the kinds it registers (residual-model
                                     and discrepancy-baseline types; imported on first use)
    faults                           fault ids of the plant (empty: any name)
    validate_fault(event)            raises ValueError on an event the plant cannot apply
    build_bank(cfg, progress, seed, log)  identifies the missing models of a bank; returns
                                     the ids built (``None``: the wing has nothing to build)
    model_dir_spec(path)             spec of a bare model directory of this wing, or ``None``
    fst                              path of the fault-symptom table file (or ``None``)
    reproduce / figures              the plant's ``fdi-ros`` sub-commands, as typed
                                     (``"reproduce diesel"``)
    """

    name: str
    runner: Callable[..., PlantRunner]
    preprocessor: Callable[..., Preprocessor]
    kinds: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    faults: tuple[str, ...] = ()
    validate_fault: Callable[[FaultEvent], None] | None = None
    build_bank: Callable[..., list[str]] | None = None
    model_dir_spec: Callable[[Path], dict | None] | None = None
    fst: Path | None = None
    reproduce: str | None = None
    figures: str | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)


_WINGS: dict[str, Wing] = {}


def register_wing(wing: Wing) -> Wing:
    """Make ``wing`` known by its name (a later registration of the same name replaces it)."""
    if not wing.name or not isinstance(wing.name, str):
        raise ValueError("a wing needs a non-empty name")
    _WINGS[wing.name] = wing
    return wing


def _entry_points() -> dict[str, str]:
    try:
        eps = metadata.entry_points(group=ENTRY_POINT_GROUP)
    except Exception:  # noqa: BLE001 - broken metadata must not break the shipped wings
        return {}
    return {ep.name: ep.value for ep in eps}


def _from_env() -> dict[str, str]:
    out = {}
    for item in os.environ.get(ENV_VAR, "").split(","):
        if item.strip():
            name, sep, module = item.partition("=")
            if not sep or not name.strip() or not module.strip():
                raise ValueError(f"{ENV_VAR}: expected name=module, got {item!r}")
            out[name.strip()] = module.strip()
    return out


def _modules() -> dict[str, str]:
    """Plant name -> wing module; the shipped table wins over the others."""
    return {**_entry_points(), **_from_env(), **TABLE}


def known_plants() -> list[str]:
    return sorted(set(_modules()) | set(_WINGS))


def get_wing(name: str) -> Wing:
    """The wing called ``name`` (imported on first use); ValueError names the known ones."""
    if name in _WINGS:
        return _WINGS[name]
    module = _modules().get(name)
    if module is None:
        raise ValueError(f"unknown plant {name!r}; known: {known_plants()}")
    wing = getattr(importlib.import_module(module), "WING", None)
    if not isinstance(wing, Wing) or wing.name != name:
        raise ValueError(f"{module} does not define WING = Wing(name={name!r}, ...)")
    return register_wing(wing)


def make_runner(plant: str, scenario: str | Path | dict | None = None, *,
                seed: int | None = None, **options: Any) -> PlantRunner:
    """Streaming simulator of ``plant`` running ``scenario`` (YAML path or mapping)."""
    return get_wing(plant).runner(scenario, seed=seed, **options)


def make_preprocessor(plant: str, **options: Any) -> Preprocessor:
    return get_wing(plant).preprocessor(**options)


def validate_fault(plant: str, event: FaultEvent) -> None:
    """Raise ValueError if ``plant`` cannot apply ``event`` (unknown fault, size, unit)."""
    wing = get_wing(plant)
    if wing.validate_fault is not None:
        wing.validate_fault(event)
    elif event.fault and wing.faults and event.fault not in wing.faults:
        raise ValueError(f"unknown {plant} fault {event.fault!r}; known: {list(wing.faults)}")


def _all_wings() -> list[Wing]:
    out = []
    for name in known_plants():
        try:
            out.append(get_wing(name))
        except (ImportError, ValueError):
            continue  # a broken third-party wing must not hide the others
    return out


def _import_kind(name: str) -> bool:
    """Import the wing module that registers kind ``name``."""
    for wing in _all_wings():
        for module, names in wing.kinds.items():
            if name in names:
                importlib.import_module(module)
                return True
    return False


def _dir_spec(path: Path) -> dict | None:
    for wing in _all_wings():
        if wing.model_dir_spec is not None:
            spec = wing.model_dir_spec(path)
            if spec is not None:
                return spec
    return None


def _known_kinds() -> tuple[str, ...]:
    return tuple(sorted({k for w in _all_wings() for names in w.kinds.values() for k in names}))


# The core's kind tables (residual models, baselines) find every wing's kinds here.
kinds.set_lookup(_import_kind, _known_kinds, _dir_spec)


def load_residual_model(path_or_spec: Any, *, model_id: str) -> residual_models.ResidualModel:
    """:func:`fdi_ros.core.residual_models.load_residual_model` with every wing's kinds."""
    return residual_models.load_residual_model(path_or_spec, model_id=model_id)


def ensure_bank(config: str | Path | GraphConfig, *, progress: bool = True, seed: int = 0,
                log: Log = print) -> list[str]:
    """Identify every missing model of the configuration's bank (through its plant's wing);
    returns the ids built. One build per plant at a time: a second caller (another command,
    a test process) waits on a lock in build/ and then finds the bank built."""
    import fcntl

    from fdi_ros.core.graphconfig import GraphConfig, load_graph_config

    cfg = config if isinstance(config, GraphConfig) else load_graph_config(config)
    wing = get_wing(cfg.plant)
    if wing.build_bank is None:
        return []
    lock = ROOT / "build" / f".bank_{cfg.plant}.lock"
    lock.parent.mkdir(parents=True, exist_ok=True)
    with lock.open("w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)  # released when the file closes
        return wing.build_bank(cfg, progress=progress, seed=seed, log=log)


def fault_rules(plant: str) -> tuple[tuple[str, ...], Callable[[FaultEvent], None]]:
    """The fault ids (or types) ``plant`` knows and its check of one event (ValueError with
    the reason), for run-time injection requests (:mod:`fdi_ros.core.faultcheck`)."""
    return tuple(get_wing(plant).faults), functools.partial(validate_fault, plant)
