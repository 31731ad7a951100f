"""``fdi-ros discrepancy``: what the model gets wrong in measured data, why, and the gain.

Loads measured data (CSV with our column names, any CSV + mapping YAML, or a bag directory),
builds the plant's baseline model (identified on fault-free data, or loaded with
``--baseline``), runs the discrepancy analysis (every catalogue effect fitted on training
blocks, scored on held-out contiguous blocks, significance-tested, ranked by held-out gain)
and writes the JSON contract; optionally a report (Markdown + PNGs) and the extended model
(JSON + ``residual_model.yaml`` for the residual-model registry).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

COMMAND = ("discrepancy",)
HELP = "find what the model gets wrong in measured data, name the cause, extend, measure the gain"

LIU_DIR_DEFAULT = "../shared/data/liu_ice"
LIU_MAPPING = "config/mappings/liu_ice.yaml"
DIESEL_CACHE = Path("build/cache/discrepancy/diesel_baseline.json")
REPO = Path(__file__).resolve().parents[2]


def _here_or_repo(path: str) -> str:
    """A relative default path: from the working directory, else from the repository root."""
    p = Path(path)
    if p.is_absolute() or p.exists():
        return str(p)
    return str(REPO / p) if (REPO / p).exists() else str(p)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="[selftest]", required=False)
    st = sub.add_parser("selftest", help="randomised self-test: hide random effects in plant "
                                         "data, analyse, report the confusion matrix",
                        description="Draw N random cases (effect from the whole catalogue, "
                                    "channel, size log-uniform over the detectable range, "
                                    "extra columns with random smooth shapes, plant run and "
                                    "window) plus null cases, hide each, analyse, and report "
                                    "the confusion matrix, channel accuracy, parameter error "
                                    "and false discoveries.")
    st.add_argument("--n", type=int, required=True, help="cases with a hidden effect")
    st.add_argument("--nulls", type=int, default=None,
                    help="null cases (nothing hidden); default N // 6, at least 1")
    st.add_argument("--seed", type=int, required=True, help="seed of the draw (replayable)")
    st.add_argument("--json", dest="selftest_json", required=True, help="output JSON file")
    st.add_argument("--only", default=None,
                    help="replay only these case indices of the draw (comma-separated)")
    st.add_argument("--quiet", dest="selftest_quiet", action="store_true")
    st.set_defaults(_run=run_selftest)
    parser.add_argument("--plant", choices=["diesel", "liu_ice"],
                        help="plant whose model is checked against the data (required)")
    parser.add_argument("--measured",
                        help="measured data: CSV (our columns, or any columns with --mapping) "
                             "or a bag directory (required)")
    parser.add_argument("--mapping", default=None,
                        help=f"mapping YAML for a CSV (liu_ice default: {LIU_MAPPING})")
    parser.add_argument("--json", help="output JSON file (required)")
    parser.add_argument("--report", default=None, help="report directory (Markdown + PNGs)")
    parser.add_argument("--save-model", default=None,
                        help="write the extended model JSON here (+ residual_model.yaml)")
    parser.add_argument("--baseline", default=None,
                        help="baseline model JSON (a saved baseline or extended model); "
                             "default: identify on fault-free data")
    parser.add_argument("--reference", default=None,
                        help="diesel: check the project's reference models (LOLIMOT tables, "
                             "a directory made by `fdi-ros identify`) instead of the "
                             "speed-density + pulsation model")
    parser.add_argument("--ident", nargs="*", default=None,
                        help="fault-free CSVs to identify the baseline on (liu_ice default: "
                             "the *_NF.csv files of the data directory)")
    parser.add_argument("--ident-fraction", type=float, default=0.6,
                        help="liu_ice: identify on this leading fraction of each file")
    parser.add_argument("--data-dir", default=LIU_DIR_DEFAULT,
                        help="liu_ice data directory (for the default identification files)")
    parser.add_argument("--window", default=None,
                        help="analyse only T0:T1 seconds of the measured data")
    parser.add_argument("--effects", default=None,
                        help="comma-separated catalogue effects to try (default: all)")
    parser.add_argument("--alpha", type=float, default=0.05,
                        help="family-wise significance level")
    parser.add_argument("--min-gain", type=float, default=2.0,
                        help="smallest held-out gain [%%] reported as a finding")
    parser.add_argument("--crank-step", type=float, default=20.0,
                        help="analyse crank-resolved data at this crank-angle spacing [deg CA] "
                             "(every k-th sample; 0 keeps all)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")


def load_baseline_file(path: Path):
    from fdi_ros.core.discrepancy.model import FORMAT, ExtendedModel, baseline_from_dict
    from fdi_ros.core.files import read_document

    d = read_document(path, "baseline model", fmt="json")
    if d.get("format") == FORMAT:
        return ExtendedModel.from_dict(d).baseline
    return baseline_from_dict(d)


def build_baseline(args, say):
    """The plant's baseline model: loaded, or identified on fault-free data."""
    from fdi_ros.core.measured import load_csv

    if args.baseline:
        return load_baseline_file(Path(args.baseline))
    if args.reference:
        if args.plant != "diesel":
            raise ValueError("--reference is for the diesel plant's reference models")
        from fdi_ros.plants.diesel.discrepancy import DieselReferenceBaseline
        from fdi_ros.plants.diesel.reference import MANIFEST

        if not (Path(args.reference) / MANIFEST).is_file():
            raise FileNotFoundError(f"no reference models in {args.reference} (missing "
                                    f"{MANIFEST}); run `fdi-ros identify` first")
        return DieselReferenceBaseline(path=str(args.reference))
    if args.plant == "liu_ice":
        from fdi_ros.plants.liu_ice.engine import LIU_ICE_FAULT_FREE, identify_liu_ice

        mapping = args.mapping or _here_or_repo(LIU_MAPPING)
        files = args.ident or [str(Path(_here_or_repo(args.data_dir)) / f)
                               for f in LIU_ICE_FAULT_FREE]
        for f in files:
            if not Path(f).is_file():
                raise FileNotFoundError(f"identification file {f} not found (give --ident or "
                                        f"--data-dir)")
        say(f"identifying the speed-density model on the first {args.ident_fraction:.0%} of "
            f"{', '.join(Path(f).name for f in files)}")
        return identify_liu_ice([load_csv(f, mapping) for f in files],
                                fraction=args.ident_fraction)
    if args.ident:
        from fdi_ros.core.measured import load_measured
        from fdi_ros.plants.diesel import discrepancy_scenarios as sc

        return sc.diesel_model_template().fit([load_measured(f, args.mapping)
                                               for f in args.ident])
    return diesel_baseline(say)


