"""The diesel intake wing: streaming runner, crank-synchronous preprocessor, residual-model
kinds (``diesel_reference``, ``diesel_fault_hypothesis``) and the bank builder, registered as
plant ``"diesel"`` in :mod:`fdi_ros.plants`.

The bank builder identifies, once, whatever model directory of a bank is missing: the nominal
reference model set (LOLIMOT + tables + fault-free thresholds) and one fault-hypothesis model per
fault, each identified on the identification cycle with its fault present.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from fdi_ros.core.graphconfig import GraphConfig
from fdi_ros.core.plant_api import FaultQueue
from fdi_ros.core.types import FaultEvent, FeatureVector, SampleBlock
from fdi_ros.plants import ROOT, Wing
from fdi_ros.plants.diesel.plant import FAULT_IDS, FAULT_UNITS, crank_segmenter

DEFAULT_SCENARIO = ROOT / "config" / "scenarios" / "diesel_paper_op.yaml"
# Size at which each fault-hypothesis model is identified (mid-range of the scenarios; the
# hypothesis model estimates the size on line, so any size of that fault fits it).
HYPOTHESIS_SIZES = {"crankcase_vent_open": 10.0, "leak_ic_engine": 5.0,
                    "restriction_ic_engine": 0.7, "swirl_flap_closed": 1.0,
                    "egr_stuck_open": 0.5, "egr_leaky": 4.0}
# A size-specific hypothesis (bank entry fault ``<fault>_small`` / ``_large``, as the turbofan
# bank sizes its faults) is identified at this multiple of the size above unless its model
# spec names ``size:``; sizes are clipped to the plant's fault limits.
SIZE_FACTORS = {"small": 0.5, "medium": 1.0, "large": 2.0}
HYPOTHESIS_WINDOW = 40  # segments over which a hypothesis estimates its fault size (0.6 s)
# What a hypothesis holds: 2 = effect maps of the EGR-open regimes beside the base regime's,
# 3 = and a valve leak's eta_V effect from the exhaust side (hypotheses of an older layout are
# rebuilt)
HYPOTHESIS_LAYOUT = 3
BUILD_INFO = "build_info.json"
REFERENCE_FILES = ("reference_models.json", "thresholds.json")


class DieselRunner:
    """The diesel intake plant running a scenario, one block of ``block_deg`` at a time."""

    plant = "diesel"

    def __init__(self, scenario: str | Path | dict | None = None, *,
                 seed: int | None = None) -> None:
        from fdi_ros.plants.diesel.plant import DieselIntakePlant
        from fdi_ros.plants.diesel.scenario import load_scenario

        sc = load_scenario(scenario if scenario is not None else DEFAULT_SCENARIO)
        self.scenario = sc
        self.sim = DieselIntakePlant(params=sc.params, seed=sc.seed if seed is None else seed,
                                     dalpha_deg=sc.dalpha_deg)
        self.sim.set_input_profile(sc.inputs_at)
        self._truth = FaultQueue()
        for ev in sc.faults:
            self.inject(ev)
        self._per_block = max(int(round(sc.block_deg / sc.dalpha_deg)), 1)
        self._t = 0.0

    @property
    def t(self) -> float:
        return self._t

    @property
    def done(self) -> bool:
        return self._t >= self.scenario.duration_s

    def next_block(self) -> SampleBlock:
        block = self.sim.advance(self._per_block)
        self._t = float(block.t[-1])
        return block

    def inject(self, event: FaultEvent) -> None:
        self.sim.inject(event)
        self._truth.add(event)

    def pop_truth(self) -> list[FaultEvent]:
        return self._truth.due(self._t)


class DieselPreprocessor:
    """Crank-synchronous segments (180 deg CA) of the diesel's sensor blocks.

    A lost block leaves a crank-angle gap that the segmenter itself detects: the segment across
    it is flagged invalid, so ``mark_gap`` has nothing to add.
    """

    def __init__(self, **kwargs: Any) -> None:
        self.seg = crank_segmenter(None, **kwargs)

    def push(self, block: SampleBlock) -> list[FeatureVector]:
        return self.seg.push(block)

    def push_many(self, blocks: Sequence[SampleBlock]) -> list[FeatureVector]:
        """The feature vectors of consecutive blocks, segmented in one pass (offline): the
        same as pushing them one by one, since the segmenter spans block boundaries."""
        from fdi_ros.core.crank import join_blocks

        return self.seg.push_table(join_blocks(blocks)).to_features()

    def mark_gap(self) -> None:
        pass

    def reset(self) -> None:
        self.seg.reset()


def validate_fault(event: FaultEvent) -> None:
    """Raise ValueError if the plant cannot apply ``event`` (fault id, unit, size range)."""
    from fdi_ros.plants.diesel.plant import _FaultSchedule

    _FaultSchedule().add(event)


def _reference_dir_spec(path: Path) -> dict | None:
    return {"type": "diesel_reference", "path": "."} \
        if (path / "reference_models.json").exists() else None


# -- bank builder ---------------------------------------------------------------------------------
def reference_fingerprint(ref_dir: str | Path) -> str:
    """Hash of the reference model set and thresholds a hypothesis model was built against:
    a hypothesis is stale (and rebuilt) when the reference models change under it."""
    h = hashlib.sha256()
    for name in REFERENCE_FILES:
        f = Path(ref_dir) / name
        h.update(f.read_bytes() if f.exists() else b"-")
    return h.hexdigest()[:16]


def hypothesis_fault(fault_id: str, spec: dict) -> tuple[str, float]:
    """The plant fault and the size a hypothesis of bank fault ``fault_id`` is identified at:
    ``leak_ic_engine`` -> (leak_ic_engine, 5 mm), ``leak_ic_engine_small`` -> (.., 2.5 mm),
    or the spec's own ``size``."""
    from fdi_ros.core.supervisor import fault_type
    from fdi_ros.plants.diesel.plant import FAULT_LIMITS

    fault = fault_type(fault_id)
    if fault not in HYPOTHESIS_SIZES:
        raise ValueError(f"bank fault {fault_id!r}: no diesel fault {fault!r}")
    if spec.get("size") is not None:
        size = float(spec["size"])
    else:
        word = fault_id[len(fault) + 1:] or "medium"
        size = HYPOTHESIS_SIZES[fault] * SIZE_FACTORS[word]
    lo, hi = FAULT_LIMITS[fault]
    if not lo < size <= hi:
        raise ValueError(f"bank fault {fault_id!r}: size {size:g} outside ({lo:g}, {hi:g}]")
    return fault, size


