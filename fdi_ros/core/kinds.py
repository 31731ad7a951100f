"""Named kinds (residual-model types, discrepancy baseline types, ...): a table of factories per
family, filled by the modules that define them.

A kind not registered yet is looked for through the lookup that the plant registry
(:mod:`fdi_ros.plants`) installs with :func:`set_lookup`: it imports the wing module that
provides the name. The core itself names no plant kind.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, Generic, TypeVar

__all__ = ["Kinds", "bare_model_dir_spec", "set_lookup"]

F = TypeVar("F", bound=Callable[..., object])


def _find_nothing(name: str) -> bool:
    return False


def _know_nothing() -> tuple[str, ...]:
    return ()


def _no_dir(path: Path) -> dict[str, Any] | None:
    return None


class _Lookup:
    find: Callable[[str], bool] = staticmethod(_find_nothing)
    known: Callable[[], tuple[str, ...]] = staticmethod(_know_nothing)
    model_dir: Callable[[Path], dict[str, Any] | None] = staticmethod(_no_dir)


def set_lookup(find: Callable[[str], bool], known: Callable[[], tuple[str, ...]],
               model_dir: Callable[[Path], dict[str, Any] | None] = _no_dir) -> None:
    """``find(name)`` imports the module that registers kind ``name`` (True if it knew one);
    ``known()`` names every kind it could provide; ``model_dir(path)`` is the spec of a bare
    model directory that a wing recognises as its own (or None)."""
    _Lookup.find = staticmethod(find)
    _Lookup.known = staticmethod(known)
    _Lookup.model_dir = staticmethod(model_dir)


def bare_model_dir_spec(path: Path) -> dict[str, Any] | None:
    """Spec of a model directory without a spec file, if a wing recognises it."""
    return _Lookup.model_dir(path)


class Kinds(Generic[F]):
    """Factories of one family of kinds, by name."""

    def __init__(self, family: str, builtin: dict[str, str] | None = None) -> None:
        self.family = family
        self._factories: dict[str, F] = {}
        self._builtin = dict(builtin or {})  # kind -> "module" registering it or "module:attr"

    def register(self, name: str) -> Callable[[F], F]:
        """Decorator: make ``name`` a kind of this family (same factory again: no-op)."""
        if not name or not isinstance(name, str):
            raise ValueError(f"a {self.family} type needs a non-empty name")

        def deco(factory: F) -> F:
            other = self._factories.get(name)
            if other is not None and other is not factory and \
                    getattr(other, "__qualname__", None) != getattr(factory, "__qualname__",
                                                                    None):
                raise ValueError(f"{self.family} type {name!r} is already registered")
            self._factories[name] = factory
            return factory

        return deco

    def _load(self, name: str) -> None:
        if name in self._factories:
            return
        if name in self._builtin:
            import importlib

            module, _, attr = self._builtin[name].partition(":")
            found = importlib.import_module(module)
            if attr and name not in self._factories:
                self._factories[name] = getattr(found, attr)
        else:
            _Lookup.find(name)

    def get(self, name: str) -> F:
        self._load(name)
        if name not in self._factories:
            raise ValueError(f"unknown {self.family} type {name!r}; known: {self.known()}")
        return self._factories[name]

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and name in self._factories

    def known(self) -> tuple[str, ...]:
        """Every kind of this family that can be loaded (imports their modules)."""
        for name in (*self._builtin, *_Lookup.known()):
            try:
                self._load(name)
            except ImportError:
                continue
        return tuple(sorted(self._factories))
