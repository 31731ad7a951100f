"""``fdi-ros bag recover BAG``: rebuild a bag a killed recorder left without metadata."""

from __future__ import annotations

import argparse
import json
import sys

COMMAND = ("bag", "recover")
HELP = "rebuild metadata.yaml (and a complete MCAP file) of a bag cut short, like ros2 bag reindex"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("bag", help="rosbag2 directory holding one .mcap file")


def run(args: argparse.Namespace) -> int:
    from fdi_ros.bag import BagError, recover

    try:
        out = recover(args.bag)
    except (BagError, OSError) as exc:
        print(f"fdi-ros bag recover: {exc}", file=sys.stderr)
        return 2
    if out["truncated"]:
        print(f"fdi-ros bag recover: the file ends early ({out['error']}); kept every message "
              "before that point", file=sys.stderr)
    print(json.dumps(out, indent=2))
    return 0