def _hypothesis_current(spec: dict, fault_id: str) -> bool:
    d = Path(spec["hypothesis"])
    if not (d / "hypothesis.json").exists() or not (d / BUILD_INFO).exists():
        return False
    try:
        info = json.loads((d / BUILD_INFO).read_text())
    except ValueError:
        return False
    fault, size = hypothesis_fault(fault_id, spec)
    return bool(info.get("reference") == reference_fingerprint(spec["path"])
                and info.get("layout") == HYPOTHESIS_LAYOUT
                and info.get("fault", fault) == fault
                and math.isclose(float(info.get("size", size)), size))


def _reference_current(d: Path, resolve: Callable[[str], Any] = Path) -> bool:
    """The reference model set exists, was identified on today's features (and, a set the
    bank builder made, on its identification and calibration scenarios as they are now: one
    identified by hand on other data is kept) and carries its validity region with today's
    actuator tolerances (sets identified before are rebuilt)."""
    from fdi_ros.plants.diesel.identify import FEATURES_VERSION, digest_of, reference_sources
    from fdi_ros.plants.diesel.reference import ACTUATOR_TOL

    if not all((d / f).exists() for f in REFERENCE_FILES):
        return False
    try:
        manifest = json.loads((d / REFERENCE_FILES[0]).read_text())
    except ValueError:
        return False
    validity = manifest.get("validity")
    # identified in operating regimes, the EGR-open ones included (sets from before are
    # rebuilt)
    info = manifest.get("info", {})
    if not validity or not info.get("regime") or not info.get("further_regimes") \
            or info.get("features") != FEATURES_VERSION \
            or info.get("sources", "") not in ("", digest_of(reference_sources(resolve))):
        return False
    tol = {r.get("name"): r.get("tol") for r in validity.get("ranges", [])}
    return all(tol.get(k, v) == v for k, v in ACTUATOR_TOL.items())


