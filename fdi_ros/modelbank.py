"""Build the model artifacts a graph configuration needs, once, and reuse them.

Identified models are artifacts, not sources: ``fdi-ros build-bank config/<plant>.yaml``
(and ``make demo``, and the graph tests) regenerate whatever model directory of the bank is
missing. For the diesel plant that is the nominal reference model set (LOLIMOT + tables +
fault-free thresholds) and one fault-hypothesis model per fault, each identified on the
identification cycle with its fault present.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from fdi_ros.core.graphconfig import GraphConfig, load_graph_config

# Size at which each diesel fault-hypothesis model is identified (mid-range of the scenarios;
# the hypothesis model estimates the size on line, so any size of that fault fits it).
DIESEL_HYPOTHESIS_SIZES = {"crankcase_vent_open": 10.0, "leak_ic_engine": 5.0,
                           "restriction_ic_engine": 0.7, "swirl_flap_closed": 1.0,
                           "egr_stuck_open": 0.5, "egr_leaky": 4.0}
HYPOTHESIS_WINDOW = 40  # segments over which a hypothesis estimates its fault size (0.6 s)


BUILD_INFO = "build_info.json"


def reference_fingerprint(ref_dir: str | Path) -> str:
    """Hash of the reference model set and thresholds a hypothesis model was built against:
    a hypothesis is stale (and rebuilt) when the reference models change under it."""
    import hashlib

    h = hashlib.sha256()
    for name in ("reference_models.json", "thresholds.json"):
        f = Path(ref_dir) / name
        h.update(f.read_bytes() if f.exists() else b"-")
    return h.hexdigest()[:16]


def _hypothesis_current(spec: dict) -> bool:
    import json

    d = Path(spec["hypothesis"])
    if not (d / "hypothesis.json").exists() or not (d / BUILD_INFO).exists():
        return False
    try:
        info = json.loads((d / BUILD_INFO).read_text())
    except ValueError:
        return False
    return info.get("reference") == reference_fingerprint(spec["path"])


def _missing(cfg: GraphConfig) -> list[tuple[str, dict]]:
    out = []
    for e in cfg.bank:
        spec = cfg.resolve_spec(e.model)
        if not isinstance(spec, dict):
            continue
        if spec.get("type") == "diesel_reference":
            d = Path(spec["path"])
            if not (d / "reference_models.json").exists() or not (d / "thresholds.json").exists():
                out.append((e.id, spec))
        elif spec.get("type") == "diesel_fault_hypothesis":
            if not _hypothesis_current(spec):
                out.append((e.id, spec))
        elif spec.get("type") == "turbofan_ts" and not Path(spec["path"]).exists():
            out.append((e.id, spec))
    return out


def ensure_bank(config: str | Path | GraphConfig, *, progress: bool = True, seed: int = 0,
                log: Callable[[str], None] = print) -> list[str]:
    """Identify every missing model of the configuration's bank; returns what was built."""
    cfg = config if isinstance(config, GraphConfig) else load_graph_config(config)
    if cfg.plant not in ("diesel", "turbofan") and cfg.plant.isidentifier():
        import importlib

        try:  # a plant wing that builds its own models
            wing = importlib.import_module(f"fdi_ros.plants.{cfg.plant}.bank")
        except ModuleNotFoundError:
            wing = None
        if wing is not None and hasattr(wing, "ensure_bank"):
            return wing.ensure_bank(cfg, progress=progress, log=log)
    todo = _missing(cfg)
    if not todo:
        return []
    if cfg.plant == "turbofan":
        # one global TS model serves every bank model (it interpolates over the fault sizes)
        from fdi_ros.commands.train_turbofan import train
        from fdi_ros.plants.turbofan.settings import load_settings

        t0 = time.perf_counter()
        log(f"[bank] training the turbofan's Takagi-Sugeno node models "
            f"(for {', '.join(m for m, _ in todo)})")
        train(load_settings(cfg.path), progress=progress)
        log(f"[bank] turbofan models: {time.perf_counter() - t0:.1f} s")
        return [m for m, _ in todo]
    if cfg.plant != "diesel":
        raise ValueError(f"models missing for {[m for m, _ in todo]}: no builder for plant "
                         f"{cfg.plant!r}")
    from fdi_ros.commands.identify import (
        DEFAULT_DRIVE,
        DEFAULT_IDENT,
        build_models,
        simulate_features,
    )
    from fdi_ros.core.types import FaultEvent
    from fdi_ros.plants.diesel.plant import FAULT_UNITS
    from fdi_ros.plants.diesel.reference import ReferenceModelSet
    from fdi_ros.plants.diesel.symptoms import identify_fault_hypothesis, load_symptom_config

    built = []
    refs = [(m, s) for m, s in todo if s["type"] == "diesel_reference"]
    for mid, spec in refs:
        t0 = time.perf_counter()
        log(f"[bank] identifying the reference models {mid!r} -> {spec['path']}")
        build_models(cfg.resolve(DEFAULT_IDENT), out=spec["path"], seed=seed,
                     fault_free=cfg.resolve(DEFAULT_DRIVE), progress=progress)
        built.append(mid)
        log(f"[bank] {mid}: {time.perf_counter() - t0:.1f} s")
    for i, (mid, spec) in enumerate(s for s in todo if s[1]["type"] != "diesel_reference"):
        t0 = time.perf_counter()
        mset = ReferenceModelSet.load(spec["path"])
        scfg = load_symptom_config(spec["path"])
        # the fault of this hypothesis: its bank entry's single fault
        fault = next(iter(cfg.entry(mid).faults))
        size = DIESEL_HYPOTHESIS_SIZES[fault]
        log(f"[bank] identifying fault hypothesis {mid!r} ({fault} {size:g} "
            f"{FAULT_UNITS[fault]}) -> {spec['hypothesis']}")
        feats, _ = simulate_features(
            cfg.resolve(DEFAULT_IDENT), seed=seed + 500 + i, progress=progress,
            faults=[FaultEvent(t=5.0, fault=fault, size=size, size_unit=FAULT_UNITS[fault])])
        hyp = identify_fault_hypothesis(mset, scfg, feats, fault=fault, size=size, t_from=6.0,
                                        model_id=mid, window=HYPOTHESIS_WINDOW)
        hyp.save(spec["hypothesis"])
        import json

        (Path(spec["hypothesis"]) / BUILD_INFO).write_text(json.dumps(
            {"reference": reference_fingerprint(spec["path"]), "fault": fault, "size": size,
             "seed": seed + 500 + i, "window": HYPOTHESIS_WINDOW}))
        built.append(mid)
        log(f"[bank] {mid}: {time.perf_counter() - t0:.1f} s")
    return built
