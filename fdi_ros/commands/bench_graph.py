"""``fdi-ros bench graph --json``: the live graph's latency, real-time margin and cost.

Runs the diesel graph (7 residual-generator processes + plant, preprocessor, supervisor) in
real time at 3600 rpm (120 segments/s; at 3900-4000 rpm the
reference models are at the edge of their identified region) with a leak switched on and
off four times, and
measures from a watcher process:

* ``onset_to_symptom``: wall time from the arrival of the sensor block that carries a fault
  onset to the arrival of the first symptom message after it (median, p95; ms and segments);
* ``pipeline``: for every segment, symptom arrival minus arrival of the block that completed
  the segment (preprocessor + residual nodes + supervisor + three DDS hops); this is the
  baseline the onset latency is compared with: their difference is the detection delay the
  method itself needs (filtering and debouncing), not the graph;
* ``realtime_held``: the pipeline latency at the end of the run is not larger than at the start
  (no growing backlog) and every segment was diagnosed;
* CPU (percent of one core) and resident memory of every node process.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

COMMAND = ("bench", "graph")
HELP = "live graph: fault-to-symptom latency, real time at ~4000 rpm, CPU and memory per node"

ROOT = Path(__file__).resolve().parents[2]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print JSON (the default output)")
    p.add_argument("--config", default=str(ROOT / "config" / "diesel.yaml"))
    p.add_argument("--scenario",
                   default=str(ROOT / "config" / "scenarios" / "bench_graph.yaml"))


def _pct(x: list[float], q: float) -> float:
    import numpy as np

    return float(np.percentile(np.asarray(x), q)) if x else math.nan


def run(args: argparse.Namespace) -> int:
    import bisect

    import psutil

    from fdi_ros.livegraph import run_live
    from fdi_ros.plants import ensure_bank
    from fdi_ros.plants.diesel.scenario import load_scenario

    ensure_bank(args.config, progress=False, log=lambda s: None)
    sc = load_scenario(args.scenario)
    n_rpm = float(sc.n[0])
    seg_ms = 180.0 / (6.0 * n_rpm) * 1e3  # one 180 deg CA segment [ms]
    usage: dict[str, dict] = {}
    first: dict[str, tuple] = {}

    last = {"t": 0.0}

    def sample(graph, w, run):
        now = time.monotonic()
        if now - last["t"] < 1.0:  # sample the processes once a second: keep the watcher light
            return
        last["t"] = now
        for n in graph.nodes:
            if n.proc is None or n.proc.poll() is not None:
                continue
            try:
                p = psutil.Process(n.proc.pid)
                ct = p.cpu_times()
                cpu = ct.user + ct.system
                if n.name not in first and w.seen.blocks:
                    first[n.name] = (now, cpu)
                if n.name in first:
                    t0, c0 = first[n.name]
                    usage[n.name] = {"cpu_pct_of_one_core": round(100 * (cpu - c0) /
                                                                 max(now - t0, 1e-9), 1),
                                     "rss_mb": round(p.memory_info().rss / 2**20, 1)}
            except psutil.Error:
                pass

    run_, w = run_live(args.config, scenario=args.scenario, realtime_factor=1.0,
                       timeout_s=120, during=sample, watch_blocks=True)
    blocks = w.seen.blocks  # (wall arrival, plant time of the block's last sample)
    b_t = [t for _, t in blocks]
    b_wall = [wall for wall, _ in blocks]

    def block_arrival(t_plant: float) -> float:
        i = bisect.bisect_left(b_t, t_plant - 1e-9)
        return b_wall[i] if i < len(b_wall) else math.nan

    pipe = []
    for wall, m in w.seen.symptoms:
        a = block_arrival(float(m.t_s))
        if not math.isnan(a):
            pipe.append((float(m.t_s), 1e3 * (wall - a)))
    onsets = [sc_f.t for sc_f in sc.faults if sc_f.active]
    onset_lat, onset_segments = [], []
    for t_on in onsets:
        a = block_arrival(t_on)
        hit = next(((wall, m) for wall, m in w.seen.symptoms
                    if m.t_s >= t_on and m.valid and any(int(v) for v in m.levels)), None)
        if hit is None or math.isnan(a):
            continue
        onset_lat.append(1e3 * (hit[0] - a))
        onset_segments.append((hit[1].t_s - t_on) * 1e3 / seg_ms)
    lat = [x for _, x in pipe]
    q = max(len(lat) // 4, 1)
    early, late = _pct(lat[:q], 50), _pct(lat[-q:], 50)
    expected = int(round(sc.duration_s * 1e3 / seg_ms))
    out = {
        "scenario": Path(args.scenario).name, "engine_speed_rpm": n_rpm,
        "segment_ms": round(seg_ms, 3), "model_nodes": len(run_.lifecycle_after) or 7,
        "onset_to_symptom": {
            "n_faults": len(onset_lat),
            "median_ms": round(_pct(onset_lat, 50), 2), "p95_ms": round(_pct(onset_lat, 95), 2),
            "median_segments": round(_pct(onset_lat, 50) / seg_ms, 2),
            "p95_segments": round(_pct(onset_lat, 95) / seg_ms, 2),
            "detection_delay_segments_plant_time": [round(x, 2) for x in onset_segments]},
        "pipeline": {"n": len(lat), "median_ms": round(_pct(lat, 50), 2),
                     "p95_ms": round(_pct(lat, 95), 2),
                     "median_segments": round(_pct(lat, 50) / seg_ms, 2),
                     "p95_segments": round(_pct(lat, 95) / seg_ms, 2)},
        "ratio_onset_to_pipeline_median": round(_pct(onset_lat, 50) / _pct(lat, 50), 2)
        if lat and onset_lat else None,
        "realtime_held": bool(lat) and run_.segments >= expected - 2 and late <= 2 * early + 5,
        "segments_diagnosed": run_.segments, "segments_expected": expected,
        "pipeline_median_ms_first_quarter": round(early, 2),
        "pipeline_median_ms_last_quarter": round(late, 2),
        "wall_s": round(run_.wall_s, 2),
        "nodes": usage,
        "cpu_pct_total": round(sum(u["cpu_pct_of_one_core"] for u in usage.values()), 1),
    }
    print(json.dumps(out, indent=2))
    return 0
