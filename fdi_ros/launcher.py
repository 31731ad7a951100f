"""Start a graph configuration as separate processes (as ``ros2 launch`` would).

The graph configuration (``config/<plant>.yaml``, see :mod:`fdi_ros.core.graphconfig`) names
the node sections; the bank adds one residual-generator node per model, hosted as the
configuration's ``hosting`` (or the ``hosting`` argument) says: one process per model node
(the default), or several model nodes per model-host process (``fdi_model_host_<k>``, see
:mod:`fdi_ros.nodes.model_host_node`), each still a lifecycle node of its own. Each process gets
a parameter file with only its own section (``--ros-args --params-file``) and its node name
(``-r __node:=``). Output lines are prefixed with the node name. ``stop()`` sends SIGINT to
all, waits, and kills what is left: Ctrl-C on ``fdi-ros launch`` shuts everything down cleanly.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import yaml

from fdi_ros.core.graphconfig import GraphConfig, Hosting, load_graph_config

# node name of the launcher's own watcher (diagnosis events, end of data, /diagnostics reports)
WATCHER = "fdi_launch_watcher"
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


# the largest ROS domain id whose DDS ports exist (ROS 2 documents 0-232)
MAX_DOMAIN_ID = 232


@dataclass
class NodeProcess:
    name: str
    module: str
    argv: list[str]
    proc: subprocess.Popen | None = None
    lines: list[str] = field(default_factory=list)
    hosted: tuple[str, ...] = ()  # the node names a model host holds


class Graph:
    """A running (or ready to run) graph of node processes.

    Parameters
    ----------
    config : path of the graph configuration.
    overrides : per-node parameter overrides, ``{"fdi_plant": {"scenario": "..."}}``.
    record : bag directory to record every fdi topic into (adds the recorder node).
    replay : bag directory to replay instead of running the plant (adds the replayer node).
    echo : callable receiving every prefixed output line (default: print).
    hosting : how the bank's model nodes are hosted (default: the configuration's ``hosting``;
        a dict replaces only the fields it names, e.g. ``{"mode": "container"}``).
    extra_block_readers : readers of /fdi/sensor_block outside the graph (e.g. a watcher)
        that the source waits for too.
    watcher : node name of a watcher outside the graph (:class:`fdi_ros.graphwatch.
        GraphWatcher`) whose reader of /fdi/diagnosis the supervisor waits for (None: none).

    Start-up handshake: the source (plant or replayer) sends its first block once every
    reader of the sensor blocks in the graph (preprocessor, supervisor, recorder) is matched
    to it and the supervisor has said on ``/fdi/ready`` that the bank is active and every
    reader of the features, residuals and diagnoses is there (the recorder too). So all
    processes may start at once, under ``fdi-ros launch`` as under ``ros2 launch``, and no
    part misses the first segments.
    """

    def __init__(self, config: str | Path, *, overrides: dict[str, dict] | None = None,
                 record: str | Path | None = None, replay: str | Path | None = None,
                 echo: Callable[[str], None] | None = print,
                 env: dict[str, str] | None = None,
                 hosting: Hosting | dict[str, Any] | None = None, extra_block_readers: int = 0,
                 watcher: str | None = None) -> None:
        self.config_path = Path(config).resolve()
        self.cfg: GraphConfig = load_graph_config(self.config_path)
        if isinstance(hosting, dict):  # some fields over the configuration's
            hosting = dataclasses.replace(self.cfg.hosting, **{
                k: v for k, v in hosting.items() if v is not None})
        self.hosting = hosting if hosting is not None else self.cfg.hosting
        self.echo = echo
        self.env = dict(os.environ if env is None else env)
        self.env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        domain = self.env.get("ROS_DOMAIN_ID", "0").strip() or "0"
        if not domain.isdigit() or int(domain) > MAX_DOMAIN_ID:
            # Fast DDS derives its ports from the domain id: above 232 it logs an RTPS error
            # in every process and the graph never discovers itself
            raise ValueError(f"ROS_DOMAIN_ID={domain!r}: a domain id is 0-{MAX_DOMAIN_ID}")
        # many node processes share few cores: one BLAS thread each (spinning BLAS worker
        # threads of one node would take the core another node needs)
        self.env.setdefault("OPENBLAS_NUM_THREADS", "1")
        self.env.setdefault("OMP_NUM_THREADS", "1")
        self.env["PYTHONUNBUFFERED"] = "1"
        # parameter files live until stop() (a ROS launch file keeps them for its nodes)
        self._tmp = Path(tempfile.mkdtemp(prefix="fdi_launch_"))
        # removed by stop(), and at the latest when the graph object goes (or the interpreter
        # exits), however the launcher ends
        weakref.finalize(self, shutil.rmtree, str(self._tmp), True)
        sections = {k: dict(v) for k, v in self.cfg.node_params.items() if k in NODE_KINDS}
        for k, v in (overrides or {}).items():
            if k != MODELS_SECTION:
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
        sections["fdi_supervisor"].setdefault("wait_for_readers", [
            *(["fdi_recorder"] if record is not None else []),
            *([f"{watcher}:/fdi/diagnosis"] if watcher else [])] or [""])
        readers = sum(k in sections for k in ("fdi_preprocessor", "fdi_supervisor",
                                              "fdi_recorder")) + extra_block_readers
        for src in ("fdi_plant", "fdi_replayer"):
            if src in sections:
                sections[src].setdefault("min_subscribers", readers)
                sections[src].setdefault("wait_for_ready", True)
        self.nodes: list[NodeProcess] = []
        # bank models first: the supervisor finds their services when it starts; each gets the
        # common section `fdi_models` (e.g. use_sim_time) and its own model
        common = {**(self.cfg.node_params.get(MODELS_SECTION) or {}),
                  **(overrides or {}).get(MODELS_SECTION, {})}
        pfiles = {}
        for e in self.cfg.bank:
            spec = self.cfg.resolve_spec(e.model)
            if not isinstance(spec, str):
                spec = yaml.safe_dump(spec, default_flow_style=True, width=10_000).strip()
            pfiles[e.node_name] = self._params_file(
                e.node_name, {**common, "model_id": e.id, "model": spec})
        # the symptoms' model answers first in its host (nodes/bundle.py)
        urgent = {e.node_name for e in self.cfg.bank
                  if e.id == (self.cfg.symptoms or {}).get("model")}
        for i_host, names in enumerate(self.hosting.groups(list(pfiles))):
            if self.hosting.mode == "process":
                self._add(names[0], "residual_node", pfile=pfiles[names[0]])
                continue
            host = [f"--node={n}={pfiles[n]}" for n in names] + [
                f"--urgent={n}" for n in names if n in urgent]
            self.nodes.append(NodeProcess(
                name=f"fdi_model_host_{i_host}", module="model_host_node", hosted=tuple(names),
                argv=[sys.executable, "-m", "fdi_ros.nodes.model_host_node",
                      f"--executor={self.hosting.executor}", *host]))
        order = ["fdi_recorder", "fdi_supervisor", "fdi_preprocessor", "fdi_plant",
                 "fdi_replayer"]
        for name in order:
            if name in sections:
                self._add(name, NODE_KINDS[name], sections[name])

    def _params_file(self, name: str, params: dict[str, Any]) -> Path:
        pfile = self._tmp / f"{name}.yaml"
        pfile.write_text(yaml.safe_dump({name: {"ros__parameters": params}}))
        return pfile

    def _add(self, name: str, module: str, params: dict[str, Any] | None = None,
             pfile: Path | None = None) -> None:
        pfile = pfile if pfile is not None else self._params_file(name, params or {})
        argv = [sys.executable, "-m", f"fdi_ros.nodes.{module}", "--ros-args",
                "-r", f"__node:={name}", "--params-file", str(pfile)]
        self.nodes.append(NodeProcess(name=name, module=module, argv=argv))

    def node(self, name: str) -> NodeProcess:
        """The process of node ``name`` (for a hosted model node: its model host)."""
        for n in self.nodes:
            if n.name == name or name in n.hosted:
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
        """Liveness per process and per hosted node (a hosted node lives with its host)."""
        out = {}
        for n in self.nodes:
            out[n.name] = n.proc is not None and n.proc.poll() is None
            out.update(dict.fromkeys(n.hosted, out[n.name]))
        return out

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        """Kill one node process (tests use this to check the supervisor survives); for a
        hosted model node, its model host with every node it holds."""
        p = self.node(name).proc
        if p is not None and p.poll() is None:
            os.killpg(p.pid, sig)
            p.wait(timeout=10)

    def stop(self, timeout: float = 15.0) -> dict[str, int | None]:
        """SIGINT every node (the recorder last, so it sees everything), wait, kill leftovers."""
        procs = [(n.module, p) for n in self.nodes if (p := n.proc) is not None
                 and p.poll() is None]
        last = [p for module, p in procs if module == "recorder_node"]
        first = [p for module, p in procs if module != "recorder_node"]
        for group in (first, last):
            for p in group:
                try:
                    os.killpg(p.pid, signal.SIGINT)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + timeout
            for p in group:
                try:
                    p.wait(timeout=max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait()
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


# nodes restarted when they die (ROS launch's ``respawn=True``); the others end the run
RESPAWN_MODULES = ("supervisor_node", "residual_node", "model_host_node")


@dataclass
class RespawnPolicy:
    """Back-off ``first_delay_s * 2**k`` (capped at ``max_delay_s``), at most ``limit``
    restarts per node."""

    limit: int = 5
    first_delay_s: float = 1.0
    max_delay_s: float = 8.0

    def delay(self, attempt: int) -> float:
        return min(self.max_delay_s, self.first_delay_s * 2 ** attempt)


def _died(code: int | None) -> bool:
    """An exit that is not a clean stop (0, SIGINT, SIGTERM)."""
    return code not in (None, 0, -signal.SIGINT, -signal.SIGTERM, 130, 143)


def run_until_interrupted(graph: Graph, *, respawn: RespawnPolicy | None = None,
                          json_out: str | Path | None = None,
                          log: Callable[[str], None] | None = None) -> int:
    """``fdi-ros launch``: run until SIGINT / SIGTERM, until the data ends, or until
    the graph cannot go on (the recorder died, a node died past its respawn limit).

    Every process starts at once; the source (plant or replayer) sends its first block after
    the start-up handshake (see :class:`Graph`). When its data ends (the end-of-data event on
    ``/fdi/end_of_data``, of the replayer or of the plant at its scenario's end) the launcher
    waits for the supervisor's end of the diagnosis (the last segment diagnosed, see
    :func:`fdi_ros.graphwatch.run_ended`), stops the graph and exits 0. A recorder that dies
    is reported at once on ``/diagnostics`` (ERROR, "fdi_launch: recorder") before the graph
    stops; so is any other node that dies (WARN while it is respawned, ERROR when that ends
    the run). ``json_out`` gets the diagnosis events of the run (the format of
    ``fdi-ros diagnose --json``'s ``events``).
    Exit status: 0 clean, 1 a node died (or the recorder could not record), 130/143 on
    SIGINT/SIGTERM.
    """
    log = log or (lambda m: print(f"fdi-ros launch: {m}", file=sys.stderr, flush=True))
    respawn = respawn or RespawnPolicy()
    stop = threading.Event()
    got: dict[str, int] = {}

    def _on_signal(signum: int, _frame: object) -> None:
        got.setdefault("sig", signum)
        stop.set()

    # set both explicitly: a background job inherits SIGINT as ignored
    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    source = graph.source
    watcher = None
    status = 0
    try:
        if source in {n.name for n in graph.nodes}:
            from fdi_ros.graphwatch import GraphWatcher, run_ended

            watcher = GraphWatcher(WATCHER, watch_end=True)
        graph.start()
        if watcher is None:
            log(f"no {source} in the graph: running until stopped")
        attempts: dict[str, int] = {}
        due: dict[str, float] = {}
        end_seen_at: float | None = None
        while status == 0 and not stop.is_set():
            if watcher is not None:
                watcher.executor.spin_once(timeout_sec=0.1)
            else:
                stop.wait(0.2)
            now = time.monotonic()
            for n in graph.nodes:
                code = n.proc.poll() if n.proc is not None else None
                if n.proc is None or code is None or n.name in due:
                    continue
                if n.module == "recorder_node":
                    why = (f"the recorder exited (status {code}): the graph is not being "
                           "recorded; stopping")
                    log(why)
                    if watcher is not None:
                        watcher.report("fdi_launch: recorder", 2, why, n.name)
                    status = 1
                elif n.module in RESPAWN_MODULES and _died(code):
                    k = attempts.get(n.name, 0)
                    if k >= respawn.limit:
                        why = (f"{n.name} died (status {code}) and was restarted {k} times "
                               "already: giving up")
                        status = 1
                    else:
                        d = respawn.delay(k)
                        why = (f"{n.name} died (status {code}); respawning in {d:.1f} s "
                               f"(attempt {k + 1}/{respawn.limit})")
                        due[n.name] = now + d
                        attempts[n.name] = k + 1
                    log(why)
                    if watcher is not None:
                        watcher.report(f"fdi_launch: {n.name}", 2 if status else 1, why, n.name)
                elif _died(code):
                    log(f"{n.name} died (status {code}); stopping")
                    if watcher is not None:
                        watcher.report(f"fdi_launch: {n.name}", 2, f"{n.name} died (status "
                                       f"{code}); stopping", n.name)
                    status = 1
            for name, t in list(due.items()):
                if now >= t and not stop.is_set():
                    del due[name]
                    graph.start_node(name)
            if watcher is not None:
                ended = run_ended(watcher.seen)
                # the supervisor's end names the source's end: its own message (another topic)
                # can reach this watcher after the end of the diagnosis
                if end_seen_at is None and (watcher.seen.end_of_data or ended):
                    end_seen_at = now
                    log("end of data" + ("" if ended else
                                         ": waiting for the last segment's diagnosis"))
                if ended:
                    log("end of the diagnosis: every segment of the data diagnosed")
                    break
                if end_seen_at is not None and now - end_seen_at > END_TIMEOUT_S:
                    log(f"the diagnosis did not reach the end of the data {END_TIMEOUT_S:g} s "
                        "after it (is the supervisor or the preprocessor running?); stopping")
                    status = 1
            if watcher is None and not any(graph.alive().values()):
                break
    finally:
        codes = graph.stop()
        if watcher is not None:
            if json_out is not None:
                _write_events(watcher, json_out)
                log(f"diagnosis events written to {json_out}")
            watcher.close()
    bad = {k: v for k, v in codes.items() if _died(v)}
    if bad:
        log(f"nodes exited with errors: {bad}")
        status = status or 1
    if "sig" in got and status == 0:
        status = 128 + got["sig"]
    return status


# health only: wall seconds after the source's end of data without the supervisor's end of the
# diagnosis (which normally follows within the pipeline's lag) before the run is given up
END_TIMEOUT_S = 60.0


def _write_events(watcher: Any, path: str | Path) -> None:
    import json

    from fdi_ros.core.events import diagnosis_events

    ds = sorted((d for _, d in watcher.seen.diagnoses), key=lambda d: d.index)
    Path(path).write_text(json.dumps({"events": diagnosis_events(ds)}, indent=2) + "\n")
