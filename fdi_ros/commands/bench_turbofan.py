"""``fdi-ros bench turbofan``: speed of the turbofan pieces against baselines of the same run.

* LM fit of one TS system (1000 samples, R = 3): analytic Jacobian vs scipy's finite-difference
  Jacobian (same data, same start, the same budget of 40 LM iterations: MINPACK counts the
  n + 1 function calls of a finite-difference Jacobian as evaluations).
* Bank of 16 models over 20 s: vectorised open-loop simulation (all models in one array) vs the
  live path (one :class:`TurbofanResidualModel` per model, sample by sample).
* Plant: 50 engines in one batched simulation vs 50 separate simulations.
Figures are seconds and ratios (baseline / fast); real-time factors are plant s per wall s.
"""

from __future__ import annotations

import argparse
import json
import time

COMMAND = ("bench", "turbofan")
HELP = "benchmark the turbofan: LM analytic Jacobian, vectorised bank, batched plant"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="JSON output (the default)")
    parser.add_argument("--repeat", type=int, default=3, help="repetitions (best time counts)")


def _best(fn, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def run(args: argparse.Namespace) -> int:
    import numpy as np
    from scipy.optimize import least_squares

    from fdi_ros.core.tsfuzzy import fit_ts, initial_model
    from fdi_ros.core.types import FeatureVector
    from fdi_ros.plants.turbofan import bank as tfb
    from fdi_ros.plants.turbofan import plant as tfp
    from fdi_ros.plants.turbofan.models import NORM_OFFSET, NORM_SCALE, GridSpec, train_global

    if args.repeat < 1:
        raise ValueError("--repeat must be >= 1")
    out: dict = {}
    plant = tfp.Turbofan()
    c = np.array(tfp.PAPER_CONDITION)
    wfs = plant.scheduled_fuel(c)

    # -- LM: analytic vs finite-difference Jacobian ------------------------------------------
    u = tfp.training_input(wfs, np.random.default_rng(0), duration_s=20.02)
    x = plant.simulate(u, c, 0.1 * tfp.DETERIORATION_FULL, noise=False)["x"]
    inp = np.column_stack([x[:-1], u[:-1]])
    y = np.diff(x[:, 0]) / plant.k.Ts
    init = initial_model(inp, y, n_rules=3, premise=0, offset=NORM_OFFSET, scale=NORM_SCALE)
    fast = fit_ts(inp, y, init=init, offset=NORM_OFFSET, scale=NORM_SCALE, max_nfev=40)
    t_fast = _best(lambda: fit_ts(inp, y, init=init, offset=NORM_OFFSET, scale=NORM_SCALE,
                                  max_nfev=40), args.repeat)

    def fd_fit():
        def fun(theta):
            return init.with_theta(theta)(inp) - y
        return least_squares(fun, init.theta(), jac="2-point", method="lm", max_nfev=40 * 19,
                             x_scale="jac")

    fd = fd_fit()
    t_fd = _best(fd_fit, args.repeat)
    out["lm_fit"] = {"analytic_s": round(t_fast, 4), "finite_difference_s": round(t_fd, 4),
                     "ratio": round(t_fd / t_fast, 2), "rmse_analytic": round(fast.rmse, 4),
                     "rmse_finite_difference": round(float(np.sqrt(2 * fd.cost / y.size)), 4)}

    # -- bank: vectorised vs per-model live path -----------------------------------------------
    grid = GridSpec(ALT=(15000.0,), XM=(0.7,), deterioration=(0.0, 0.1, 0.2),
                    region={"ALT": (14500.0, 15500.0), "XM": (0.68, 0.72),
                            "DTAMB": (-5.0, 5.0), "PC": (45.5, 46.5)})
    t0 = time.perf_counter()
    gm = train_global(grid, progress=False)
    report = gm.report
    if report is None:
        raise RuntimeError("training returned no report")
    out["training_small_grid"] = {"nodes": report.n_nodes,
                                  "seconds": round(time.perf_counter() - t0, 2),
                                  "seconds_per_node": round((time.perf_counter() - t0)
                                                            / report.n_nodes, 4)}
    sc = tfb.Scenario(name="bench", events=((5.0, {"hub": "small"}),))
    sim = tfb.simulate_plant(sc)
    ids = [m.id for m in tfb.PAPER_BANK]
    mix = tfb.bank_mixture(gm, ids, condition=c, deterioration=0.1)
    t_vec = _best(lambda: mix.simulate(sim["wf"], sim["y"][0]), args.repeat)
    models = [tfb.TurbofanResidualModel(global_model=gm, model_id=m, condition=c,
                                        deterioration=0.1) for m in ids]
    fvs = [FeatureVector(plant="turbofan", index=k, t_start=float(sim["t"][k]),
                         t_end=float(sim["t"][k]), alpha_start=0.0, valid=True, status="",
                         names=("XNL", "XNH", "WF36"), units=("rpm", "rpm", "kg/s"),
                         values=np.array([*sim["y"][k], sim["wf"][k]])) for k in range(1000)]

    def live():
        for m in models:
            m.reset()
        for fv in fvs:
            for m in models:
                m.residuals(fv)

    t_live = _best(live, 1)
    span = float(sim["t"][-1] + plant.k.Ts)
    out["bank_16_models_20s"] = {"vectorised_s": round(t_vec, 4), "per_model_live_s":
                                 round(t_live, 4), "ratio": round(t_live / t_vec, 1),
                                 "realtime_factor_vectorised": round(span / t_vec, 1),
                                 "realtime_factor_live": round(span / t_live, 1)}

    # -- plant: batched vs one by one ----------------------------------------------------------
    wf = tfp.paper_input(wfs)
    p = np.zeros((50, 10))
    t_batch = _best(lambda: plant.simulate(np.broadcast_to(wf, (50, wf.size)),
                                           np.broadcast_to(c, (50, 4)), p, noise=False),
                    args.repeat)
    t_loop = _best(lambda: [plant.simulate(wf, c, p[i], noise=False) for i in range(50)], 1)
    out["plant_50_engines_20s"] = {"batched_s": round(t_batch, 4), "loop_s": round(t_loop, 4),
                                   "ratio": round(t_loop / t_batch, 1)}
    print(json.dumps(out, indent=2))
    return 0