def _missing(cfg: GraphConfig) -> list[tuple[str, dict]]:
    """The bank's models to (re)build: missing or stale references, and the hypotheses that
    are missing, stale, or rest on a reference rebuilt now (they are fitted on it)."""
    out = []
    specs = [(e, cfg.resolve_spec(e.model)) for e in cfg.bank]
    specs = [(e, s) for e, s in specs if isinstance(s, dict)]
    rebuilt = set()
    for e, spec in specs:
        if spec.get("type") == "diesel_reference" and not _reference_current(
                Path(spec["path"]), cfg.resolve):
            out.append((e.id, spec))
            rebuilt.add(Path(spec["path"]).resolve())
    for e, spec in specs:
        if spec.get("type") == "diesel_fault_hypothesis" and (
                Path(spec.get("path", ".")).resolve() in rebuilt
                or not _hypothesis_current(spec, next(iter(e.faults), ""))):
            out.append((e.id, spec))
    return out


def build_bank(cfg: GraphConfig, *, progress: bool = True, seed: int = 0,
               log: Callable[[str], None] = print) -> list[str]:
    """Identify every missing reference / hypothesis model of the bank; returns the ids built.

    The simulations are most of the work and need no model: the reference's identification
    cycle and fault-free drive and each hypothesis' faulty identification cycle all start at
    once on every core; the reference is identified here as soon as its two are done (beside
    the hypotheses' simulations still running), then each hypothesis is fitted on it.
    """
    todo = _missing(cfg)
    if not todo:
        return []
    from fdi_ros.core.parallel import process_pool
    from fdi_ros.plants.diesel.identify import (
        REFERENCE_SOURCES,
        REGIME_SOURCES,
        THRESHOLD_SEED,
        THRESHOLD_SOURCES,
        build_reference_models,
    )

    t0 = time.perf_counter()
    built = []
    ident = [str(cfg.resolve(s)) for s in (*REFERENCE_SOURCES, *REGIME_SOURCES)]
    regime_ident = str(cfg.resolve(REGIME_SOURCES[0]))   # the EGR-open regimes' slow passes
    drives = [str(cfg.resolve(s)) for s in THRESHOLD_SOURCES]
    refs = [s for s in todo if s[1]["type"] == "diesel_reference"]
    jobs = []
    for i, (mid, spec) in enumerate(s for s in todo if s[1]["type"] != "diesel_reference"):
        # the fault of this hypothesis: its bank entry's single fault (sized or not)
        fault, size = hypothesis_fault(next(iter(cfg.entry(mid).faults)), spec)
        log(f"[bank] identifying fault hypothesis {mid!r} ({fault} {size:g} "
            f"{FAULT_UNITS[fault]}) -> {spec['hypothesis']}")
        jobs.append((ident[0], regime_ident, mid, spec, fault, size, seed + 500 + i))
    with process_pool() as pool:
        # the reference's data first (cached in build/), then the hypotheses' simulations
        ref_data = [pool.submit(_simulate_reference, job) for job in
                    [(s, seed + i) for i, s in enumerate(ident)]
                    + [(d, THRESHOLD_SEED + i) for i, d in enumerate(drives)]
                    ] if refs else []
        sims = [pool.submit(_simulate_hypothesis, job) for job in jobs]
        for f in ref_data:
            f.result()
        for mid, spec in refs:
            log(f"[bank] identifying the reference models {mid!r} -> {spec['path']}")
            build_reference_models(spec["path"], seed=seed, progress=progress, log=log,
                                   resolve=cfg.resolve)
            built.append(mid)
            log(f"[bank] {mid}: {time.perf_counter() - t0:.1f} s")
        fits = [pool.submit(_fit_hypothesis, (job, f.result())) for job, f in zip(jobs, sims)]
        for f in fits:
            mid, seconds = f.result()
            built.append(mid)
            log(f"[bank] {mid}: {seconds:.1f} s")
    return built


