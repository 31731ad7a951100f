"""``fdi-ros train turbofan``: train the turbofan node models (TS fuzzy, Levenberg-Marquardt).

Simulates every node of the grid in ``config/turbofan.yaml`` and fits F1 (XNLdot) and F2 (XNHdot)
per node (the pipeline is :mod:`fdi_ros.plants.turbofan.train`); writes the global model (npz, a
regenerated artifact under build/) and prints the training report (time, node count, fit errors).
"""

from __future__ import annotations

import argparse
import json

COMMAND = ("train", "turbofan")
HELP = "train the turbofan Takagi-Sugeno node models by Levenberg-Marquardt (global model npz)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", default="config/turbofan.yaml",
                        help="graph/turbofan configuration (section turbofan:)")
    parser.add_argument("--out", default=None, help="model file (default: model_path of config)")
    parser.add_argument("--seed", type=int, default=None, help="training-input seed")
    parser.add_argument("--fit-widths", action="store_true",
                        help="also fit the interpolation widths by LM on off-node validation "
                             "runs (better between nodes, blurrier on them; off by default)")
    parser.add_argument("--json", action="store_true", help="print the report as JSON only")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from fdi_ros.plants.turbofan.settings import load_settings
    from fdi_ros.plants.turbofan.train import train

    settings = load_settings(args.config)
    gm, path, fit = train(settings, out=args.out, seed=args.seed,
                          progress=not args.no_progress, fit_widths=args.fit_widths)
    report = {"model": str(path), **gm.report.as_dict(), "xnl_range_rpm": gm.xnl_range,
              "width_fit": fit.as_dict() if fit else None}
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(f"trained {report['n_nodes']} node models ({report['n_fits']} TS systems) in "
              f"{report['seconds']:.1f} s -> {path}")
        print(f"  worst RMSE: XNLdot {report['rmse_xnldot_max']:.3f} rpm/s, "
              f"XNHdot {report['rmse_xnhdot_max']:.3f} rpm/s; mean LM evaluations "
              f"{report['nfev_mean']:.1f}")
        if fit:
            print(f"  interpolation widths {tuple(round(w, 3) for w in fit.x)} (from "
                  f"{fit.x0}): validation XNLdot RMS {fit.rms_before:.1f} -> "
                  f"{fit.rms_after:.1f} rpm/s")
    return 0
