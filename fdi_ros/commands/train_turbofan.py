"""``fdi-ros train turbofan``: train the turbofan node models (TS fuzzy, Levenberg-Marquardt).

Simulates every node of the grid in ``config/turbofan.yaml`` (operating conditions x
deterioration x fault sizes) on 20 s of transient data and fits F1 (XNLdot) and F2 (XNHdot) per
node; writes the global model (npz, a regenerated artifact under build/) and prints the training
report (time, node count, fit errors).
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
    parser.add_argument("--json", action="store_true", help="print the report as JSON only")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def train(settings, *, out=None, seed=None, progress=True):
    """Train and save the global model of ``settings``; returns (model, path)."""
    from fdi_ros.core.turbofan.models import train_global

    gm = train_global(settings.grid, n_rules=settings.n_rules,
                      seed=settings.training_seed if seed is None else seed,
                      duration_s=settings.training_duration_s, max_nfev=settings.max_nfev,
                      progress=progress)
    path = gm.save(out or settings.model_path)
    return gm, path


def run(args: argparse.Namespace) -> int:
    from fdi_ros.core.turbofan.settings import load_settings

    settings = load_settings(args.config)
    gm, path = train(settings, out=args.out, seed=args.seed, progress=not args.no_progress)
    report = {"model": str(path), **gm.report.as_dict(), "xnl_range_rpm": gm.xnl_range}
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(f"trained {report['n_nodes']} node models ({report['n_fits']} TS systems) in "
              f"{report['seconds']:.1f} s -> {path}")
        print(f"  worst RMSE: XNLdot {report['rmse_xnldot_max']:.3f} rpm/s, "
              f"XNHdot {report['rmse_xnhdot_max']:.3f} rpm/s; mean LM evaluations "
              f"{report['nfev_mean']:.1f}")
    return 0
