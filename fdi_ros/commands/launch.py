"""``fdi-ros launch config/<plant>.yaml``: the live graph, one process per node."""

from __future__ import annotations

import argparse

COMMAND = ("launch",)
HELP = "launch the live graph of a configuration (each node its own process; Ctrl-C stops all)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="graph configuration, e.g. config/diesel.yaml")
    p.add_argument("--scenario", help="plant scenario YAML (overrides the configuration)")
    p.add_argument("--realtime-factor", type=float, help="plant seconds per wall second")
    p.add_argument("--record", metavar="BAG", help="record every fdi topic into this bag")
    p.add_argument("--replay", metavar="BAG", help="replay this bag instead of the plant")
    p.add_argument("--rate", type=float, default=1.0, help="replay rate (with --replay)")


def run(args: argparse.Namespace) -> int:
    from fdi_ros.launcher import Graph, run_until_interrupted

    over: dict[str, dict] = {"fdi_plant": {}, "fdi_replayer": {"rate": args.rate}}
    if args.scenario:
        over["fdi_plant"]["scenario"] = args.scenario
    if args.realtime_factor is not None:
        over["fdi_plant"]["realtime_factor"] = args.realtime_factor
    graph = Graph(args.config, overrides=over, record=args.record, replay=args.replay)
    return run_until_interrupted(graph)
