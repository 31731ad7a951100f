"""Identification pipeline of the diesel reference models (LOLIMOT + ECU tables).

Data: a scenario YAML (simulated with the diesel plant), a bag (features, or sensor blocks that
are segmented here) or a CSV (+ mapping). Writes the model set (npz + table JSON + manifest),
fault-free thresholds (when a fault-free driving scenario is given) and figures like the
paper's Figs. 5, 7-10.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

DEFAULT_IDENT = "config/scenarios/diesel_ident.yaml"
# the part-load passes with the EGR valve and the flaps run by the ECU's maps: their EGR-closed
# segments fill the base regime's map at low speed and their valve moves show the T2 sensor's
# lag; the other regimes' maps from them are not good enough for thresholds yet (README)
DEFAULT_IDENT_ECU = "config/scenarios/diesel_ident_ecu.yaml"
# a slow part-load pass with the flaps closed and the EGR valve open: quasi-stationary data
# for that regime's EGR flow model only (its EGR-closed segments stay out of the base maps)
DEFAULT_IDENT_FLAPS = "config/scenarios/diesel_ident_flaps.yaml"
DEFAULT_DRIVE = "config/scenarios/diesel_drive.yaml"
# a drive as the ECU runs it (another route than the realistic drive the coverage is judged on)
DEFAULT_CALIBRATION_DRIVE = "config/scenarios/diesel_calibration_drive.yaml"
# ... and a hard driver's (ramps 0.3-2.4 s): the transients' thresholds must hold for tip-ins
# that close the EGR valve in a few tenths of a second
DEFAULT_CALIBRATION_HARD = "config/scenarios/diesel_calibration_hard.yaml"
# ... and 40 hard tip-ins and tip-outs (0.2-1 s between part and full load): with the three
# drives alone 7 of 16 random ones gave a false symptom (the EGR valve closing and opening,
# the flaps switching, the VGT saturating within tenths of a second)
DEFAULT_CALIBRATION_TIPS = "config/scenarios/diesel_calibration_tips.yaml"
CACHE_DIR = Path("build/cache/features")
# Part of the feature cache's key: bumped whenever the plant or its preprocessing changes
# what a scenario's features are (2: the T2 rate became a quadratic's end-point slope, and
# an EGR valve below the boost pressure passes intake gas back at the intake's density; 3: a
# scenario with an ECU limits a torque demand to its full-load fuel)
FEATURES_VERSION = "features-3"
THRESHOLD_SEED = 101  # noise seed of the fault-free drives the thresholds are calibrated on


def _blocks_from_csv(path: Path, mapping):
    import numpy as np

    from fdi_ros.core.measured import load_csv
    from fdi_ros.core.types import SampleBlock

    m = load_csv(path, mapping)
    if m.alpha is None:
        raise ValueError(f"{path}: the diesel features need a crank-angle column 'alpha'")
    names = tuple(k for k in m.signals if k in ("n", "p2", "T2", "maf", "p_amb", "T_amb"))
    skipped = m.skipped(names)
    if skipped["samples"]:
        per = ", ".join(f"{k} in {n}" for n, k in skipped["by_signal"].items())
        print(f"fdi-ros identify: {path}: {skipped['samples']} of {skipped['of']} samples with "
              f"missing or non-finite values ({per}); the segments holding them are skipped",
              file=sys.stderr, flush=True)
    vals = np.vstack([m.signals[k] for k in names])
    return [SampleBlock(plant="diesel", index=0, t=m.t, alpha=m.alpha, channels=names,
                        units=tuple(m.units[k] for k in names), values=vals)]


def features_from_blocks(blocks) -> list:
    """Crank-synchronous features of consecutive blocks (segments may straddle blocks)."""
    from fdi_ros.plants.diesel.plant import crank_segmenter

    seg = crank_segmenter()
    out = []
    for b in blocks:
        out.extend(seg.push_table(b).to_features())
    return out


def simulate_features(scenario, *, seed: int, progress: bool = False, faults=None,
                      duration_s: float | None = None):
    """Simulate a diesel scenario (path or Scenario; ``faults`` replaces its fault events) and
    return (features, fault truth events)."""
    import dataclasses

    from fdi_ros.plants.diesel.scenario import Scenario, load_scenario, simulate

    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    if faults is not None:
        sc = dataclasses.replace(sc, faults=tuple(faults))
    if duration_s is not None:
        sc = dataclasses.replace(sc, duration_s=min(float(duration_s), sc.duration_s))
    sim = simulate(sc, seed=seed, keep_blocks=False, progress=progress)
    if sim.features is None:
        raise ValueError("the simulation produced no features")
    return sim.features.to_features(), list(sim.faults)


def load_features(source, *, seed: int = 0, mapping=None, cache: bool = True,
                  case: str | None = None) -> list:
    """Feature vectors of a scenario (simulated, cached in build/; ``case``: one of the
    file's cases), bag or CSV."""
    path = Path(source)
    if not path.exists():
        raise FileNotFoundError(f"no data at {path}")
    if path.suffix in (".yaml", ".yml"):
        tag = f"seed={seed},{FEATURES_VERSION}" + (f",case={case}" if case is not None else "")
        key = hashlib.sha1(path.read_bytes() + tag.encode()).hexdigest()[:16]
        cached = CACHE_DIR / f"{case or path.stem}_{seed}_{key}.npz"
        if cache and cached.exists():
            return _read_cache(cached)
        if case is not None:
            from fdi_ros.plants.diesel.scenario import load_scenario

            feats, _ = simulate_features(load_scenario(path, case=case), seed=seed)
        else:
            feats, _ = simulate_features(path, seed=seed)
        if cache:
            _write_cache(cached, feats)
        return feats
    if path.is_dir():
        from fdi_ros import bag

        tops = bag.topics(path)
        if "/fdi/features" in tops:
            return bag.read_features(path)
        if "/fdi/sensor_block" in tops:
            return features_from_blocks(bag.read_blocks(path))
        raise ValueError(f"{path}: bag has neither /fdi/features nor /fdi/sensor_block")
    if path.suffix.lower() == ".csv":
        return features_from_blocks(_blocks_from_csv(path, mapping))
    raise ValueError(f"{path}: expected a scenario .yaml, a bag directory or a .csv")


def _write_cache(path: Path, feats) -> None:
    import numpy as np

    path.parent.mkdir(parents=True, exist_ok=True)
    if not feats:
        return
    names = feats[0].names
    if any(f.names != names for f in feats):
        return  # heterogeneous vectors: not worth caching
    np.savez_compressed(
        path, names=np.array(names), units=np.array(feats[0].units),
        values=np.vstack([f.values for f in feats]),
        meta=np.array([[f.index, f.t_start, f.t_end, f.alpha_start] for f in feats]),
        valid=np.array([f.valid for f in feats]), status=np.array([f.status for f in feats]),
        plant=np.array(feats[0].plant))


def _read_cache(path: Path) -> list:
    import numpy as np

    from fdi_ros.core.types import FeatureVector

    with np.load(path, allow_pickle=False) as z:
        names = tuple(str(x) for x in z["names"])
        units = tuple(str(x) for x in z["units"])
        plant = str(z["plant"])
        return [FeatureVector(plant=plant, index=int(m[0]), t_start=float(m[1]),
                              t_end=float(m[2]), alpha_start=float(m[3]), valid=bool(ok),
                              status=str(st), names=names, units=units, values=v)
                for v, m, ok, st in zip(z["values"], z["meta"], z["valid"], z["status"])]


def calibrate_from_features(mset, feats, **kw):
    """Fault-free residual statistics -> SymptomConfig (thresholds, storage correction, gate);
    ``feats``: one stream of feature vectors or several. Also returns the number of segments
    with a valid residual under the calibrated gate."""
    from fdi_ros.core.types import FeatureVector
    from fdi_ros.plants.diesel.symptoms import calibrate_with_residuals, valid_under

    streams = [feats] if not feats or isinstance(feats[0], FeatureVector) else list(feats)
    kw.setdefault("transients", "regime")
    cfg, rvs = calibrate_with_residuals(mset, streams, **kw)
    return cfg, valid_under(cfg, rvs)


def identification_table(streams) -> dict:
    """The identification arrays of one or several feature streams: the reference models'
    inputs and outputs and whatever else the regimes read (p2, T2 and its rate, fuel, VGT,
    the actuator commands), the stored-air regressor computed per stream, then joined."""
    import numpy as np

    from fdi_ros.plants.diesel.reference import (
        ACTUATORS,
        INPUTS,
        OUTPUTS,
        feature_table,
        storage_regressor,
    )

    parts = []
    for feats in streams:
        have = feats[0].names if feats else ()
        names = INPUTS + OUTPUTS + tuple(k for k in ("p2", "T2", "T2_rate", "fuel", "vgt",
                                                          "vgt_rate")
                                         + ACTUATORS if k in have)
        d = feature_table(feats, names=names)
        d["storage_x"] = storage_regressor(d["t"], d["n"], d["p2"])
        parts.append(d)
    common = set(parts[0]).intersection(*parts[1:])
    return {k: np.concatenate([d[k] for d in parts]) for k in parts[0] if k in common}


def build_models(data_source, *, out, seed: int = 0, fault_free=DEFAULT_DRIVE,
                 threshold_seed: int = THRESHOLD_SEED, mapping=None, config=None,
                 progress: bool = True, figures=None, log=lambda s: None,
                 further_regimes: bool = False, regime_sources=(),
                 sources_digest: str = ""):
    """Identify, save, calibrate the fault-free thresholds; returns (result, symptom config or
    None, report dict). ``data_source`` and ``fault_free``: one source (scenario, bag, CSV) or
    a list of them; each source is a stream of its own (e.g. the EGR-closed identification
    cycle and the part-load passes with the ECU's maps); with ``further_regimes`` every
    operating regime with enough data gets models of its own (:func:`identify_regime_models`),
    else the base regime's only; ``regime_sources``: more streams for the further regimes
    only (seeds after the data sources'); ``sources_digest``: kept with the models (the
    bank's set, :func:`digest_of` its sources: rebuilt when one of them changes)."""
    import numpy as np

    from fdi_ros.plants.diesel.reference import (
        REGIMES,
        REGIMES_ONLY,
        IdentificationConfig,
        identify_regime_models,
        regime_labels,
        table_grid_errors,
    )
    from fdi_ros.plants.diesel.symptoms import THRESHOLDS_FILE

    cfg = config or IdentificationConfig(seed=seed)
    sources = data_source if isinstance(data_source, (list, tuple)) else [data_source]
    data = identification_table([load_features(src, seed=seed + i, mapping=mapping)
                                 for i, src in enumerate(sources)])
    if further_regimes and regime_sources:
        more = identification_table([load_features(src, seed=seed + len(sources) + j,
                                                   mapping=mapping)
                                     for j, src in enumerate(regime_sources)])
        data = {k: np.concatenate([data[k], more[k]]) for k in data if k in more}
        data[REGIMES_ONLY] = np.r_[np.zeros(data["n"].size - more["n"].size),
                                   np.ones(more["n"].size)]
    res = identify_regime_models(data, config=cfg, progress=progress, log=log,
                                 further_regimes=further_regimes)
    out = Path(out)
    res.models.info["further_regimes"] = bool(further_regimes)
    res.models.info["features"] = FEATURES_VERSION
    if sources_digest:
        res.models.info["sources"] = sources_digest
    res.models.save(out)
    info = res.models.info
    report = {"out": str(out), "n_segments": int(data["n"].size), "n_train": res.n_train,
              "n_val": res.n_val, "n_test": res.n_test, "train_s": round(res.train_s, 3),
              "eta_storage_coeff": info.get("storage_coeff", 0.0),
              "t2_sensor_tau_s": round(float(info.get("t2_tau", 0.0)), 3),
              "regimes": {name: {"segments": n,
                                 "nrmse_test": {k: round(v, 4) for k, v in
                                                info["regime_nrmse_test"][name].items()}}
                          for name, n in info.get("regime_segments", {}).items()},
              "models": {k: {"n_models": {n: r.n_models for n, r in res.results.items()
                                          if n == k or n.startswith(k + "_")},
                             "nrmse_test": round(res.nrmse_test[k], 4),
                             "nrmse_test_lut": round(res.nrmse_test_lut[k], 4),
                             "lut_vs_model_rmse": res.lut_error[k]["rmse"]}
                         for k in res.nrmse_test}}
    in_base = (regime_labels(data) == REGIMES[0][0]) & (data.get(REGIMES_ONLY, 0.0) == 0)
    base = {k: v[in_base] for k, v in data.items()}
    X = np.column_stack([base[k] for k in res.models.inputs])
    report["inputs"] = list(res.models.inputs)
    if res.models.validity is not None:
        report["validity"] = {r.name: r.describe() for r in res.models.validity.ranges}
    report["table_vs_model_rmse"] = table_grid_errors(res.models, X[:: max(1, len(X) // 4000)])
    scfg = None
    ff_sources = fault_free if isinstance(fault_free, (list, tuple)) else [fault_free]
    ff_sources = [f for f in ff_sources if f and str(f).lower() != "none"]
    if ff_sources:
        ff = [load_features(f, seed=threshold_seed + i, mapping=mapping)
              for i, f in enumerate(ff_sources)]
        scfg, n_used = calibrate_from_features(res.models, ff)
        (out / THRESHOLDS_FILE).write_text(json.dumps(scfg.to_dict(), indent=1))
        report["thresholds"] = dict(zip(scfg.names, scfg.threshold))
        report["regime_thresholds"] = {r: dict(zip(scfg.names, st["threshold"]))
                                       for r, st in scfg.regimes.items()}
        report["storage_coeff"] = scfg.storage_coeff
        report["threshold_segments"] = int(n_used)
    if figures:
        report["figures"] = [str(p) for p in identification_figures(res, base, figures)]
    return res, scfg, report


# The sources of the graph's reference model set: what it is identified on and the fault-free
# drives its thresholds come from (seeds: the first source's seed, then one more per source).
REFERENCE_SOURCES = (DEFAULT_IDENT, DEFAULT_IDENT_ECU)
REGIME_SOURCES = (DEFAULT_IDENT_FLAPS,)
THRESHOLD_SOURCES = (DEFAULT_DRIVE, DEFAULT_CALIBRATION_DRIVE, DEFAULT_CALIBRATION_HARD,
                     DEFAULT_CALIBRATION_TIPS)


# The structure of the sets the builder makes (in the digest: a set of another structure is
# rebuilt as a changed source would make it): 2, the EGR-open pulsation-ratio regime.
BUILDER_VERSION = "reference-sets-2"


def digest_of(sources) -> str:
    """Digest of the identification and calibration sources a model set was built from (file
    names and contents; other sources by their name; the builder's version): a set is rebuilt
    when one changes."""
    import hashlib

    h = hashlib.sha256(BUILDER_VERSION.encode() + b"\0")
    for src in sources:
        path = Path(str(src))
        h.update(path.name.encode() + b"\0")
        if path.is_file():
            h.update(path.read_bytes())
    return h.hexdigest()[:16]


def reference_sources(resolve=Path) -> list[str]:
    """Every source :func:`build_reference_models` reads, resolved, in its order."""
    return [str(resolve(s)) for s in (*REFERENCE_SOURCES, *REGIME_SOURCES, *THRESHOLD_SOURCES)]


def build_reference_models(out, *, seed: int = 0, progress: bool = True, log=lambda s: None,
                           resolve=Path):
    """The reference model set of the diesel graph's bank (the base regime, with the ECU's
    part-load passes for its low-speed map and the T2 sensor's lag; the EGR-open regimes the
    passes hold enough of), thresholds from the two fault-free drives: what ``fdi-ros
    build-bank`` and ``reproduce diesel --rebuild`` build. ``resolve`` turns the
    repository-relative scenario paths into paths."""
    return build_models([str(resolve(s)) for s in REFERENCE_SOURCES], out=out, seed=seed,
                        fault_free=[str(resolve(s)) for s in THRESHOLD_SOURCES],
                        threshold_seed=THRESHOLD_SEED, progress=progress, log=log,
                        further_regimes=True,
                        regime_sources=[str(resolve(s)) for s in REGIME_SOURCES],
                        sources_digest=digest_of(reference_sources(resolve)))


def identification_figures(res, data, outdir) -> list[Path]:
    """Partition with centres (paper Fig. 5), data distribution (Fig. 7) and each model's map
    against the data points (Figs. 8-10), plus held-out predicted-vs-measured."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from matplotlib.patches import Rectangle

    from fdi_ros.plants.diesel.reference import INPUTS, UNITS, split_blocks

    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    paths = []
    X = np.column_stack([data[k] for k in INPUTS])
    _, _, te = split_blocks(X.shape[0], block=res.models.info["config"]["block"],
                            seed=res.models.info["config"]["seed"])
    mset = res.models
    # Fig. 5 + 7: partition of the eta_v model, centres, data points.
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    for ax, k in zip(axes, ("eta_v", "maf_amp")):
        m = mset.models[k]
        ax.plot(X[:, 0], X[:, 1], ".", ms=1, color="0.7", label="data points")
        lo, hi = m.cell_bounds
        for a, b in zip(lo, hi):   # (n, rho2) projection of the cells
            ax.add_patch(Rectangle(a[:2], *(b - a)[:2], fill=False, lw=1.2, color="C0"))
        c = m.centres
        ax.plot(c[:, 0], c[:, 1], "x", color="C3", ms=8, mew=2, label="local model centres")
        ax.set_xlabel(f"engine speed n [{UNITS['n']}]")
        ax.set_ylabel(f"boost density rho2 [{UNITS['rho2']}]")
        ax.set_title(f"LOLIMOT partition of {k}: {m.n_models} local models")
        ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    paths.append(outdir / "fig05_partition.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    # Figs. 8-10: maps (look-up table over the identified region) against the data points.
    for k in mset.outputs:
        tab = mset.tables[k if k in mset.tables else f"{k}_cos"]
        bn, br = tab.breakpoints[:2]
        nn, rr = np.meshgrid(np.linspace(bn[0], bn[-1], 60), np.linspace(br[0], br[-1], 50))
        P = np.column_stack([nn.ravel(), rr.ravel()])
        ref, ok = mset.predict(P[:, 0], P[:, 1])
        v = ref[k]
        y = data[k]
        if k in mset.phase_centre:
            from fdi_ros.plants.diesel.reference import wrap_phase
            y = wrap_phase(y, mset.phase_centre[k])
            v = wrap_phase(v, mset.phase_centre[k])
        V = np.where(ok, v, np.nan).reshape(nn.shape)
        fig = plt.figure(figsize=(13, 5))
        ax = fig.add_subplot(1, 2, 1, projection="3d")
        ax.plot_surface(nn, rr, np.ma.masked_invalid(V), cmap="viridis", alpha=0.7,
                        linewidth=0)
        sub = np.arange(0, X.shape[0], max(1, X.shape[0] // 1500))
        ax.scatter(X[sub, 0], X[sub, 1], y[sub], s=2, color="k", label="data points")
        ax.set_xlabel("n [rpm]")
        ax.set_ylabel("rho2 [kg/m^3]")
        ax.set_zlabel(f"{k} [{UNITS[k]}]")
        ax.set_title(f"reference model {k} (ECU table) vs data")
        ax2 = fig.add_subplot(1, 2, 2)
        yp = mset.predict(X[te, 0], X[te, 1], use_tables=False,
                          extra={a: data[a][te] for a in mset.extra_inputs})[0][k]
        if k in mset.phase_centre:
            yp = wrap_phase(yp, mset.phase_centre[k])
        ax2.plot(y[te], yp, ".", ms=2)
        lim = [np.nanmin(y[te]), np.nanmax(y[te])]
        ax2.plot(lim, lim, "k--", lw=1)
        ax2.set_xlabel(f"measured {k} [{UNITS[k]}]")
        ax2.set_ylabel(f"model {k} [{UNITS[k]}]")
        ax2.set_title(f"held-out segments: NRMSE = {res.nrmse_test[k]:.3f}")
        fig.tight_layout()
        paths.append(outdir / f"map_{k}.png")
        fig.savefig(paths[-1], dpi=110)
        plt.close(fig)
    return paths
