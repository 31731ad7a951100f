"""The graph configuration file (``config/<plant>.yaml``): one file, read by everyone.

It is a ROS 2 parameter file (one ``<node>: ros__parameters:`` section per node kind) plus one
``fdi_graph:`` section that ROS parameters cannot express (the bank: a list of models with their
fault sets and model specs). The launcher hands each node only its own section; the supervisor
and offline tools read ``fdi_graph`` through :func:`load_graph_config`.

``fdi_graph`` keys
------------------
plant : plant id ("diesel", "turbofan").
bank : list of ``{id, faults: [fault ids], model: <spec for load_residual_model>}``; the
    model with no faults is the nominal (reference) model.
t0_s : isolation hold time T0 [s].
symptoms : optional ``{model: <bank id whose residuals give symptoms>, config: {...}}``.
stale_s : residuals older than this (plant time) count as missing [s].
node_timeout_s : a lifecycle service that does not answer within this [s] marks the node failed.
hosting : optional ``{mode: process | container, containers: N, executor: single | events}``:
    how the bank's model nodes are hosted. ``process`` (the default): one process per model
    node. ``container``: the model nodes spread over ``containers`` host processes (round
    robin), several lifecycle nodes on one executor per process, each still its own node.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from fdi_ros.core.files import read_document
from fdi_ros.core.supervisor import BankModel

KNOWN_KEYS = {"plant", "bank", "t0_s", "symptoms", "stale_s", "node_timeout_s", "description",
              "hosting"}
HOSTING_MODES = ("process", "container")
HOSTING_EXECUTORS = ("single", "events")


@dataclass(frozen=True)
class Hosting:
    """How bank model nodes are hosted: one process each, or ``containers`` host processes."""

    mode: str = "process"
    containers: int = 1
    executor: str = "single"

    def __post_init__(self) -> None:
        if self.mode not in HOSTING_MODES:
            raise ValueError(f"hosting mode {self.mode!r}; known: {', '.join(HOSTING_MODES)}")
        if self.executor not in HOSTING_EXECUTORS:
            raise ValueError(f"hosting executor {self.executor!r}; known: "
                             f"{', '.join(HOSTING_EXECUTORS)}")
        if isinstance(self.containers, bool) or not isinstance(self.containers, int) \
                or self.containers < 1:
            raise ValueError(f"hosting containers must be an integer >= 1, got "
                             f"{self.containers!r}")

    @classmethod
    def parse(cls, doc: Any) -> Hosting:
        """From the ``hosting`` mapping (or a bare mode string); ValueError when malformed."""
        if doc is None:
            return cls()
        if isinstance(doc, str):
            doc = {"mode": doc}
        if not isinstance(doc, dict):
            raise ValueError("hosting must be a mapping {mode, containers, executor}")
        unknown = set(doc) - {"mode", "containers", "executor"}
        if unknown:
            raise ValueError(f"unknown key(s) in hosting: {sorted(unknown)}")
        return cls(mode=str(doc.get("mode", "process")), containers=doc.get("containers", 1),
                   executor=str(doc.get("executor", "single")))

    def groups(self, names: list[str]) -> list[list[str]]:
        """The node names per host process: one each (process), or round robin over at most
        ``containers`` hosts (container)."""
        if self.mode == "process":
            return [[n] for n in names]
        k = min(self.containers, len(names)) or 1
        return [names[i::k] for i in range(k) if names[i::k]]


@dataclass(frozen=True)
class BankEntry:
    id: str
    faults: frozenset[str]
    model: Any  # spec handed to load_residual_model

    @property
    def node_name(self) -> str:
        return "fdi_model_" + "".join(c if c.isalnum() else "_" for c in self.id)


@dataclass(frozen=True)
class GraphConfig:
    path: Path
    plant: str
    bank: tuple[BankEntry, ...]
    t0_s: float
    symptoms: dict[str, Any] | None = None
    stale_s: float = math.inf
    node_timeout_s: float = 2.0
    node_params: dict[str, dict[str, Any]] = field(default_factory=dict)
    hosting: Hosting = field(default_factory=Hosting)

    @property
    def bank_models(self) -> list[BankModel]:
        return [BankModel(id=e.id, faults=e.faults) for e in self.bank]

    def entry(self, model_id: str) -> BankEntry:
        for e in self.bank:
            if e.id == model_id:
                return e
        raise KeyError(f"no bank model {model_id!r} in {self.path}")

    def resolve_spec(self, spec: Any) -> Any:
        """A model spec with its relative paths (any string value naming a path with '/')
        made absolute against the repository root."""
        if isinstance(spec, dict):
            return {k: (self.resolve(v) if isinstance(v, str) and "/" in v else v)
                    for k, v in spec.items()}
        if isinstance(spec, str) and "/" in spec and not spec.lstrip().startswith("{"):
            return self.resolve(spec)
        return spec

    def resolve(self, value: str) -> str:
        """A path relative to the repository root (the config's parent's parent) or absolute."""
        p = Path(value)
        if p.is_absolute() or p.exists():
            return str(p)
        return str(self.path.resolve().parent.parent / p)


def load_graph_config(path: str | Path) -> GraphConfig:
    """Read and validate a graph configuration file (clear errors for malformed files)."""
    p = Path(path)
    doc = read_document(p, "graph configuration", fmt="yaml")
    if not isinstance(doc, dict) or "fdi_graph" not in doc:
        raise ValueError(f"{p}: no 'fdi_graph' section")
    g = doc["fdi_graph"]
    if not isinstance(g, dict):
        raise ValueError(f"{p}: 'fdi_graph' must be a mapping")
    unknown = set(g) - KNOWN_KEYS
    if unknown:
        raise ValueError(f"{p}: unknown key(s) in fdi_graph: {sorted(unknown)}")
    if not isinstance(g.get("bank") or [], list):
        raise ValueError(f"{p}: 'bank' must be a list of models")
    bank = []
    for i, e in enumerate(g.get("bank") or []):
        if not isinstance(e, dict) or "id" not in e or "model" not in e:
            raise ValueError(f"{p}: bank entry {i} needs 'id' and 'model'")
        bank.append(BankEntry(id=str(e["id"]), faults=frozenset(e.get("faults") or ()),
                              model=e["model"]))
    if not bank:
        raise ValueError(f"{p}: the bank is empty")
    node_params = {k: v.get("ros__parameters", {}) for k, v in doc.items()
                   if k != "fdi_graph" and isinstance(v, dict)}
    cfg = GraphConfig(path=p, plant=str(g.get("plant", "")), bank=tuple(bank),
                      t0_s=float(g.get("t0_s", 1.2)), symptoms=g.get("symptoms"),
                      stale_s=float(g.get("stale_s", math.inf)),
                      node_timeout_s=float(g.get("node_timeout_s", 2.0)),
                      node_params=node_params)
    try:
        cfg = replace(cfg, hosting=Hosting.parse(g.get("hosting")))
    except ValueError as exc:
        raise ValueError(f"{p}: {exc}") from None
    _ = cfg.bank_models  # validates the fault sets (one size per fault type and model)
    return cfg