def diesel_baseline(say):
    """The diesel baseline identified on the plant's fault-free runs (cached: they take
    seconds to simulate and fit; the cache holds the model of one template, a changed
    template is identified again)."""
    from fdi_ros.core.discrepancy.model import baseline_from_dict
    from fdi_ros.plants.diesel import discrepancy_scenarios as sc

    template = sc.diesel_model_template().to_dict()
    if DIESEL_CACHE.is_file():
        cached = json.loads(DIESEL_CACHE.read_text())
        if cached.get("template") == template:
            return baseline_from_dict(cached["model"])
    say("identifying the diesel speed-density + pulsation model on 3 fault-free plant runs")
    model = sc.diesel_baseline()
    DIESEL_CACHE.parent.mkdir(parents=True, exist_ok=True)
    DIESEL_CACHE.write_text(json.dumps({"template": template, "model": model.to_dict()}))
    return model


def run_selftest(args: argparse.Namespace) -> int:
    from fdi_ros.plants.diesel.discrepancy_selftest import run_selftest as selftest

    def say(msg: str) -> None:
        if not args.selftest_quiet:
            print(msg, flush=True)

    if args.n < 0 or (args.nulls is not None and args.nulls < 0):
        raise ValueError("--n and --nulls must be >= 0")
    say(f"self-test: {args.n} random cases + nulls, seed {args.seed}")
    baseline = diesel_baseline(say)
    only = {int(x) for x in args.only.split(",")} if args.only else None
    out = selftest(args.n, args.seed, n_null=args.nulls, baseline=baseline, progress=say,
                   only=only)
    path = Path(args.selftest_json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1, default=float))
    acc = out["top1_effect_and_channel"]
    pe = out["parameter_rel_error"]
    key = "top1_or_tie"
    say(f"top-1 effect and channel right: "
        f"{'n/a' if acc is None else f'{100 * acc:.0f} %'} of {out['n_cases']}; "
        f"parameter within {100 * pe['tolerance']:.0f} %: {pe['within_tolerance']}/{pe['of']}; "
        f"false discoveries: {out['false_discoveries']}/{out['n_nulls']} nulls; "
        f"ties containing the truth: {out['ties_containing_truth']} "
        f"(top-1 or tie: {'n/a' if acc is None else f'{100 * out[key]:.0f} %'}) -> {path}")
    return 0


