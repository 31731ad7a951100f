"""Start a graph configuration as separate processes, one per node (as ``ros2 launch`` would).

The graph configuration (``config/<plant>.yaml``, see :mod:`fdi_ros.core.graphconfig`) names
the node sections; the bank adds one residual-generator process per model. Each process gets
a parameter file with only its own section (``--ros-args --params-file``) and its node name
(``-r __node:=``). Output lines are prefixed with the node name. ``stop()`` sends SIGINT to
all, waits, and kills what is left: Ctrl-C on ``fdi-ros launch`` shuts everything down cleanly.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import yaml

from fdi_ros.core.graphconfig import GraphConfig, load_graph_config

# node section name -> node module (fdi_ros.nodes.<module>)
NODE_KINDS = {
    "fdi_plant": "plant_node",
    "fdi_preprocessor": "preprocessor_node",
    "fdi_supervisor": "supervisor_node",
    "fdi_recorder": "recorder_node",
    "fdi_replayer": "replayer_node",
}
# section of the graph configuration with the parameters common to every bank model node
MODELS_SECTION = "fdi_models"


@dataclass
class NodeProcess:
    name: str
    module: str
    argv: list[str]
    proc: subprocess.Popen | None = None
    lines: list[str] = field(default_factory=list)


class Graph:
    """A running (or ready to run) graph of node processes.

    Parameters
    ----------
    config : path of the graph configuration.
    overrides : per-node parameter overrides, ``{"fdi_plant": {"scenario": "..."}}``.
    record : bag directory to record every fdi topic into (adds the recorder node).
    replay : bag directory to replay instead of running the plant (adds the replayer node).
    echo : callable receiving every prefixed output line (default: print).
    """

    def __init__(self, config: str | Path, *, overrides: dict[str, dict] | None = None,
                 record: str | Path | None = None, replay: str | Path | None = None,
                 echo: Callable[[str], None] | None = print,
                 env: dict[str, str] | None = None) -> None:
        self.config_path = Path(config).resolve()
        self.cfg: GraphConfig = load_graph_config(self.config_path)
        self.echo = echo
        self.env = dict(os.environ if env is None else env)
        self.env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        self.env["PYTHONUNBUFFERED"] = "1"
        # parameter files live until stop() (a ROS launch file keeps them for its nodes)
        self._tmp = Path(tempfile.mkdtemp(prefix="fdi_launch_"))
        sections = {k: dict(v) for k, v in self.cfg.node_params.items() if k in NODE_KINDS}
        for k, v in (overrides or {}).items():
            sections.setdefault(k, {}).update(v)
        sections.setdefault("fdi_supervisor", {})["graph_config"] = str(self.config_path)
        if replay is not None:
            sections.pop("fdi_plant", None)
            sections.setdefault("fdi_replayer", {})["bag"] = str(Path(replay).resolve())
        else:
            sections.pop("fdi_replayer", None)
        plant = sections.get("fdi_plant")
        # the plant id of the graph configuration, unless a node section names another
        for node in ("fdi_plant", "fdi_preprocessor"):
            if node in sections:
                sections[node].setdefault("plant", self.cfg.plant)
        if plant and plant.get("scenario"):
            plant["scenario"] = self.cfg.resolve(str(plant["scenario"]))
        if record is not None:
            sections.setdefault("fdi_recorder", {})["bag"] = str(Path(record).resolve())
        else:
            sections.pop("fdi_recorder", None)
        self.nodes: list[NodeProcess] = []
        # bank models first: the supervisor finds their services when it starts; each gets the
        # common section `fdi_models` (e.g. use_sim_time) and its own model
        common = dict(self.cfg.node_params.get(MODELS_SECTION) or {})
        for e in self.cfg.bank:
            spec = self.cfg.resolve_spec(e.model)
            if not isinstance(spec, str):
                spec = yaml.safe_dump(spec, default_flow_style=True, width=10_000).strip()
            self._add(e.node_name, "residual_node", {**common, "model_id": e.id, "model": spec})
        order = ["fdi_recorder", "fdi_supervisor", "fdi_preprocessor", "fdi_plant",
                 "fdi_replayer"]
        for name in order:
            if name in sections:
                self._add(name, NODE_KINDS[name], sections[name])

    def _add(self, name: str, module: str, params: dict[str, Any]) -> None:
        pfile = self._tmp / f"{name}.yaml"
        pfile.write_text(yaml.safe_dump({name: {"ros__parameters": params}}))
        argv = [sys.executable, "-m", f"fdi_ros.nodes.{module}", "--ros-args",
                "-r", f"__node:={name}", "--params-file", str(pfile)]
        self.nodes.append(NodeProcess(name=name, module=module, argv=argv))

    def node(self, name: str) -> NodeProcess:
        for n in self.nodes:
            if n.name == name:
                return n
        raise KeyError(name)

    # -- processes ----------------------------------------------------------------------------
    def start(self, *, exclude: tuple[str, ...] = ()) -> Graph:
        """Start every node not yet started (except ``exclude``: start those later with
        :meth:`start_node`, e.g. the plant once the bank is on line)."""
        for n in self.nodes:
            if n.proc is None and n.name not in exclude:
                self.start_node(n.name)
        return self

    def start_node(self, name: str) -> None:
        n = self.node(name)
        n.proc = subprocess.Popen(n.argv, env=self.env, stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True, start_new_session=True,
                                  preexec_fn=_die_with_parent)
        threading.Thread(target=self._pump, args=(n,), daemon=True).start()

    @property
    def source(self) -> str:
        """The node that feeds the graph: the plant, or the replayer."""
        return "fdi_replayer" if any(n.name == "fdi_replayer" for n in self.nodes) \
            else "fdi_plant"

    def _pump(self, n: NodeProcess) -> None:
        assert n.proc is not None and n.proc.stdout is not None
        out: IO[str] = n.proc.stdout
        width = max(len(x.name) for x in self.nodes)
        for line in out:
            line = line.rstrip("\n")
            n.lines.append(line)
            if self.echo is not None:
                self.echo(f"[{n.name:<{width}}] {line}")

    def alive(self) -> dict[str, bool]:
        return {n.name: n.proc is not None and n.proc.poll() is None for n in self.nodes}

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        """Kill one node process (tests use this to check the supervisor survives)."""
        p = self.node(name).proc
        if p is not None and p.poll() is None:
            os.killpg(p.pid, sig)
            p.wait(timeout=10)

    def stop(self, timeout: float = 15.0) -> dict[str, int | None]:
        """SIGINT every node (the recorder last, so it sees everything), wait, kill leftovers."""
        procs = [n for n in self.nodes if n.proc is not None and n.proc.poll() is None]
        last = [n for n in procs if n.module == "recorder_node"]
        first = [n for n in procs if n.module != "recorder_node"]
        for group in (first, last):
            for n in group:
                try:
                    os.killpg(n.proc.pid, signal.SIGINT)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + timeout
            for n in group:
                try:
                    n.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    os.killpg(n.proc.pid, signal.SIGKILL)
                    n.proc.wait()
        shutil.rmtree(self._tmp, ignore_errors=True)
        return {n.name: (n.proc.returncode if n.proc else None) for n in self.nodes}

    def __enter__(self) -> Graph:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _die_with_parent() -> None:
    """In the child before exec: SIGTERM it when the launching process dies, however it dies
    (the nodes run in sessions of their own, so a killed launcher would otherwise leave them
    running). Linux only; elsewhere a no-op."""
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def run_until_interrupted(graph: Graph) -> int:
    """``fdi-ros launch``: run until Ctrl-C / SIGTERM or until every node has exited."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    graph.start()
    try:
        while not stop.is_set() and any(graph.alive().values()):
            stop.wait(0.2)
    except KeyboardInterrupt:
        pass
    codes = graph.stop()
    bad = {k: v for k, v in codes.items() if v not in (0, None, -2, 130)}
    if bad:
        print(f"fdi-ros launch: nodes exited with errors: {bad}", file=sys.stderr)
    return 0
