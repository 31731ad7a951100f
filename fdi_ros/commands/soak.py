"""``fdi-ros soak``: the live graph on a fault-free transient drive, disturbed the way a user
and a bad day disturb it, counting false isolations (there must be none).

Every ``--every`` wall seconds one disturbance, in turn: an external ``deactivate`` of the
nominal model through its lifecycle service (the supervisor reconciles it), a SIGSTOP of the
preprocessor for ``--freeze`` s then SIGCONT, ``kill -9`` of a random hypothesis model node and
``kill -9`` of the supervisor (each respawned after 1 s, as ``fdi-ros launch`` does). Prints
(and with ``--json`` writes) the figures; exit status 1 on any isolation.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import tempfile
import time
from pathlib import Path
from typing import Any

COMMAND = ("soak",)
HELP = "fault-free live soak under external lifecycle changes, frozen and killed nodes"
DISTURBANCES = ("external_deactivate", "freeze_preprocessor", "kill_model", "kill_supervisor")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", default="config/diesel.yaml")
    p.add_argument("--scenario", default="config/scenarios/diesel_drive.yaml",
                   help="fault-free transient scenario (longer than --minutes)")
    p.add_argument("--minutes", type=float, default=10.0, help="plant minutes to run")
    p.add_argument("--every", type=float, default=30.0, help="wall s between disturbances")
    p.add_argument("--freeze", type=float, default=3.0, help="wall s the preprocessor stops")
    p.add_argument("--seed", type=int, default=0, help="seed of the models killed")
    p.add_argument("--json", metavar="OUT", help="write the figures to OUT")


def _deactivate(w: Any, node: str) -> bool:
    from lifecycle_msgs.srv import ChangeState

    cli = w.node.create_client(ChangeState, f"/{node}/change_state")
    try:
        if not cli.wait_for_service(timeout_sec=5.0):
            return False
        req = ChangeState.Request()
        req.transition.id = 4  # deactivate
        fut = cli.call_async(req)
        w.spin_until(fut.done, 10.0, f"change_state of {node}")
        return bool(fut.result().success)
    finally:
        w.node.destroy_client(cli)


def _signal(graph: Any, name: str, sig: int) -> None:
    p = graph.node(name).proc
    if p is not None and p.poll() is None:
        os.killpg(p.pid, sig)


def run(args: argparse.Namespace) -> int:
    from fdi_ros.graphwatch import GraphWatcher, run_ended
    from fdi_ros.launcher import RESPAWN_MODULES, Graph

    rng = random.Random(args.seed)
    state = tempfile.mkdtemp(prefix="fdi_soak_")  # a fault memory of its own
    env = {**os.environ, "FDI_ROS_STATE_DIR": state}
    graph = Graph(args.config, overrides={"fdi_plant": {"scenario": str(Path(
        args.scenario).resolve()), "realtime_factor": 1.0}}, echo=None, env=env,
        watcher="fdi_soak_watcher")
    w = GraphWatcher("fdi_soak_watcher")
    hyps = [e for e in graph.cfg.bank if e.faults]
    nominal = next(e for e in graph.cfg.bank if not e.faults)
    done: list[dict] = []
    respawns = 0
    due: dict[str, float] = {}
    thaw: float | None = None
    end_t = 60.0 * args.minutes
    wall0 = time.monotonic()
    next_at = None
    try:
        graph.start()
        while time.monotonic() - wall0 < end_t * 1.5 + 180:
            w.executor.spin_once(timeout_sec=0.05)
            d = w.last_diagnosis()
            now = time.monotonic()
            if d is not None and d.t >= end_t or run_ended(w.seen):
                break
            for n in graph.nodes:  # respawn, as fdi-ros launch does
                if n.module in RESPAWN_MODULES and n.proc is not None and \
                        n.proc.poll() is not None and n.name not in due:
                    due[n.name] = now + 1.0
            for name, at in list(due.items()):
                if now >= at:
                    del due[name]
                    graph.start_node(name)
                    respawns += 1
            if thaw is not None and now >= thaw:
                _signal(graph, "fdi_preprocessor", signal.SIGCONT)
                thaw = None
            if d is None:
                continue
            next_at = now + args.every if next_at is None else next_at
            if now < next_at or due or thaw is not None:
                continue
            next_at = now + args.every
            kind = DISTURBANCES[len(done) % len(DISTURBANCES)]
            what = ""
            if kind == "external_deactivate":
                what = f"{nominal.node_name} deactivated: {_deactivate(w, nominal.node_name)}"
            elif kind == "freeze_preprocessor":
                _signal(graph, "fdi_preprocessor", signal.SIGSTOP)
                thaw, what = now + args.freeze, f"preprocessor stopped {args.freeze:g} s"
            else:
                name = ("fdi_supervisor" if kind == "kill_supervisor"
                        else rng.choice(hyps).node_name)
                graph.kill(name)
                what = f"{name} killed (-9)"
            done.append({"t": round(d.t, 3), "kind": kind, "what": what})
            print(f"t = {d.t:8.3f} s  {what}", flush=True)
    finally:
        if thaw is not None:
            _signal(graph, "fdi_preprocessor", signal.SIGCONT)
        graph.stop()
        w.close()
    ds = [d for _, d in w.seen.diagnoses]
    iso = sorted({(round(d.isolation_time, 3), d.fault_model) for d in ds
                  if d.state == "isolated"})
    states: dict[str, int] = {}
    for d in ds:
        states[d.state] = states.get(d.state, 0) + 1
    out = {"plant_s": round(ds[-1].t, 3) if ds else 0.0,
           "wall_s": round(time.monotonic() - wall0, 1), "segments": len(ds),
           "states": states, "false_isolations": [{"t": t, "model": m} for t, m in iso],
           "disturbances": done, "respawns": respawns}
    print(json.dumps(out, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    ok = not iso and out["plant_s"] >= 0.95 * end_t
    print(f"soak: {len(iso)} false isolations in {out['plant_s']:.0f} s of plant time "
          f"({len(done)} disturbances, {respawns} respawns): {'OK' if ok else 'FAILED'}")
    return 0 if ok else 1
