"""``fdi-ros simulate``: run a diesel scenario into a rosbag2 (MCAP) bag and/or a CSV file.

The bag holds ``/fdi/sensor_block`` (SampleBlocks of ``block_deg`` crank angle each, channels
n [rpm], p2 [Pa], T2 [K], maf [kg/h], fuel [mg/stroke], egr_cmd, swirl_cmd, vgt [1]) and
``/fdi/fault_truth`` (the scenario's fault events at their times); with ``--features`` also
``/fdi/features`` (the crank-synchronous segment features).

The CSV has a header row ``t,alpha,n,p2,T2,maf,fuel,egr_cmd,swirl_cmd,vgt`` with units
t [s], alpha [deg CA], n [rpm], p2 [Pa], T2 [K], maf [kg/h], fuel [mg/stroke], egr_cmd [1],
swirl_cmd [1], vgt [1] (``config/mappings/fdi_ros_csv.yaml`` maps it).
"""

from __future__ import annotations

import argparse
import json

COMMAND = ("simulate",)
HELP = "simulate a diesel scenario (YAML) into a rosbag2 MCAP bag and/or CSV"

CSV_COLUMNS = ("t", "alpha", "n", "p2", "T2", "maf", "fuel", "egr_cmd", "swirl_cmd", "vgt")
_CSV_FMT = ("%.9f", "%.3f", "%.3f", "%.2f", "%.4f", "%.4f", "%.4f", "%.4f", "%.4f", "%.5f")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", help="scenario YAML (config/scenarios/diesel_*.yaml)")
    parser.add_argument("--out", help="bag directory to create (rosbag2, MCAP storage)")
    parser.add_argument("--csv", help="also/instead write the samples to this CSV file")
    parser.add_argument("--seed", type=int, default=None,
                        help="sensor-noise seed (default: the scenario's)")
    parser.add_argument("--case", default=None, help="case name or index in a multi-case file")
    parser.add_argument("--features", action="store_true",
                        help="also write the crank-synchronous features to /fdi/features")
    parser.add_argument("--features-only", action="store_true",
                        help="write /fdi/features and /fdi/fault_truth but no sensor blocks "
                             "(a small bag that `fdi-ros diagnose` reads directly)")
    parser.add_argument("--duration", type=float, default=None,
                        help="stop after this many seconds [s] (default: the scenario's)")
    parser.add_argument("--progress", action="store_true", help="show a progress bar")


def run(args: argparse.Namespace) -> int:
    import dataclasses
    from pathlib import Path

    import numpy as np

    from fdi_ros.plants.diesel.plant import crank_segmenter
    from fdi_ros.plants.diesel.scenario import iter_simulate, load_scenario

    if not args.out and not args.csv:
        raise ValueError("give --out <bag dir> and/or --csv <file.csv>")
    case = args.case
    if case is not None and case.isdigit():
        case = int(case)
    sc = load_scenario(args.scenario, case=case)
    if args.duration is not None:
        if not args.duration > 0:
            raise ValueError("--duration must be > 0")
        sc = dataclasses.replace(sc, duration_s=float(args.duration))
    if args.out and Path(args.out).exists():
        raise ValueError(f"bag {args.out} already exists: choose another --out")
    writer = None
    if args.out:
        from fdi_ros import bag
        writer = bag.BagWriter(args.out)
    fh = open(args.csv, "w") if args.csv else None  # noqa: SIM115 (closed in finally)
    want_features = args.features or args.features_only
    seg = crank_segmenter(sc.params) if want_features else None
    bar = None
    if args.progress:
        from tqdm import tqdm
        bar = tqdm(total=round(sc.duration_s, 3), unit="s", desc=sc.name)
    n_blocks = n_samples = n_feat = 0
    pending = sorted(sc.faults, key=lambda e: e.t)
    try:
        if fh is not None:
            fh.write(",".join(CSV_COLUMNS) + "\n")
        for block, _plant in iter_simulate(sc, seed=args.seed):
            if writer is not None:
                while pending and pending[0].t <= block.t[-1]:
                    writer.write_fault(pending.pop(0))
                if not args.features_only:
                    writer.write_block(block)
                if seg is not None:
                    for fv in seg.push(block):
                        writer.write_features(fv)
                        n_feat += 1
            if fh is not None:
                cols = [block.t, block.alpha] + [block.channel(c) for c in CSV_COLUMNS[2:]]
                np.savetxt(fh, np.column_stack(cols), fmt=_CSV_FMT, delimiter=",")
            n_blocks += 1
            n_samples += block.t.size
            if bar is not None:
                bar.update(round(min(block.t[-1], sc.duration_s) - bar.n, 3))
        if writer is not None:
            for ev in pending:          # events after the end are still ground truth
                writer.write_fault(ev)
    finally:
        if writer is not None:
            writer.close()
        if fh is not None:
            fh.close()
        if bar is not None:
            bar.close()
    print(json.dumps({"scenario": sc.name, "seed": sc.seed if args.seed is None else args.seed,
                      "duration_s": sc.duration_s, "blocks": n_blocks, "samples": n_samples,
                      "features": n_feat, "faults": len(sc.faults), "bag": args.out,
                      "csv": args.csv}))
    return 0
