"""``fdi-ros reproduce turbofan``: Diao & Passino (2004), section 4, in our simulator.

Runs the paper's four cases (no fault; small fan fault; small hub fault at 5 s growing to
large at 15 s; medium fan fault then medium hub fault at 10 s) through the 16-model bank and
the expert supervisor, prints detection and isolation times next to the paper's, checks >= 50
fault-free runs with random manufacturing variation and deterioration for false isolations,
sweeps the hold time T0 (false isolations vs isolation delay) and saves figures like the
paper's Figs. 4-7. Trains the models first if the model file is missing.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

HELP = "reproduce the turbofan fault diagnosis of Diao & Passino (2004): 4 cases, T0 sweep"

PAPER_MEAN_DELAY_S = (2.44 + (7.38 - 5.0) + (17.04 - 15.0) + 2.34 + (12.12 - 10.0)) / 5


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", default="config/turbofan.yaml",
                        help="graph/turbofan configuration (section turbofan:)")
    parser.add_argument("--model", default=None, help="global model file (default from config)")
    parser.add_argument("--figures", default="out/turbofan", help="directory for PNG figures "
                        "('none' to skip)")
    parser.add_argument("--t0", type=float, default=None, help="hold time T0 [s] (default "
                        "from config, the paper's 1.2 s)")
    parser.add_argument("--xnh-weight", type=float, default=None,
                        help="weight of the XNH residual in the norm (0 = paper: XN2 only)")
    parser.add_argument("--runs", type=int, default=None, help="fault-free runs (default 50)")
    parser.add_argument("--no-sweep", action="store_true", help="skip the T0 sweep")
    parser.add_argument("--seeds", type=int, default=10,
                        help="repeat the four cases with this many other noise seeds (0: no)")
    parser.add_argument("--retrain", action="store_true", help="train the models again first")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def _delays(results) -> list[float]:
    out = []
    for res in results:
        for ev in res.summary()["events"]:
            d = ev["isolation_delay_s"]
            out.append(math.inf if d is None else d)
    return out


def run(args: argparse.Namespace) -> int:
    import time

    import numpy as np

    from fdi_ros.plants.turbofan import bank as tfb
    from fdi_ros.plants.turbofan.models import GlobalModel
    from fdi_ros.plants.turbofan.settings import load_scenario, load_settings

    settings = load_settings(args.config)
    t0_s = settings.t0_s if args.t0 is None else args.t0
    w = settings.xnh_weight if args.xnh_weight is None else args.xnh_weight
    if t0_s < 0 or w < 0:
        raise ValueError("--t0 and --xnh-weight must be >= 0")
    n_runs = settings.fault_free_runs if args.runs is None else args.runs
    if n_runs < 1:
        raise ValueError("--runs must be >= 1")
    model_path = Path(args.model or settings.model_path)
    report: dict = {"t0_s": t0_s, "xnh_weight": w, "model": str(model_path)}
    from fdi_ros.plants.turbofan.plant import plant_signature

    stale = False
    if model_path.exists() and not args.retrain:
        try:
            gm = GlobalModel.load(model_path)
            stale = gm.signature != plant_signature() or not gm.same_structure(settings.grid)
            why = "trained on another plant version or grid"
        except ValueError as exc:
            stale, why = True, str(exc)
        if stale:
            print(f"{model_path}: {why}; training again", file=sys.stderr)
    if args.retrain or stale or not model_path.exists():
        from fdi_ros.plants.turbofan.train import train

        gm, _, _ = train(settings, out=model_path, progress=not args.no_progress)
        report["training"] = gm.report.as_dict()
    else:
        report["training"] = gm.report.as_dict() if gm.report else None
    scenarios = [load_scenario(p, settings) for p in settings.scenarios]
    if not scenarios:
        raise ValueError(f"{args.config}: no scenarios listed under turbofan.scenarios")

    clock = time.perf_counter()
    sims = {sc.name: tfb.simulate_plant(sc) for sc in scenarios}
    results = [tfb.run_scenario(gm, sc, t0_s=t0_s, xnh_weight=w, sim=sims[sc.name])
               for sc in scenarios]
    report["cases"] = [_with_paper(r.summary()) for r in results]
    if w > 0:
        # the paper's residual (XN2 only), for comparison
        paper_out = [tfb.run_scenario(gm, sc, t0_s=t0_s, xnh_weight=0.0, sim=sims[sc.name])
                     for sc in scenarios]
        report["xn2_only"] = [{"case": r.scenario.name, "events": [
            {k: ev[k] for k in ("true_situation", "detected_s", "isolated_s", "isolated_model",
                                "wrong_isolations")} for ev in r.summary()["events"]],
            "fault_index_ever_wrong": r.summary()["fault_index_ever_wrong"]}
            for r in paper_out]

    if args.seeds < 0:
        raise ValueError("--seeds must be >= 0")
    if args.seeds:
        import dataclasses

        wrong, delays, n_events = 0, [], 0
        for seed in range(1, args.seeds + 1):
            for sc in scenarios:
                summ = tfb.run_scenario(gm, dataclasses.replace(sc, seed=sc.seed + seed),
                                        t0_s=t0_s, xnh_weight=w).summary()
                wrong += len(summ["false_isolations"])
                for ev in summ["events"]:
                    n_events += 1
                    delays.append(math.inf if ev["isolation_delay_s"] is None
                                  else ev["isolation_delay_s"])
        report["other_noise_seeds"] = {
            "seeds": args.seeds, "fault_events": n_events, "wrong_isolations": wrong,
            "not_isolated": int(sum(not math.isfinite(d) for d in delays)),
            "mean_isolation_delay_s": round(float(np.mean(delays)), 3),
            "max_isolation_delay_s": round(float(np.max(delays)), 3)}

    ff = tfb.fault_free_batch(gm, n_runs=n_runs, seed=settings.fault_free_seed,
                              condition=settings.condition,
                              deterioration_range=settings.fault_free_deterioration,
                              manufacturing_sigma=settings.fault_free_manufacturing_sigma,
                              xnh_weight=w)
    hold = tfb.longest_wrong_hold(ff["res"], ts=0.02)
    # the same runs with twice the manufacturing spread: where the method's robustness ends
    wide = tfb.fault_free_batch(gm, n_runs=n_runs, seed=settings.fault_free_seed,
                                condition=settings.condition,
                                deterioration_range=settings.fault_free_deterioration,
                                manufacturing_sigma=2 * settings.fault_free_manufacturing_sigma,
                                xnh_weight=w)
    hold_wide = tfb.longest_wrong_hold(wide["res"], ts=0.02)
    report["fault_free"] = {
        "runs": n_runs, "seed": settings.fault_free_seed,
        "false_isolations": int(np.sum(hold >= t0_s - 1e-9)),
        "longest_wrong_minimum_s": round(float(hold.max()), 2),
        "max_nominal_residual_after_2s_rpm": round(float(ff["res"][:, 0, 100:].max()), 2),
        "deterioration_range": list(settings.fault_free_deterioration),
        "manufacturing_sigma": settings.fault_free_manufacturing_sigma,
        "false_isolations_at_twice_the_manufacturing_sigma": int(np.sum(hold_wide >= t0_s - 1e-9))}

    if not args.no_sweep:
        sweep = []
        for t0 in sorted(set(settings.t0_sweep) | {t0_s}):
            res_t = [tfb.run_scenario(gm, sc, t0_s=t0, xnh_weight=w, sim=sims[sc.name])
                     for sc in scenarios]
            delays = _delays(res_t)
            wrong = sum(len(ev["wrong_isolations"]) for r in res_t
                        for ev in r.summary()["events"])
            wrong += sum(bool(r.summary()["false_isolations"]) and not r.scenario.events
                         for r in res_t)
            sweep.append({"t0_s": t0, "fault_free_false_isolations":
                          int(np.sum(hold >= t0 - 1e-9)),
                          "fault_free_false_isolations_twice_sigma":
                          int(np.sum(hold_wide >= t0 - 1e-9)),
                          "wrong_isolations_in_cases": int(wrong),
                          "mean_isolation_delay_s": round(float(np.mean(delays)), 3),
                          "max_isolation_delay_s": round(float(np.max(delays)), 3)})
        report["t0_sweep"] = sweep
        ok = [s for s in sweep if s["fault_free_false_isolations"] == 0
              and s["wrong_isolations_in_cases"] == 0
              and math.isfinite(s["max_isolation_delay_s"])]
        best = min(ok, key=lambda s: s["mean_isolation_delay_s"]) if ok else None
        report["goal"] = {
            "paper_mean_isolation_delay_s": round(PAPER_MEAN_DELAY_S, 3),
            "best_t0_s": best["t0_s"] if best else None,
            "best_mean_isolation_delay_s": best["mean_isolation_delay_s"] if best else None,
            "faster_than_paper_at_zero_false_isolations":
                bool(best and best["mean_isolation_delay_s"] < PAPER_MEAN_DELAY_S)}
    report["run_seconds"] = round(time.perf_counter() - clock, 2)

    if args.figures != "none":
        from fdi_ros.plants.turbofan.figures import case_figure, sweep_figure

        out = Path(args.figures)
        out.mkdir(parents=True, exist_ok=True)
        report["figures"] = [str(case_figure(r, out / f"turbofan_{r.scenario.name}.png",
                                             xnh_weight=w)) for r in results]
        if "t0_sweep" in report:
            report["figures"].append(str(sweep_figure(report["t0_sweep"],
                                                      out / "turbofan_t0_sweep.png",
                                                      paper_delay=PAPER_MEAN_DELAY_S)))

    if args.json:
        print(json.dumps(report, indent=2))
    else:
        _print_text(report)
    return 0


def _with_paper(summary: dict) -> dict:
    """Put the paper's detection/isolation time next to ours in every event."""
    paper = summary["paper"]
    for i, ev in enumerate(summary["events"]):
        for key in ("detected_s", "isolated_s"):
            vals = paper.get(key) or []
            ev[f"paper_{key}"] = vals[i] if i < len(vals) else None
    return summary


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.2f}"