def _simulate_reference(job: tuple[str, int]) -> str:
    """Simulate one scenario of the reference identification into the feature cache (a
    worker process); build_models then finds it there."""
    from fdi_ros.plants.diesel.identify import load_features

    scenario, seed = job
    load_features(scenario, seed=seed)
    return scenario


_Job = tuple[str, str, str, dict, str, float, int]


def _simulate_hypothesis(job: _Job) -> tuple[list[str], float]:
    """Simulate the identification cycle and the EGR-open regimes' slow passes with one
    hypothesis' fault (a worker process) into feature files beside its model; returns (paths,
    seconds)."""
    from fdi_ros.plants.diesel.identify import _write_cache, simulate_features

    scenario, regime_scenario, mid, spec, fault, size, seed = job
    t0 = time.perf_counter()
    paths = []
    for k, (src, name) in enumerate(((scenario, "identification"),
                                     (regime_scenario, "regime_identification"))):
        feats, _ = simulate_features(
            src, seed=seed + 1000 * k, progress=False,
            faults=[FaultEvent(t=5.0, fault=fault, size=size, size_unit=FAULT_UNITS[fault])])
        path = Path(spec["hypothesis"]) / f"{name}_features.npz"
        _write_cache(path, feats)
        if not path.exists():
            raise ValueError(f"{mid}: the simulation of {src} gave no uniform feature vectors "
                             "to identify on")
        paths.append(str(path))
    return paths, time.perf_counter() - t0


def _fit_hypothesis(arg: tuple[_Job, tuple[list[str], float]]) -> tuple[str, float]:
    """Identify one fault hypothesis of the bank on its simulated features and the reference
    (a worker process), save; returns (model id, seconds of simulation and fit)."""
    from fdi_ros.plants.diesel.identify import _read_cache
    from fdi_ros.plants.diesel.reference import ReferenceModelSet
    from fdi_ros.plants.diesel.symptoms import identify_fault_hypothesis, load_symptom_config

    (_scenario, _regime_scenario, mid, spec, fault, size, seed), (paths, sim_s) = arg
    t0 = time.perf_counter()
    mset = ReferenceModelSet.load(spec["path"])
    scfg = load_symptom_config(spec["path"])
    if scfg is None:
        raise ValueError(f"{spec['path']}: no thresholds for the hypothesis {mid!r}")
    feats, regime_feats = (_read_cache(Path(p)) for p in paths)
    for p in paths:
        Path(p).unlink()
    hyp = identify_fault_hypothesis(mset, scfg, feats, fault=fault, size=size, t_from=6.0,
                                    model_id=mid, window=HYPOTHESIS_WINDOW,
                                    regime_features=regime_feats)
    hyp.save(spec["hypothesis"])
    (Path(spec["hypothesis"]) / BUILD_INFO).write_text(json.dumps(
        {"reference": reference_fingerprint(spec["path"]), "fault": fault, "size": size,
         "seed": seed, "window": HYPOTHESIS_WINDOW, "layout": HYPOTHESIS_LAYOUT,
         "regimes": sorted(hyp.regime_directions)}))
    return mid, sim_s + time.perf_counter() - t0


WING = Wing(
    name="diesel",
    runner=DieselRunner,
    preprocessor=DieselPreprocessor,
    kinds={"fdi_ros.plants.diesel.symptoms": ("diesel_reference", "diesel_fault_hypothesis"),
           "fdi_ros.plants.diesel.discrepancy": ("diesel_reference_baseline",)},
    faults=FAULT_IDS,
    validate_fault=validate_fault,
    build_bank=build_bank,
    model_dir_spec=_reference_dir_spec,
    fst=ROOT / "config" / "diesel_fst.yaml",
    reproduce="reproduce diesel",
    figures="figures diesel-plant",
)
