"""``fdi-ros build-bank config/<plant>.yaml``: identify every missing model of the bank."""

from __future__ import annotations

import argparse

COMMAND = ("build-bank",)
HELP = "identify every model of a graph configuration's bank that is not built yet"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="graph configuration, e.g. config/diesel.yaml")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    from fdi_ros.plants import ensure_bank

    built = ensure_bank(args.config, progress=not args.no_progress, seed=args.seed)
    print(f"built: {', '.join(built) if built else 'nothing (all models present)'}")
    return 0