def _print_text(report: dict) -> None:
    print(f"T0 = {report['t0_s']} s, XNH weight {report['xnh_weight']}")
    for case in report["cases"]:
        print(f"case {case['case']}: F* ever wrong: {case['fault_index_ever_wrong']}; final "
              f"{case['final_fault_model']}")
        for ev in case["events"]:
            pd, pi = ev["paper_detected_s"], ev["paper_isolated_s"]
            print(f"  fault at {ev['fault_at_s']:5.2f} s -> {ev['true_situation']:>22}: "
                  f"detected {_fmt(ev['detected_s'])} s (paper {_fmt(pd)}), isolated "
                  f"{_fmt(ev['isolated_s'])} s (paper {_fmt(pi)}) as {ev['isolated_model']}")
    ff = report["fault_free"]
    print(f"fault-free runs: {ff['runs']}, false isolations {ff['false_isolations']}, longest "
          f"wrong minimum {ff['longest_wrong_minimum_s']} s (twice the manufacturing spread: "
          f"{ff['false_isolations_at_twice_the_manufacturing_sigma']} false isolations)")
    for case in report.get("xn2_only", []):
        isos = [f"{ev['true_situation']} isolated at {_fmt(ev['isolated_s'])} s, wrong "
                f"{ev['wrong_isolations'] or 'none'}" for ev in case["events"]]
        print(f"  paper's XN2-only residual, case {case['case']}: F* ever wrong "
              f"{case['fault_index_ever_wrong']}; {'; '.join(isos)}")
    if "other_noise_seeds" in report:
        o = report["other_noise_seeds"]
        print(f"cases with {o['seeds']} other noise seeds: {o['wrong_isolations']} wrong "
              f"isolations, {o['not_isolated']} of {o['fault_events']} faults not isolated, "
              f"mean isolation delay {o['mean_isolation_delay_s']} s (max "
              f"{o['max_isolation_delay_s']} s)")
    if "goal" in report:
        g = report["goal"]
        print(f"T0 sweep: best T0 {g['best_t0_s']} s, mean isolation delay "
              f"{g['best_mean_isolation_delay_s']} s vs paper {g['paper_mean_isolation_delay_s']}"
              f" s; faster at zero false isolations: "
              f"{g['faster_than_paper_at_zero_false_isolations']}")
    for f in report.get("figures", []):
        print(f"figure: {f}")
