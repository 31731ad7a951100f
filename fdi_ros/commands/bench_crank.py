"""``fdi-ros bench crank``: throughput of the crank-synchronous front end.

Synthetic MAF and p2 signals at 6000 rpm, 1 deg CA sampling (36 000 samples/s of engine
time per channel), two channels. Measured in the same run:

* ``samples_per_s`` / ``segments_per_s``: the vectorised fit (:func:`crank_harmonics`) on one
  long record; ``realtime_factor_6000rpm`` = engine seconds processed per wall second.
* ``baseline_*``: a straightforward per-segment loop (trapezoid Fourier integrals per 180 deg
  CA segment, the textbook way) on the same data; ``speedup_vs_baseline`` is the ratio.
* ``streaming_*``: :class:`CrankSegmenter` fed 720 deg CA blocks with the four channels a
  diesel block needs, producing FeatureVector objects (what a ROS node does per message).
"""

from __future__ import annotations

import argparse
import json

COMMAND = ("bench", "crank")
HELP = "throughput of the crank-synchronous front end at 6000 rpm (JSON figures)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--seconds", type=float, default=60.0,
                        help="engine time to process [s] (default 60)")
    parser.add_argument("--repeat", type=int, default=5, help="best of N runs (default 5)")


def _baseline(alpha, x, D=180.0):
    import numpy as np
    out = []
    for j in range(int(alpha[0] // D), int(alpha[-1] // D)):
        lo = int(np.searchsorted(alpha, j * D))
        hi = int(np.searchsorted(alpha, (j + 1) * D, side="right"))
        a, seg = alpha[lo:hi], x[:, lo:hi]
        th = 2.0 * np.pi * a / D
        mean = np.trapezoid(seg, a, axis=1) / D
        c = 2.0 * np.trapezoid(seg * np.cos(th), a, axis=1) / D
        s = 2.0 * np.trapezoid(seg * np.sin(th), a, axis=1) / D
        out.append((mean, np.hypot(c, s), np.arctan2(-s, c)))
    return out


def run(args: argparse.Namespace) -> int:
    import time

    import numpy as np

    from fdi_ros.core.crank import crank_harmonics
    from fdi_ros.core.types import SampleBlock
    from fdi_ros.plants.diesel.wing import DieselPreprocessor

    if not args.seconds > 0 or args.repeat < 1:
        raise ValueError("--seconds must be > 0 and --repeat >= 1")
    n_rpm = 6000.0
    rate = 6.0 * n_rpm                                   # deg CA per second
    N = int(args.seconds * rate) + 1
    rng = np.random.default_rng(0)
    alpha = np.arange(N, dtype=float)
    t = alpha / rate
    th = 2.0 * np.pi * alpha / 180.0
    maf = 300.0 + 20.0 * np.cos(th + 0.4) + 3.0 * np.cos(2 * th) + rng.normal(0, 1.0, N)
    p2 = 1.8e5 + 4e3 * np.cos(th - 0.3) + rng.normal(0, 100.0, N)
    X = np.vstack([maf, p2])

    def best(fn):
        times = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            res = fn()
            times.append(time.perf_counter() - t0)
        return min(times), res

    dt_fast, (h, _) = best(lambda: crank_harmonics(alpha, t, X, segment_deg=180.0))
    n_seg = int(h.index.size)
    # baseline on a slice (it is slow); per-segment cost scales linearly
    n_base = min(N, int(rate * min(args.seconds, 5.0)) + 1)
    dt_base, ref = best(lambda: _baseline(alpha[:n_base], X[:, :n_base]))
    base_seg_per_s = len(ref) / dt_base
    # agreement of the two on the common segments (a correctness check of the bench itself)
    k = min(len(ref), n_seg)
    amp_fast = h.amplitude(1)[:, :k]
    amp_ref = np.array([r[1] for r in ref[:k]]).T
    max_diff = float(np.max(np.abs(amp_fast - amp_ref)))

    # streaming: 720 deg CA blocks, four channels, FeatureVector objects
    n_stream = min(N, int(rate * min(args.seconds, 10.0)))
    n_stream -= n_stream % 720
    vals = np.vstack([np.full(N, n_rpm), p2, np.full(N, 330.0), maf])[:, :n_stream]

    def stream():
        seg = DieselPreprocessor().seg  # the engine's displacement and gas constant
        count = 0
        for i in range(0, n_stream, 720):
            b = SampleBlock(plant="diesel", index=i // 720, t=t[i:i + 720],
                            alpha=alpha[i:i + 720], channels=("n", "p2", "T2", "maf"),
                            units=("rpm", "Pa", "K", "kg/h"), values=vals[:, i:i + 720])
            count += len(seg.push(b))
        return count

    dt_stream, n_stream_seg = best(stream)
    out = {
        "n_rpm": n_rpm, "dalpha_deg": 1.0, "channels": 2, "engine_seconds": args.seconds,
        "samples": N, "segments": n_seg,
        "samples_per_s": N / dt_fast,
        "segments_per_s": n_seg / dt_fast,
        "realtime_factor_6000rpm": args.seconds / dt_fast,
        "baseline_segments_per_s": base_seg_per_s,
        "baseline_realtime_factor_6000rpm": base_seg_per_s / (rate / 180.0),
        "speedup_vs_baseline": (n_seg / dt_fast) / base_seg_per_s,
        "max_amp_diff_vs_baseline": max_diff,
        "streaming_block_deg": 720, "streaming_channels": 4,
        "streaming_segments_per_s": n_stream_seg / dt_stream,
        "streaming_realtime_factor_6000rpm": (n_stream / rate) / dt_stream,
        "goal_realtime_factor": 1000.0,
    }
    if args.json:
        print(json.dumps(out))
    else:
        for k2, v in out.items():
            print(f"{k2:36s} {v:.6g}" if isinstance(v, float) else f"{k2:36s} {v}")
    return 0