def run(args: argparse.Namespace) -> int:
    from fdi_ros.core.discrepancy import CATALOGUE, DiscrepancyConfig, discover
    from fdi_ros.core.measured import load_measured

    missing = [f"--{k}" for k in ("plant", "measured", "json") if not getattr(args, k)]
    if missing:
        raise ValueError(f"discrepancy needs {', '.join(missing)} (or: discrepancy selftest)")

    def say(msg: str) -> None:
        if not args.quiet:
            print(msg, flush=True)

    mapping = args.mapping or (_here_or_repo(LIU_MAPPING) if args.plant == "liu_ice" else None)
    data = load_measured(args.measured, mapping)
    if args.window:
        try:
            t0, t1 = (float(x) for x in args.window.split(":"))
        except ValueError:
            raise ValueError(f"--window must be T0:T1 in seconds, got {args.window!r}") from None
        data = data.window(t0, t1)
    if args.crank_step and data.alpha is not None:
        from fdi_ros.core.measured import decimate_crank

        data = decimate_crank(data, args.crank_step)
    effects = CATALOGUE if not args.effects else tuple(e.strip() for e in
                                                       args.effects.split(","))
    cfg = DiscrepancyConfig(alpha=args.alpha, min_gain_pct=args.min_gain, effects=effects)
    baseline = build_baseline(args, say)
    from fdi_ros.core.discrepancy.model import signals_read

    missing = [s for s in signals_read(baseline) if s not in data.signals]
    if missing:
        raise ValueError(f"{args.measured}: the {args.plant} model needs signals {missing}; "
                         f"the data has {sorted(data.signals)} (a mapping file renames columns)")
    skipped = data.skipped(list(signals_read(baseline)))
    if skipped["samples"]:
        per = ", ".join(f"{k} in {n}" for n, k in skipped["by_signal"].items())
        print(f"fdi-ros discrepancy: skipped {skipped['samples']} of {skipped['of']} samples "
              f"with missing or non-finite values ({per})", file=sys.stderr, flush=True)
    say(f"analysing {data.n_samples} samples ({data.t[-1] - data.t[0]:.1f} s) of "
        f"{data.source}")
    res, ext = discover(data, baseline, config=cfg, progress=say if not args.quiet else None)
    doc = res.to_dict()
    doc.update({"plant": args.plant, "measured": str(args.measured), "skipped": skipped,
                "baseline": baseline.to_dict()})
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1))
    say(f"{res.verdict}: {res.message}")
    for f in res.findings:
        say(f"  #{f.rank} {f.label} on {f.channel}: held-out RMSE {f.rmse_before:.4g} -> "
            f"{f.rmse_after:.4g} ({f.gain_pct:.1f} %), p_adj {f.p_adjusted:.2g}")
    if args.save_model:
        from fdi_ros.core.discrepancy.residual import write_spec

        path = ext.save(args.save_model)
        write_spec(path)
        say(f"extended model -> {path}")
    if args.report:
        from fdi_ros.core.discrepancy.report import write_report

        md = write_report(args.report, data, baseline, ext, res,
                          title=f"Discrepancy analysis: {args.plant} model vs "
                                f"{Path(args.measured).name}")
        say(f"report -> {md}")
    if not res.success:
        raise ValueError(f"{args.measured}: {res.message} (JSON written to {out})")
    return 0
