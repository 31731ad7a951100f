"""``fdi-ros identify``: identify the diesel reference models (LOLIMOT + ECU tables).

Data: a scenario YAML (simulated with the diesel plant), a bag (features, or sensor blocks that
are segmented here) or a CSV (+ mapping). Writes the model set (npz + table JSON + manifest),
fault-free thresholds (when a fault-free driving scenario is given) and figures like the
paper's Figs. 5, 7-10.
"""

from __future__ import annotations

import argparse
import json

COMMAND = ("identify",)
HELP = "identify the diesel reference models (LOLIMOT, look-up tables) from a bag, CSV or scenario"

def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--plant", default="diesel", choices=["diesel"],
                        help="plant configuration (only the diesel plant has these models)")
    parser.add_argument("--data", default=None, action="append",
                        help="identification data: scenario YAML, bag directory or CSV; "
                             "repeat for several streams (default: the bank's identification "
                             "cycle and ECU-run part-load passes)")
    parser.add_argument("--mapping", default=None, help="mapping YAML for a CSV")
    parser.add_argument("--fault-free", default=None, action="append",
                        help="fault-free transient data for the thresholds (scenario, bag or "
                             "CSV; repeat for several; 'none' to skip; default: the bank's two "
                             "fault-free drives)")
    parser.add_argument("--regimes", action="store_true",
                        help="also identify maps of the EGR-open regimes the data hold "
                             "(experimental: see the README's coverage section)")
    parser.add_argument("--out", default="build/models/diesel", help="output model directory")
    parser.add_argument("--figures", default=None, help="directory for PNG figures")
    parser.add_argument("--seed", type=int, default=0, help="simulation/split seed")
    parser.add_argument("--threshold-seed", type=int, default=101,
                        help="seed of the fault-free threshold simulation")
    parser.add_argument("--max-models", type=int, default=None, help="LOLIMOT max_models")
    parser.add_argument("--lut-n", default=None,
                        help="table breakpoints in rpm, comma separated (default 17 points)")
    parser.add_argument("--lut-rho2", default=None,
                        help="table breakpoints in kg/m^3, comma separated (default 13 points)")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def _floats(text: str | None) -> tuple[float, ...]:
    if not text:
        return ()
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        raise ValueError(f"breakpoints must be comma-separated numbers, got {text!r}") from None


def run(args: argparse.Namespace) -> int:
    from fdi_ros.plants.diesel.identify import (
        REFERENCE_SOURCES,
        THRESHOLD_SOURCES,
        build_models,
    )
    from fdi_ros.plants.diesel.reference import IdentificationConfig

    kw = {}
    if args.max_models is not None:
        kw["max_models"] = args.max_models
    cfg = IdentificationConfig(seed=args.seed, lut_n=_floats(args.lut_n),
                               lut_rho2=_floats(args.lut_rho2), **kw)
    data = list(REFERENCE_SOURCES) if args.data is None else args.data
    fault_free = list(THRESHOLD_SOURCES) if args.fault_free is None else args.fault_free
    res, _, report = build_models(data, out=args.out, seed=args.seed,
                                  fault_free=fault_free, threshold_seed=args.threshold_seed,
                                  mapping=args.mapping, config=cfg,
                                  progress=not args.no_progress, figures=args.figures,
                                  further_regimes=args.regimes)
    if args.json:
        print(json.dumps(report, indent=1))
    else:
        print(f"identified {len(res.nrmse_test)} reference models ({len(res.results)} LOLIMOT "
              f"maps) from {report['n_segments']} segments "
              f"in {res.train_s:.2f} s -> {report['out']}")
        for k, v in report["models"].items():
            nm = "+".join(str(x) for x in v["n_models"].values())
            print(f"  {k:10s} models={nm:5s}  held-out NRMSE={v['nrmse_test']:.4f}"
                  f"  (table {v['nrmse_test_lut']:.4f})")
    return 0
