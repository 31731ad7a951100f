"""``fdi-ros import CSV --mapping M --out BAG``: a measured file as a bag of sensor blocks."""

from __future__ import annotations

import argparse
from pathlib import Path

COMMAND = ("import",)
HELP = ("turn a measured CSV (with a column mapping) into a rosbag2/MCAP bag of sensor blocks "
        "and its fault ground truth, for fdi-ros diagnose and the live graph's replay")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("csv", help="measured CSV file")
    p.add_argument("--mapping", required=True, help="column mapping YAML, e.g. "
                   "config/mappings/liu_ice.yaml")
    p.add_argument("--out", required=True, metavar="BAG", help="bag directory to create")
    p.add_argument("--plant", default="liu_ice", choices=["liu_ice"])
    p.add_argument("--block-samples", type=int, default=10, help="samples per sensor block")
    p.add_argument("--onset", type=float, help="fault onset [s] for a file not in the "
                   "benchmark's table")


def run(args: argparse.Namespace) -> int:
    from fdi_ros.bag import BagWriter
    from fdi_ros.plants.liu_ice import truth_of
    from fdi_ros.plants.liu_ice.live import blocks_of, load_record, truth_events

    rec = load_record(args.csv, args.mapping)
    truth = truth_of(args.csv, args.onset, unlabelled_ok=True)
    blocks = blocks_of(rec, args.block_samples)
    events = truth_events(truth)
    with BagWriter(args.out) as w:
        pending = list(events)
        for b in blocks:
            w.write_block(b)
            while pending and pending[0].t <= float(b.t[-1]):
                w.write_fault(pending.pop(0))
    label = f"{truth.fault} from {truth.onset_s:g} s" if truth.faulty else \
        "none (no fault in the file's label, or no label)"
    print(f"{Path(args.csv).name}: {rec.n_samples} samples in {len(blocks)} blocks, "
          f"ground truth {label} -> {args.out}")
    return 0
