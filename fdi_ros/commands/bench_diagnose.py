"""``fdi-ros bench diagnose``: offline diagnosis from raw 1 deg CA sensor blocks in a bag to the
diagnosis, against the step-wise path measured in the same run, and a fleet of bags on 1 and N
local workers.

The bag is a window of the transient drive cycle (``config/scenarios/diesel_drive.yaml``) with
a fault, simulated into a temporary rosbag2/MCAP bag. ``realtime_factor`` = plant seconds /
wall seconds of ``fdi-ros diagnose BAG`` (reading the bag, segmenting the crank-angle signals,
loading and running the bank, symptoms and supervisor); the baseline is the step-wise path the
live graph runs (message objects from the general bag reader, one block and one segment at a
time), which must give the same result.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

COMMAND = ("bench", "diagnose")
HELP = "offline diagnosis: x real time of `fdi-ros diagnose` against the step-wise path"

DRIVE = "config/scenarios/diesel_drive.yaml"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--duration", type=float, default=300.0,
                   help="window of the drive cycle [s] (default 300)")
    p.add_argument("--fault-at", type=float, default=200.0,
                   help="a 5 mm leak intercooler -> engine from this time [s] (default 200)")
    p.add_argument("--repeat", type=int, default=3, help="fast-path runs (best reported)")
    p.add_argument("--fleet", type=int, default=4, help="bags in the fleet measurement (0: none)")
    p.add_argument("--fleet-duration", type=float, default=150.0,
                   help="window of the drive cycle per fleet bag [s]")
    p.add_argument("--workers", type=int, default=2, help="workers of the fleet measurement")
    p.add_argument("--json", action="store_true", help="JSON output (the default)")


def _window(duration: float, fault_at: float | None, seed: int) -> dict:
    import yaml

    from fdi_ros.plants import ROOT

    doc = yaml.safe_load((ROOT / DRIVE).read_text())
    doc["name"] = f"drive_window_{seed}"
    doc["duration_s"], doc["seed"] = float(duration), int(seed)
    doc["faults"] = [] if fault_at is None or fault_at >= duration else [
        {"t": float(fault_at), "fault": "leak_ic_engine", "size": 5, "unit": "mm",
         "profile": "step"}]
    return doc


def _step_wise(path) -> dict:
    """The path the live graph runs, offline: message objects, block by block, segment by
    segment (the reference of the tests)."""
    import time

    from fdi_ros import bag, msgs
    from fdi_ros.core.diagnoser import diagnose_offline
    from fdi_ros.core.graphconfig import load_graph_config
    from fdi_ros.offline import default_config, summarise
    from fdi_ros.plants import make_preprocessor

    t0 = time.perf_counter()
    blocks = [msgs.to_sample_block(m) for _, _, _, m in bag.read(path, ["/fdi/sensor_block"])]
    pre = make_preprocessor(blocks[0].plant)
    feats = [fv for b in blocks for fv in pre.push(b)]
    cfg = load_graph_config(default_config(blocks[0].plant))
    steps = diagnose_offline(cfg, feats, batch=False)
    wall = time.perf_counter() - t0
    truth = [msgs.to_fault_event(m) for _, _, _, m in bag.read(path, ["/fdi/fault_truth"])]
    span = feats[-1].t_end - feats[0].t_start
    return {"bag": str(path), "plant": blocks[0].plant, "config": str(cfg.path),
            **summarise(steps, span, wall, truth)}


def _stages(path) -> dict:
    """Where the fast path's time goes (one more run, stage by stage)."""
    import time

    from fdi_ros import bag
    from fdi_ros.core.diagnoser import diagnose_offline
    from fdi_ros.core.graphconfig import load_graph_config
    from fdi_ros.core.residual_models import load_residual_model
    from fdi_ros.offline import default_config
    from fdi_ros.plants import make_preprocessor

    t = [time.perf_counter()]
    blocks = bag.read_blocks(path)
    t.append(time.perf_counter())
    pre: Any = make_preprocessor(blocks[0].plant)
    feats = pre.push_many(blocks)
    t.append(time.perf_counter())
    cfg = load_graph_config(default_config(blocks[0].plant))
    models = {e.id: load_residual_model(cfg.resolve_spec(e.model), model_id=e.id)
              for e in cfg.bank}
    t.append(time.perf_counter())
    diagnose_offline(cfg, feats, models=models)
    t.append(time.perf_counter())
    names = ("read_bag", "crank_segmentation", "load_bank", "bank_symptoms_supervisor")
    return {k: round(b - a, 4) for k, a, b in zip(names, t, t[1:])}


