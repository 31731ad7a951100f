"""``fdi-ros diagnose <bag>... --json``: the graph's diagnosis offline, many times real time;
many bags at once on a local process pool or a Dask cluster (:mod:`fdi_ros.offline`)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from fdi_ros.offline import default_config, features_of_bag, summarise, valid_diagnosis

__all__ = ["default_config", "features_of_bag", "summarise", "valid_diagnosis"]

COMMAND = ("diagnose",)
HELP = "diagnose bags offline with the same core as the live graph (JSON summary out)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("bag", nargs="+",
                   help="rosbag2 directory with /fdi/sensor_block (or /fdi/features); several "
                        "bags: the JSON maps each bag to its single-bag result")
    p.add_argument("--config", help="graph configuration (default: config/<plant>.yaml)")
    p.add_argument("--json", metavar="FILE", nargs="?", const="-",
                   help="write the JSON summary to FILE (default: stdout)")
    p.add_argument("--workers", type=int, default=1,
                   help="bags diagnosed at once (default 1: one after the other, in this "
                        "process)")
    p.add_argument("--engine", choices=("local", "dask"), default="local",
                   help="local: a pool of local processes; dask: Dask distributed (a local "
                        "cluster of --workers processes on loopback unless --cluster)")
    p.add_argument("--cluster", metavar="ADDRESS",
                   help="the scheduler of an existing Dask cluster, e.g. tcp://host:8786 "
                        "(implies --engine dask)")
    p.add_argument("--report", metavar="DIR",
                   help="also write the fleet report: fleet.csv, fleet.md, faults_per_bag.png")
    p.add_argument("--progress", action="store_true", help="show a progress bar")


def run(args: argparse.Namespace) -> int:
    from fdi_ros.offline import diagnose_bag, diagnose_fleet, write_report

    t0 = time.perf_counter()
    single = len(args.bag) == 1 and not args.cluster and args.engine == "local"
    if single:
        # one bag: its errors end the command (one line on stderr, non-zero status)
        out: dict = diagnose_bag(args.bag[0], args.config, progress=args.progress)
        results = {str(args.bag[0]): out}
    else:
        results = diagnose_fleet(args.bag, workers=args.workers, engine=args.engine,
                                 cluster=args.cluster, config=args.config)
        out = results if len(args.bag) > 1 else results[str(args.bag[0])]
    wall = time.perf_counter() - t0
    if len(args.bag) > 1:
        span = sum(r.get("plant_seconds", 0.0) for r in results.values())
        print(f"{len(results)} bags, {span:.1f} s of plant time in {wall:.2f} s "
              f"({span / wall:.0f} x real time) with --workers {args.workers} "
              f"({'dask' if args.cluster or args.engine == 'dask' else 'local'})",
              file=sys.stderr)
    if args.report:
        files = write_report(results, args.report)
        print(f"fleet report: {', '.join(files.values())}", file=sys.stderr)
    text = json.dumps(out, indent=2)
    if args.json in (None, "-"):
        print(text)
    else:
        Path(args.json).write_text(text + "\n")
        print(f"diagnosis written to {args.json}", file=sys.stderr)
    errors = [b for b, r in results.items() if "error" in r]
    for b in errors:
        print(f"{b}: {results[b]['error']}", file=sys.stderr)
    return 1 if errors else 0
