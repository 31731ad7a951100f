"""``fdi-ros bench lolimot``: LOLIMOT against an off-the-shelf regressor on the same data.

Both learn the five diesel reference models from the same identification-cycle segments (same
contiguous-block split; the peer gets train + validation blocks, LOLIMOT uses the validation
blocks to choose its number of models) and are scored on the same held-out blocks.
"""

from __future__ import annotations

import argparse
import json

COMMAND = ("bench", "lolimot")
HELP = "LOLIMOT vs scikit-learn (gradient boosting / MLP): held-out NRMSE and training time"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from fdi_ros.plants.diesel.identify import DEFAULT_IDENT

    parser.add_argument("--data", default=DEFAULT_IDENT,
                        help=f"identification data: scenario, bag or CSV "
                             f"(default {DEFAULT_IDENT})")
    parser.add_argument("--mapping", default=None, help="mapping YAML for a CSV")
    parser.add_argument("--peer", default="hgb", choices=["hgb", "mlp"],
                        help="hgb: HistGradientBoostingRegressor; mlp: MLPRegressor")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeat", type=int, default=3,
                        help="training repetitions; the fastest time is reported")
    parser.add_argument("--json", action="store_true", help="print JSON")


def _peer(kind: str, seed: int):
    if kind == "hgb":
        from sklearn.ensemble import HistGradientBoostingRegressor

        return HistGradientBoostingRegressor(random_state=seed)
    from sklearn.neural_network import MLPRegressor
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    return make_pipeline(StandardScaler(),
                         MLPRegressor(hidden_layer_sizes=(32, 32), max_iter=500,
                                      early_stopping=True, random_state=seed))


def run(args: argparse.Namespace) -> int:
    import time

    import numpy as np

    from fdi_ros.core.lolimot import Lolimot
    from fdi_ros.plants.diesel.identify import load_features
    from fdi_ros.plants.diesel.reference import (
        AMPLITUDE_OF,
        INPUTS,
        OUTPUTS,
        PERIOD_DEG,
        PHASES,
        IdentificationConfig,
        branch_centre,
        feature_table,
        nrmse,
        split_blocks,
        wrap_phase,
    )

    if args.repeat < 1:
        raise ValueError("--repeat must be >= 1")
    feats = load_features(args.data, seed=args.seed, mapping=args.mapping)
    with_p2 = bool(feats) and "p2" in feats[0].names
    data = feature_table(feats, names=INPUTS + OUTPUTS + (("p2",) if with_p2 else ()))
    cfg = IdentificationConfig(seed=args.seed)
    targets = {k: data[k] for k in OUTPUTS}
    if with_p2:
        # The target the reference model really learns: eta_V without the air stored in the
        # boost volume during transients (coefficient from the identification's own split).
        from fdi_ros.plants.diesel.reference import identify_reference_models, storage_regressor

        c = identify_reference_models(data, config=cfg).models.info["storage_coeff"]
        xs = storage_regressor(data["t"], data["n"], data["p2"], cfg.rate_lag)
        targets["eta_v_storage_corrected"] = data["eta_v"] - c * np.nan_to_num(xs)
    X = np.column_stack([data[k] for k in INPUTS])
    tr, va, te = split_blocks(X.shape[0], block=cfg.block, seed=cfg.seed)
    trva = np.concatenate([tr, va])
    report = {"data": args.data, "n_train": int(tr.size), "n_val": int(va.size),
              "n_test": int(te.size), "peer": type(_peer(args.peer, 0)).__name__,
              "lolimot": {"max_models": cfg.max_models, "compress_bins": cfg.compress_bins},
              "models": {}}
    for k, y in targets.items():
        # Phases as the identification learns them: unit phasors (cos, sin) on segments with
        # a fair amplitude, scored by the wrapped angle error; both learners get the same.
        comps = {"": y}
        ktr, kva, kte, ktrva = tr, va, te, trva
        if k in PHASES:
            amp = data[AMPLITUDE_OF[k]]
            lim = cfg.phase_min_amp_frac * float(np.percentile(amp[tr], 95))
            ktr, kva, kte, ktrva = (i[amp[i] >= lim] for i in (tr, va, te, trva))
            ang = 2 * np.pi * y / PERIOD_DEG
            comps = {"cos": np.cos(ang), "sin": np.sin(ang)}
        t_lol, t_ref, t_peer, pred, pred_peer, n_mod = 0.0, 0.0, 0.0, {}, {}, []
        for c, yc in comps.items():
            # the data as each learner takes them, copied out before the clocks start
            Xtr, ytr, Xva, yva = X[ktr], yc[ktr], X[kva], yc[kva]
            Xtrva, ytrva = X[ktrva], yc[ktrva]
            tl: list[float] = []
            tr_: list[float] = []
            tp: list[float] = []
            for _ in range(args.repeat):
                for fast, times in ((False, tr_), (True, tl)):
                    # the reference split search (every validity recomputed), then the fast
                    Lolimot._fast_splits = fast
                    m = cfg.lolimot()
                    t0 = time.perf_counter()
                    m.fit(Xtr, ytr, X_val=Xva, y_val=yva)
                    times.append(time.perf_counter() - t0)
                pr = _peer(args.peer, args.seed)
                t0 = time.perf_counter()
                pr.fit(Xtrva, ytrva)
                tp.append(time.perf_counter() - t0)
            t_lol += min(tl)
            t_ref += min(tr_)
            t_peer += min(tp)
            pred[c], pred_peer[c] = m.predict(X[kte]), pr.predict(X[kte])
            n_mod.append(m.n_models)
        if k in PHASES:
            yw = wrap_phase(y[kte], branch_centre(y[ktr]))

            def circ(pd, yw=yw, yt=y[kte]):
                phi = np.degrees(np.arctan2(pd["sin"], pd["cos"])) * PERIOD_DEG / 360.0
                return float(np.sqrt(np.mean(wrap_phase(yt - phi, 0.0) ** 2)) / np.std(yw))
            e, ep = circ(pred), circ(pred_peer)
        else:
            e, ep = nrmse(y[kte], pred[""]), nrmse(y[kte], pred_peer[""])
        report["models"][k] = {"nrmse": round(e, 5), "train_s": round(t_lol, 4),
                               "train_s_reference_splits": round(t_ref, 4),
                               "n_models": n_mod if len(n_mod) > 1 else n_mod[0],
                               "peer_nrmse": round(ep, 5), "peer_train_s": round(t_peer, 4),
                               "nrmse_ratio": round(e / ep, 3),
                               "time_ratio": round(t_lol / t_peer, 3)}
    ms = report["models"].values()
    report["summary"] = {
        "accuracy_equal_or_better": sum(v["nrmse"] <= 1.02 * v["peer_nrmse"] for v in ms),
        "mean_time_ratio": round(float(np.mean([v["time_ratio"] for v in ms])), 3),
        "goal": "nrmse <= peer_nrmse at train_s <= 0.1 * peer_train_s"}
    if args.json:
        print(json.dumps(report, indent=1))
    else:
        for k, v in report["models"].items():
            print(f"{k:10s} LOLIMOT nrmse={v['nrmse']:.4f} in {v['train_s']:.3f} s | "
                  f"{report['peer']} nrmse={v['peer_nrmse']:.4f} in {v['peer_train_s']:.3f} s")
    return 0