def run(args: argparse.Namespace) -> int:
    import shutil
    import tempfile
    import time
    from pathlib import Path

    from fdi_ros.offline import diagnose_bag, diagnose_fleet, without_timing
    from fdi_ros.plants import ensure_bank
    from fdi_ros.plants.diesel.scenario import simulate_to_bag

    if args.repeat < 1 or args.duration <= 0:
        raise ValueError("--repeat must be >= 1 and --duration > 0")
    from fdi_ros.offline import default_config

    ensure_bank(default_config("diesel"), progress=False, log=lambda s: None)
    tmp = Path(tempfile.mkdtemp(prefix="fdi_bench_diagnose_"))
    try:
        path = tmp / "drive"
        simulate_to_bag(_window(args.duration, args.fault_at, 5), path)
        fast = [diagnose_bag(path) for _ in range(args.repeat)]
        best = min(fast, key=lambda r: r["wall_seconds"])
        base = _step_wise(path)
        out: dict = {
            "scenario": f"{DRIVE} 0-{args.duration:g} s, leak_ic_engine 5 mm at "
                        f"{args.fault_at:g} s",
            "segments": best["segments"], "plant_seconds": best["plant_seconds"],
            "wall_seconds": best["wall_seconds"], "realtime_factor": best["realtime_factor"],
            "stages_s": _stages(path),
            "baseline": {"path": "step-wise (general bag reader, block by block, segment by "
                                 "segment)",
                         "wall_seconds": base["wall_seconds"],
                         "realtime_factor": base["realtime_factor"]},
            "speedup": round(base["wall_seconds"] / best["wall_seconds"], 1),
            "same_result": without_timing({**best, "bag": ""}) ==
            without_timing({**base, "bag": ""}),
            "isolated_faults": best["isolated_faults"],
            "isolation_delay_s": best["isolation_delay_s"]}
        if args.fleet > 0:
            bags = []
            for i in range(args.fleet):
                p = tmp / f"fleet_{i}"
                fault = args.fleet_duration * 0.6 if i % 2 == 0 else None
                simulate_to_bag(_window(args.fleet_duration, fault, 100 + i), p)
                bags.append(str(p))
            # both layouts --repeat times, interleaved; the fastest of each (as above)
            walls: dict[int, list[float]] = {1: [], args.workers: []}
            results: dict[int, dict] = {}
            for _ in range(args.repeat):
                for w in walls:
                    t0 = time.perf_counter()
                    results[w] = diagnose_fleet(bags, workers=w)
                    walls[w].append(round(time.perf_counter() - t0, 3))
            one, many = results[1], results[args.workers]
            t1, tn = min(walls[1]), min(walls[args.workers])
            out["fleet"] = {
                "bags": args.fleet, "plant_seconds_per_bag": args.fleet_duration,
                "workers": args.workers, "wall_seconds_1_worker": t1,
                f"wall_seconds_{args.workers}_workers": tn, "runs": walls,
                "speedup": round(t1 / tn, 2),
                "same_results": all(without_timing(one[b]) == without_timing(many[b])
                                    for b in bags)}
        print(json.dumps(out, indent=1))
        return 0 if out["same_result"] else 1
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
