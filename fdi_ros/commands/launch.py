"""``fdi-ros launch config/<plant>.yaml``: the live graph, one process per node (or the bank's
model nodes in a few model-host processes: ``--hosting container``)."""

from __future__ import annotations

import argparse
from pathlib import Path

COMMAND = ("launch",)
HELP = "launch the live graph of a configuration (each node its own process; Ctrl-C stops all)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="graph configuration, e.g. config/diesel.yaml")
    p.add_argument("--scenario", help="plant scenario YAML (overrides the configuration)")
    p.add_argument("--realtime-factor", type=float, help="plant seconds per wall second")
    p.add_argument("--record", metavar="BAG", help="record every fdi topic into this bag")
    p.add_argument("--replay", metavar="BAG", help="replay this bag instead of the plant")
    p.add_argument("--rate", type=float, default=1.0, help="replay rate (with --replay)")
    p.add_argument("--start-delay", type=float, default=None, metavar="S",
                   help="the data source waits S more wall seconds after the start-up "
                        "handshake (default: the configuration's, else 0)")
    p.add_argument("--json", metavar="OUT",
                   help="write the run's diagnosis events (as fdi-ros diagnose --json) to OUT")
    p.add_argument("--respawn-limit", type=int, default=5,
                   help="restarts of a dead supervisor, model node or model host (0: none)")
    add_hosting_arguments(p)


def add_hosting_arguments(p: argparse.ArgumentParser) -> None:
    """``--hosting``, ``--containers``, ``--executor`` (default: the configuration's)."""
    p.add_argument("--hosting", choices=("process", "container"),
                   help="bank model nodes: one process each, or in model-host processes")
    p.add_argument("--containers", type=int, metavar="N",
                   help="model-host processes with --hosting container")
    p.add_argument("--executor", choices=("single", "events"),
                   help="executor of a model host: SingleThreadedExecutor or EventsExecutor")


def hosting_overrides(args: argparse.Namespace) -> dict:
    return {"mode": args.hosting, "containers": args.containers, "executor": args.executor}


def run(args: argparse.Namespace) -> int:
    from fdi_ros.launcher import WATCHER, Graph, RespawnPolicy, run_until_interrupted

    over: dict[str, dict] = {"fdi_plant": {}, "fdi_replayer": {"rate": args.rate}}
    if args.start_delay is not None:
        if not args.start_delay >= 0:
            raise ValueError("--start-delay must be >= 0")
        for section in over.values():
            section["start_delay_s"] = args.start_delay
    if args.scenario:
        over["fdi_plant"]["scenario"] = args.scenario
    if args.realtime_factor is not None:
        over["fdi_plant"]["realtime_factor"] = args.realtime_factor
    if args.record and Path(args.record).exists():
        raise ValueError(f"{args.record} already exists: the recorder cannot record there; "
                         "choose another --record")
    # A malformed configuration raises ValueError: fdi_ros.cli answers it in one line.
    graph = Graph(args.config, overrides=over, record=args.record, replay=args.replay,
                  hosting=hosting_overrides(args), watcher=WATCHER)
    return run_until_interrupted(graph, respawn=RespawnPolicy(limit=args.respawn_limit),
                                 json_out=args.json)
