"""Residual models of the bank: one interface, a registry keyed by ``type:``.

A residual-generator node loads ONE bank model with :func:`load_residual_model` and turns
every :class:`~fdi_ros.core.types.FeatureVector` into a
:class:`~fdi_ros.core.types.ResidualVector`; the supervisor compares the models' ``norm``
(minimum-residual index) and turns the nominal model's residuals into symptoms with a
:class:`SymptomGenerator`.

Registering a model kind (e.g. in a plant's own module)::

    @register_residual_model("turbofan_ts")
    def _make(spec: dict, *, base_dir: Path, model_id: str) -> ResidualModel: ...

A spec is a mapping with ``type:`` and kind-specific keys (paths relative to ``base_dir``);
``module:`` names a module to import first so that it can register its kind. Kinds of the
diesel plant (``diesel_reference``, ``diesel_fault_hypothesis``) register on first use.
"""

from __future__ import annotations

import importlib
import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Protocol, runtime_checkable

from fdi_ros.core.types import FeatureVector, ResidualVector

__all__ = ["ResidualModel", "SymptomConfig", "SymptomGenerator", "SymptomState", "isolate",
           "load_residual_model", "register_residual_model", "registered_types"]


@runtime_checkable
class ResidualModel(Protocol):
    """One bank model: features in, residuals out (``valid=False`` + status outside its
    region). Implementations may keep per-stream state; ``reset()`` clears it."""

    model_id: str

    def residuals(self, fv: FeatureVector) -> ResidualVector: ...

    def reset(self) -> None: ...


Factory = Callable[..., ResidualModel]
_REGISTRY: dict[str, Factory] = {}
# Modules that register the built-in kinds, imported on first use of the kind.
_PROVIDERS = {"diesel_reference": "fdi_ros.plants.diesel.symptoms",
              "diesel_fault_hypothesis": "fdi_ros.plants.diesel.symptoms",
              "turbofan_ts": "fdi_ros.plants.turbofan.bank",
              "discrepancy_extended": "fdi_ros.core.discrepancy.residual"}
SPEC_FILES = ("residual_model.yaml", "residual_model.json")


def register_residual_model(type_name: str) -> Callable[[Factory], Factory]:
    """Class/function decorator: make ``type_name`` loadable by :func:`load_residual_model`."""
    if not type_name or not isinstance(type_name, str):
        raise ValueError("a residual model type needs a non-empty name")

    def deco(factory: Factory) -> Factory:
        other = _REGISTRY.get(type_name)
        if other is not None and other is not factory and \
                getattr(other, "__qualname__", None) != getattr(factory, "__qualname__", None):
            raise ValueError(f"residual model type {type_name!r} is already registered")
        _REGISTRY[type_name] = factory
        return factory

    return deco


def registered_types() -> tuple[str, ...]:
    for mod in set(_PROVIDERS.values()):
        importlib.import_module(mod)
    return tuple(sorted(_REGISTRY))


def _read_spec(path: Path) -> dict:
    text = path.read_text()
    if path.suffix == ".json":
        try:
            return json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: not JSON: {exc}") from exc
    import yaml

    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: not YAML: {exc}") from exc
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: a residual model spec must be a mapping")
    return doc


def load_residual_model(path_or_spec, *, model_id: str) -> ResidualModel:
    """Build one bank model from a spec mapping, a spec file, or a model directory.

    A directory is read through its ``residual_model.yaml`` (or ``.json``); a diesel reference
    model directory (with ``reference_models.json``) is a ``diesel_reference`` model.
    """
    base_dir = Path.cwd()
    if isinstance(path_or_spec, Mapping):
        spec = dict(path_or_spec)
    else:
        path = Path(path_or_spec)
        if not path.exists():
            raise FileNotFoundError(f"no residual model at {path}")
        if path.is_dir():
            found = [path / f for f in SPEC_FILES if (path / f).exists()]
            if found:
                spec, base_dir = _read_spec(found[0]), path
            elif (path / "reference_models.json").exists():
                spec, base_dir = {"type": "diesel_reference", "path": "."}, path
            else:
                raise FileNotFoundError(f"{path} holds no {' or '.join(SPEC_FILES)}")
        else:
            spec, base_dir = _read_spec(path), path.parent
    kind = spec.get("type")
    if not kind:
        raise ValueError(f"residual model spec lacks 'type:' (known: {registered_types()})")
    module = spec.get("module") or _PROVIDERS.get(kind)
    if module:
        try:
            importlib.import_module(module)
        except ImportError as exc:
            raise ValueError(f"cannot import module {module!r} for type {kind!r}: {exc}") from exc
    if kind not in _REGISTRY:
        raise ValueError(f"unknown residual model type {kind!r}; known: {registered_types()}")
    if not model_id:
        raise ValueError("model_id must not be empty")
    rest = {k: v for k, v in spec.items() if k not in ("type", "module")}
    return _REGISTRY[kind](rest, base_dir=base_dir, model_id=model_id)


# Generic symptom logic re-exported here (imported last: that module registers its kinds here).
from fdi_ros.plants.diesel.symptoms import SymptomConfig, SymptomGenerator, SymptomState, isolate  # noqa: E402
