"""Residual models of the bank: one interface, a registry keyed by ``type:``.

A residual-generator node loads ONE bank model with :func:`load_residual_model` and turns
every :class:`~fdi_ros.core.types.FeatureVector` into a
:class:`~fdi_ros.core.types.ResidualVector`; the supervisor compares the models' ``norm``
(minimum-residual index) and turns the nominal model's residuals into symptoms with a
:class:`SymptomGenerator`.

Registering a model kind (e.g. in a plant wing's own module)::

    @register_residual_model("tank_level")
    def _make(spec: dict, *, base_dir: Path, model_id: str) -> ResidualModel: ...

A spec is a mapping with ``type:`` and kind-specific keys (paths relative to ``base_dir``);
``module:`` names a module to import first so that it can register its kind. The plant
registry (:mod:`fdi_ros.plants`) installs, through :mod:`fdi_ros.core.kinds`, how an unknown
kind finds the wing module that registers it; this module names no plant.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from fdi_ros.core.files import read_document
from fdi_ros.core.kinds import Kinds, bare_model_dir_spec
from fdi_ros.core.types import FeatureVector, ResidualVector

__all__ = ["KINDS", "ResidualModel", "load_residual_model", "register_residual_model",
           "registered_types"]


@runtime_checkable
class ResidualModel(Protocol):
    """One bank model: features in, residuals out (``valid=False`` + status outside its
    region). Implementations may keep per-stream state; ``reset()`` clears it."""

    model_id: str

    def residuals(self, fv: FeatureVector) -> ResidualVector: ...

    def reset(self) -> None: ...


Factory = Callable[..., ResidualModel]
# Generic kinds of the core are imported on first use; wings' kinds through the registry.
# (registered here, by name: the discrepancy module does not import this one, no cycle)
KINDS: Kinds[Factory] = Kinds("residual model", {
    "discrepancy_extended": "fdi_ros.core.discrepancy.residual:make_residual_model"})
SPEC_FILES = ("residual_model.yaml", "residual_model.json")


def register_residual_model(type_name: str) -> Callable[[Factory], Factory]:
    """Class/function decorator: make ``type_name`` loadable by :func:`load_residual_model`."""
    return KINDS.register(type_name)


def registered_types() -> tuple[str, ...]:
    return KINDS.known()


def _read_spec(path: Path) -> dict[str, Any]:
    doc = read_document(path, "residual model spec")
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: a residual model spec must be a mapping")
    return doc


def load_residual_model(path_or_spec: str | Path | Mapping[str, Any], *,
                        model_id: str) -> ResidualModel:
    """Build one bank model from a spec mapping, a spec file, or a model directory.

    A directory is read through its ``residual_model.yaml`` (or ``.json``), else through the
    installed directory lookup (a wing recognising its own model directory).
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
            elif (bare := bare_model_dir_spec(path)) is not None:
                spec, base_dir = bare, path
            else:
                raise FileNotFoundError(f"{path} holds no {' or '.join(SPEC_FILES)}")
        else:
            spec, base_dir = _read_spec(path), path.parent
    kind = spec.get("type")
    if not kind:
        raise ValueError(f"residual model spec lacks 'type:' (known: {registered_types()})")
    module = spec.get("module")
    if module:
        try:
            importlib.import_module(module)
        except ImportError as exc:
            raise ValueError(f"cannot import module {module!r} for type {kind!r}: {exc}") from exc
    factory = KINDS.get(kind)
    if not model_id:
        raise ValueError("model_id must not be empty")
    rest = {k: v for k, v in spec.items() if k not in ("type", "module")}
    return factory(rest, base_dir=base_dir, model_id=model_id)

