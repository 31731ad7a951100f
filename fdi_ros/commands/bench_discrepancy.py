"""``fdi-ros bench discrepancy``: analysis time for 10 minutes of measured data.

Data: the LiU-ICE test-bench windows (real 20 Hz data) laid end to end until the requested
duration is reached (the joins are gaps: separate segments), or the diesel plant (crank-angle
resolved, 20 deg CA) with ``--plant diesel``. Baseline measured in the same run: fitting every
candidate extension once on all samples (what an in-sample ranking would cost); the ratio says
what the honest held-out evaluation (one refit per block, tests) costs on top.
"""

from __future__ import annotations

import argparse
import json

COMMAND = ("bench", "discrepancy")
HELP = "discrepancy analysis time for 10 minutes of measured data, vs an in-sample ranking"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--plant", default="liu_ice", choices=["liu_ice", "diesel"])
    parser.add_argument("--minutes", type=float, default=10.0, help="measured data duration")
    parser.add_argument("--data-dir", default="../shared/data/liu_ice",
                        help="LiU-ICE data directory")
    parser.add_argument("--repeat", type=int, default=1,
                        help="repetitions; the fastest time is reported")
    parser.add_argument("--json", action="store_true", help="print JSON")


def _liu_record(data_dir: str, minutes: float):
    from pathlib import Path

    import numpy as np

    from fdi_ros.commands.discrepancy import LIU_MAPPING, _here_or_repo
    from fdi_ros.core.measured import Measured, load_csv, segments_from_gaps
    from fdi_ros.plants.liu_ice.engine import LIU_ICE_FAULT_FREE, identify_liu_ice

    mapping = _here_or_repo(LIU_MAPPING)
    d = Path(_here_or_repo(data_dir))
    names = sorted(p.name for p in d.glob("*.csv"))
    if not names:
        raise FileNotFoundError(f"no LiU-ICE CSV files in {d}")
    recs = [load_csv(d / n, mapping) for n in names]
    model = identify_liu_ice([load_csv(d / n, mapping) for n in LIU_ICE_FAULT_FREE])
    ts: list[np.ndarray] = []
    sigs: list[dict[str, np.ndarray]] = []
    t_end = 0.0
    k = 0
    while t_end < 60.0 * minutes:
        r = recs[k % len(recs)]
        t = r.t - r.t[0] + t_end + (1.0 if ts else 0.0)
        keep = t < 60.0 * minutes
        ts.append(t[keep])
        sigs.append({n: v[keep] for n, v in r.signals.items()})
        t_end = float(t[keep][-1]) if keep.any() else 60.0 * minutes
        k += 1
    t = np.concatenate(ts)
    sig = {n: np.concatenate([s[n] for s in sigs]) for n in sigs[0]}
    data = Measured(t=t, signals=sig, units=dict(recs[0].units),
                    segment=segments_from_gaps(t, 0.2), source="LiU-ICE windows end to end",
                    mapped=recs[0].mapped)
    return data, model


def run(args: argparse.Namespace) -> int:
    import time

    import numpy as np

    from fdi_ros.core.discrepancy import build_contexts, discover
    from fdi_ros.core.discrepancy.effects import candidates
    from fdi_ros.core.measured import segment_means

    if not args.minutes > 0 or args.repeat < 1:
        raise ValueError("--minutes must be > 0 and --repeat >= 1")
    if args.plant == "liu_ice":
        data, model = _liu_record(args.data_dir, args.minutes)
    else:
        from fdi_ros.plants.diesel import discrepancy_scenarios as sc

        model = sc.diesel_baseline()
        data = sc.plant_record(7, duration_s=60.0 * args.minutes)
    best = np.inf
    for _ in range(max(args.repeat, 1)):
        t0 = time.perf_counter()
        res, _ = discover(data, model)
        best = min(best, time.perf_counter() - t0)
    # baseline: every candidate fitted once on all samples, no held-out blocks, no tests
    view = segment_means(data) if data.alpha is not None else data
    base_model = model.without_pulsation() if data.alpha is not None else model
    t0 = time.perf_counter()
    for ctx in build_contexts(view, base_model).values():
        ok = ctx.ok
        for eff in candidates(ctx):
            eff.apply(ctx, ctx.yhat, eff.fit(ctx, ctx.yhat, ok))
    base_s = time.perf_counter() - t0
    dur = float(data.t[-1] - data.t[0])
    doc = {"bench": "discrepancy", "plant": args.plant, "data": data.source,
           "minutes": dur / 60.0, "samples": data.n_samples, "analysis_s": best,
           "realtime_factor": dur / best, "verdict": res.verdict,
           "findings": [f.label for f in res.findings],
           "baseline": {"what": "every candidate fitted once in-sample (no held-out blocks, "
                                "no tests)", "seconds": base_s},
           "ratio_to_baseline": best / base_s if base_s > 0 else None}
    if args.json:
        print(json.dumps(doc, indent=1))
    else:
        for k, v in doc.items():
            print(f"{k}: {v}")
    return 0
