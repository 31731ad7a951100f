"""``fdi-ros diagnose <bag> --json``: the graph's diagnosis, offline, many times real time."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

COMMAND = ("diagnose",)
HELP = "diagnose a bag offline with the same core as the live graph (JSON summary out)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("bag", help="rosbag2 directory with /fdi/sensor_block (or /fdi/features)")
    p.add_argument("--config", help="graph configuration (default: config/<plant>.yaml)")
    p.add_argument("--json", metavar="FILE", nargs="?", const="-",
                   help="write the JSON summary to FILE (default: stdout)")
    p.add_argument("--progress", action="store_true", help="show a progress bar")


def default_config(plant: str) -> Path:
    root = Path(__file__).resolve().parents[2]
    return root / "config" / f"{plant}.yaml"


def features_of_bag(path: str | Path) -> tuple[str, list]:
    """(plant, feature vectors) of a bag: recomputed from the sensor blocks when present."""
    from fdi_ros import bag
    from fdi_ros.plants import make_preprocessor

    tops = bag.topics(path)
    if "/fdi/sensor_block" in tops:
        blocks = bag.read_blocks(path)
        if not blocks:
            raise ValueError(f"{path}: /fdi/sensor_block is empty")
        pre = make_preprocessor(blocks[0].plant)
        feats, last = [], None
        for b in blocks:
            if last is not None and b.index != last + 1:
                pre.mark_gap()
            last = b.index
            feats.extend(pre.push(b))
        return blocks[0].plant, feats
    if "/fdi/features" in tops:
        feats = bag.read_features(path)
        if not feats:
            raise ValueError(f"{path}: /fdi/features is empty")
        return feats[0].plant, feats
    raise ValueError(f"{path}: neither /fdi/sensor_block nor /fdi/features in the bag "
                     f"(topics: {sorted(tops)})")


def valid_diagnosis(step) -> bool:
    """The segment got a valid diagnosis: the reference model's symptoms were valid there (or,
    without a symptom stage, the supervisor had enough valid residuals)."""
    if step.symptoms is not None:
        return bool(step.symptoms.valid)
    return bool(step.diagnosis.state != "not_valid")


def summarise(steps: list, plant_seconds: float, wall_seconds: float, truth: list) -> dict:
    from fdi_ros.core.events import diagnosis_events

    events = diagnosis_events(step.diagnosis for _fv, _res, step in steps)
    first_symptom: dict[str, float] = {}
    for _fv, _res, step in steps:
        d = step.diagnosis
        s = step.symptoms
        if s is not None and s.valid:
            for name, lvl in zip(s.names, s.levels):
                if lvl and name not in first_symptom:
                    first_symptom[name] = round(d.t, 4)
    final = steps[-1][2].diagnosis if steps else None
    onset = min((e.t for e in truth if e.active and e.fault), default=math.nan)
    # Detection episodes: a detection either ends in an isolation (confirmed), is still open
    # at the end, or falls back to "no fault" (cleared: a transient the hold time T0 rejected).
    episodes: list[dict] = []
    for fv, _res, step in steps:
        st = step.diagnosis.state
        if st == "detected" and (not episodes or episodes[-1]["end"] is not None):
            episodes.append({"t": round(fv.t_end, 4), "end": None})
        elif episodes and episodes[-1]["end"] is None and st in ("isolated", "no_fault"):
            episodes[-1]["end"] = "isolated" if st == "isolated" else "cleared"
    kept = [e for e in episodes if e["end"] != "cleared"]
    det = kept[0]["t"] if kept else (final.detection_time if final and final.state == "isolated"
                                      else math.nan)

    def delay(t: float) -> float | None:
        return None if math.isnan(t) or math.isnan(onset) else round(t - onset, 4)

    iso = final.isolation_time if final else math.nan
    n_valid = sum(1 for _fv, _res, step in steps if valid_diagnosis(step))
    return {
        "segments": len(steps),
        "plant_seconds": round(plant_seconds, 3),
        "wall_seconds": round(wall_seconds, 3),
        "realtime_factor": round(plant_seconds / wall_seconds, 1) if wall_seconds > 0 else None,
        "fault_truth": [{"t": e.t, "fault": e.fault, "size": e.size, "unit": e.size_unit}
                        for e in truth],
        "detected": not math.isnan(det),
        "cleared_detections_s": [e["t"] for e in episodes if e["end"] == "cleared"],
        "detection_time_s": None if math.isnan(det) else round(det, 4),
        "detection_delay_s": delay(det),
        "isolated_faults": list(final.isolated_faults) if final else [],
        "fault_model": final.fault_model if final else "",
        "isolation_time_s": None if not final or math.isnan(iso) else round(iso, 4),
        "isolation_delay_s": delay(iso),
        "first_symptom_s": first_symptom,
        "models_online": list(final.models_online) if final else [],
        "invalid_segments": sum(1 for fv, _, _ in steps if not fv.valid),
        "valid_segments": n_valid,
        "coverage": round(n_valid / len(steps), 4) if steps else None,
        "events": events,
    }


def run(args: argparse.Namespace) -> int:
    from fdi_ros import bag
    from fdi_ros.core.diagnoser import diagnose_offline
    from fdi_ros.core.graphconfig import load_graph_config

    t0 = time.perf_counter()
    plant, feats = features_of_bag(args.bag)
    cfg = load_graph_config(args.config or default_config(plant))
    steps = diagnose_offline(cfg, feats, progress=args.progress)
    wall = time.perf_counter() - t0
    truth = bag.read_faults(args.bag) if "/fdi/fault_truth" in bag.topics(args.bag) else []
    span = (feats[-1].t_end - feats[0].t_start) if feats else 0.0
    out = {"bag": str(args.bag), "plant": plant, "config": str(cfg.path),
           **summarise(steps, span, wall, truth)}
    text = json.dumps(out, indent=2)
    if args.json in (None, "-"):
        print(text)
    else:
        Path(args.json).write_text(text + "\n")
        print(f"diagnosis written to {args.json}", file=sys.stderr)
    return 0
