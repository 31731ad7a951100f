"""Offline diagnosis of bags: one bag, or many at once on a local process pool or a Dask
cluster, and a fleet report.

``diagnose_bag`` is the whole of ``fdi-ros diagnose BAG`` for one bag (bag -> features ->
bank -> diagnosis summary); :func:`diagnose_fleet` maps it over bags serially, on a pool of
local processes, or on Dask distributed (a ``LocalCluster`` of worker processes on loopback,
or an existing cluster given by its scheduler address). Every way gives each bag the same
result; only ``wall_seconds`` and ``realtime_factor`` (that bag's own timing) differ.

Dask rather than Ray, measured on this project's 2-core machines: the ``distributed`` wheel
and its dependencies add 46 MB to the venv against Ray's 261 MB; a local cluster of two worker
processes starts in about 2 s (Ray's local instance in about 6 s) and shuts down in 0.5 s
(1.3 s); per-task overhead (3 ms against 1 ms) is small beside a bag's seconds.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from fdi_ros.core.parallel import map_processes, single_threaded_numerics

TIMING_KEYS = ("wall_seconds", "realtime_factor")
ENGINES = ("local", "dask")


def default_config(plant: str) -> Path:
    root = Path(__file__).resolve().parents[1]
    return root / "config" / f"{plant}.yaml"


def features_of_bag(path: str | Path) -> tuple[str, list]:
    """(plant, feature vectors) of a bag: recomputed from the sensor blocks when present."""
    from fdi_ros import bag
    from fdi_ros.plants import make_preprocessor

    tops = bag.topics(path)
    if "/fdi/sensor_block" in tops:
        blocks = bag.read_blocks(path)
        if not blocks:
            raise ValueError(f"{path}: /fdi/sensor_block is empty")
        pre = make_preprocessor(blocks[0].plant)
        push_many = getattr(pre, "push_many", None)
        if callable(push_many):   # the whole stream in one pass (same features)
            return blocks[0].plant, list(push_many(blocks))
        feats, last = [], None
        for b in blocks:
            if last is not None and b.index != last + 1:
                pre.mark_gap()
            last = b.index
            feats.extend(pre.push(b))
        return blocks[0].plant, feats
    if "/fdi/features" in tops:
        feats = bag.read_features(path)
        if not feats:
            raise ValueError(f"{path}: /fdi/features is empty")
        return feats[0].plant, feats
    raise ValueError(f"{path}: neither /fdi/sensor_block nor /fdi/features in the bag "
                     f"(topics: {sorted(tops)})")


def valid_diagnosis(step: Any) -> bool:
    """The segment got a valid diagnosis: the reference model's symptoms were valid there (or,
    without a symptom stage, the supervisor had enough valid residuals)."""
    if step.symptoms is not None:
        return bool(step.symptoms.valid)
    return bool(step.diagnosis.state != "not_valid")


def not_valid_reasons(steps: list, most: int = 8) -> dict[str, int]:
    """Why segments got no valid diagnosis: the symptom stage's "not valid" statuses with the
    numbers replaced by ``#`` (e.g. ``not valid here: egr_cmd = # outside the identified
    region (held at #)``), counted, most frequent first."""
    import re
    from collections import Counter

    why: Counter[str] = Counter()
    for _fv, _res, step in steps:
        if not valid_diagnosis(step):
            status = step.symptoms.status if step.symptoms is not None else "not_valid"
            why[re.sub(r"-?\d+(?:\.\d+)?(?:e[-+]?\d+)?", "#", status or "not valid")] += 1
    return dict(why.most_common(most))


def summarise(steps: list, plant_seconds: float, wall_seconds: float, truth: list) -> dict:
    from fdi_ros.core.events import diagnosis_events

    events = diagnosis_events(step.diagnosis for _fv, _res, step in steps)
    first_symptom: dict[str, float] = {}
    for _fv, _res, step in steps:
        d = step.diagnosis
        s = step.symptoms
        if s is not None and s.valid:
            for name, lvl in zip(s.names, s.levels):
                if lvl and name not in first_symptom:
                    first_symptom[name] = round(d.t, 4)
    final = steps[-1][2].diagnosis if steps else None
    n_valid = sum(1 for _fv, _res, step in steps if valid_diagnosis(step))
    onset = min((e.t for e in truth if e.active and e.fault), default=math.nan)
    # Detection episodes: a detection either ends in an isolation (confirmed), is still open
    # at the end, or falls back to "no fault" (cleared: a transient the hold time T0 rejected).
    episodes: list[dict] = []
    for fv, _res, step in steps:
        st = step.diagnosis.state
        if st == "detected" and (not episodes or episodes[-1]["end"] is not None):
            episodes.append({"t": round(fv.t_end, 4), "end": None})
        elif episodes and episodes[-1]["end"] is None and st in ("isolated", "no_fault"):
            episodes[-1]["end"] = "isolated" if st == "isolated" else "cleared"
    kept = [e for e in episodes if e["end"] != "cleared"]
    det = kept[0]["t"] if kept else (final.detection_time if final and final.state == "isolated"
                                      else math.nan)

    def delay(t: float) -> float | None:
        return None if math.isnan(t) or math.isnan(onset) else round(t - onset, 4)

    iso = final.isolation_time if final else math.nan
    return {
        "segments": len(steps),
        "plant_seconds": round(plant_seconds, 3),
        "wall_seconds": round(wall_seconds, 3),
        "realtime_factor": round(plant_seconds / wall_seconds, 1) if wall_seconds > 0 else None,
        "fault_truth": [{"t": e.t, "fault": e.fault, "size": e.size, "unit": e.size_unit}
                        for e in truth],
        "detected": not math.isnan(det),
        "cleared_detections_s": [e["t"] for e in episodes if e["end"] == "cleared"],
        "detection_time_s": None if math.isnan(det) else round(det, 4),
        "detection_delay_s": delay(det),
        "isolated_faults": list(final.isolated_faults) if final else [],
        "fault_model": final.fault_model if final else "",
        "isolation_time_s": None if not final or math.isnan(iso) else round(iso, 4),
        "isolation_delay_s": delay(iso),
        "first_symptom_s": first_symptom,
        "models_online": list(final.models_online) if final else [],
        "invalid_segments": sum(1 for fv, _, _ in steps if not fv.valid),
        "valid_segments": n_valid,
        "coverage": round(n_valid / len(steps), 4) if steps else None,
        "not_valid_reasons": not_valid_reasons(steps),
        "events": events,
    }


def diagnose_bag(path: str | Path, config: str | None = None, *,
                 progress: bool = False) -> dict[str, Any]:
    """``fdi-ros diagnose BAG --json`` for one bag (the JSON summary as a dict)."""
    from fdi_ros import bag
    from fdi_ros.core.diagnoser import diagnose_offline
    from fdi_ros.core.graphconfig import load_graph_config

    t0 = time.perf_counter()
    with _one_numerics_thread():
        plant, feats = features_of_bag(path)
        cfg = load_graph_config(config or default_config(plant))
        steps = diagnose_offline(cfg, feats, progress=progress)
    wall = time.perf_counter() - t0
    truth = bag.read_faults(path) if "/fdi/fault_truth" in bag.topics(path) else []
    span = (feats[-1].t_end - feats[0].t_start) if feats else 0.0
    return {"bag": str(path), "plant": plant, "config": str(cfg.path),
            **summarise(steps, span, wall, truth)}


def _one(args: tuple[str, str | None]) -> dict[str, Any]:
    """A bag's result, or ``{"bag", "error"}`` (a bad bag does not stop the fleet)."""
    path, config = args
    try:
        return diagnose_bag(path, config)
    except Exception as exc:  # reported per bag, as the single-bag command reports it
        return {"bag": str(path), "error": f"{type(exc).__name__}: {exc}"}


def _one_numerics_thread() -> Any:
    """One BLAS thread for the while: the products here are small and many, and a second
    thread costs more than it brings on a busy 2-core machine (measured: 10-15 % less time)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        import contextlib

        return contextlib.nullcontext()
    return threadpool_limits(1)


def _bag_size(path: str) -> int:
    try:
        return sum(f.stat().st_size for f in Path(path).glob("*.mcap"))
    except OSError:
        return 0


def _local_pool(items: list[tuple[str, str | None]], workers: int) -> list[dict[str, Any]]:
    """The bags on ``workers`` local processes, the largest first (the pool stays busy to
    the end); forked where the platform can (no start-up imports), else spawned."""
    import gc
    import multiprocessing as mp

    fork = "fork" in mp.get_all_start_methods()
    if fork:   # the workers inherit the modules instead of importing them each
        import fdi_ros.core.diagnoser  # noqa: F401
        import fdi_ros.core.graphconfig  # noqa: F401
        import fdi_ros.plants  # noqa: F401

        # the parent's objects out of the collector's reach while the workers run: a
        # collection in a forked worker writes to every object it walks, which copies the
        # parent's pages (four bags on two workers, measured in one process: 1.38-1.69 s ->
        # 1.27-1.30 s)
        gc.collect()
        gc.freeze()
    order = sorted(range(len(items)), key=lambda i: -_bag_size(items[i][0]))
    try:
        return map_processes(_one, items, workers=workers, method="fork" if fork else "spawn",
                             order=order)
    finally:
        if fork:
            gc.unfreeze()


def local_dask_cluster(workers: int) -> Any:
    """A Dask ``LocalCluster`` of ``workers`` single-threaded worker processes, scheduler,
    nannies and workers listening on 127.0.0.1 only, no dashboard."""
    import logging

    from dask.distributed import LocalCluster

    return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                        host="127.0.0.1", dashboard_address=None, scheduler_port=0,
                        worker_dashboard_address=None, silence_logs=logging.ERROR)


def _dask(items: list[tuple[str, str | None]], workers: int,
          address: str | None) -> list[dict[str, Any]]:
    try:
        from dask.distributed import Client
    except ImportError:
        raise ValueError("--engine dask needs the optional dependency: "
                         "pip install 'dask[distributed]' (scripts/setup.sh installs it)"
                         ) from None
    cluster = None if address else local_dask_cluster(workers)
    client = Client(address) if address else Client(cluster)
    try:
        client.run(single_threaded_numerics)
        futures = client.map(_one, items, pure=False)
        return list(client.gather(futures))
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def diagnose_fleet(bags: Sequence[str | Path], *, workers: int = 1, engine: str = "local",
                   cluster: str | None = None,
                   config: str | None = None) -> dict[str, dict[str, Any]]:
    """Bag -> its single-bag result (or ``{"bag", "error"}``), in the order given.

    ``workers`` 1 runs in this process; more: a local process pool (``engine="local"``) or a
    Dask cluster (``engine="dask"``: a local one of ``workers`` processes, or the scheduler
    at ``cluster``)."""
    if workers < 1:
        raise ValueError("--workers must be >= 1")
    if engine not in ENGINES:
        raise ValueError(f"--engine must be one of {ENGINES}")
    if len(set(map(str, bags))) != len(bags):
        raise ValueError("a bag is given twice")
    items = [(str(b), config) for b in bags]
    if cluster or engine == "dask":
        results = _dask(items, workers, cluster)
    elif workers == 1 or len(items) == 1:
        results = [_one(it) for it in items]
    else:
        results = _local_pool(items, min(workers, len(items)))
    return {str(b): r for b, r in zip(bags, results)}


def without_timing(result: dict[str, Any]) -> dict[str, Any]:
    """A bag's result without its own timing (what equal runs share exactly)."""
    return {k: v for k, v in result.items() if k not in TIMING_KEYS}


# -- the fleet report ------------------------------------------------------------------------
def _faults(r: dict[str, Any]) -> list[str]:
    """Faults isolated in a bag, in order of first isolation (from its events)."""
    seen: list[str] = []
    for e in r.get("events", []):
        if e.get("state") == "isolated":
            f = e.get("fault_model", "")
            if f and f not in seen:
                seen.append(f)
    for f in r.get("isolated_faults", []):
        if f not in seen:
            seen.append(f)
    return seen


def _row(name: str, r: dict[str, Any]) -> dict[str, Any]:
    def num(v: Any) -> str:
        return "" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:g}"

    truth = sorted({e["fault"] for e in r.get("fault_truth", []) if e.get("fault")})
    return {"bag": name, "plant": r.get("plant", ""), "segments": r.get("segments", ""),
            "plant_s": num(r.get("plant_seconds")), "truth": " ".join(truth),
            "faults_isolated": " ".join(_faults(r)),
            "detection_s": num(r.get("detection_time_s")),
            "isolation_s": num(r.get("isolation_time_s")),
            "isolation_delay_s": num(r.get("isolation_delay_s")),
            "invalid_segments": r.get("invalid_segments", ""),
            "coverage": r.get("coverage", ""),
            "error": r.get("error", "")}


def write_report(results: dict[str, dict[str, Any]], out_dir: str | Path, *,
                 title: str = "Fleet diagnosis") -> dict[str, str]:
    """``fleet.csv``, ``fleet.md`` (one row per bag) and ``faults_per_bag.png`` (faults
    isolated per bag, by fault, beside the faults the bag's ground truth names)."""
    import csv

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    rows = [_row(Path(b).name or b, r) for b, r in results.items()]
    cols = list(rows[0]) if rows else list(_row("", {}))
    with (d / "fleet.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        w.writerows(rows)
    lines = [f"# {title}", "", f"{len(rows)} bags, "
             f"{sum(1 for r in results.values() if _faults(r))} with a fault isolated, "
             f"{sum(1 for r in results.values() if 'error' in r)} not readable.", "",
             "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(str(r[c]) for c in cols) + " |" for r in rows]
    (d / "fleet.md").write_text("\n".join(lines) + "\n")

    names = [r["bag"] for r in rows]
    faults = sorted({f for r in results.values() for f in _faults(r)})
    fig, ax = plt.subplots(figsize=(10, 1.2 + 0.45 * max(len(names), 1)))
    left = [0] * len(names)
    colours = plt.get_cmap("tab10")
    for j, f in enumerate(faults):
        vals = [1 if f in _faults(r) else 0 for r in results.values()]
        ax.barh(names, vals, left=left, color=colours(j % 10), label=f)
        left = [a + b for a, b in zip(left, vals)]
    truth = [len({e["fault"] for e in r.get("fault_truth", []) if e.get("fault")})
             for r in results.values()]
    ax.scatter(truth, names, marker="|", s=300, color="black", zorder=3,
               label="faults in the ground truth")
    ax.set_xlabel("faults isolated")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_title(title)
    ax.invert_yaxis()
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    fig.savefig(d / "faults_per_bag.png", dpi=110)
    plt.close(fig)
    return {"csv": str(d / "fleet.csv"), "markdown": str(d / "fleet.md"),
            "plot": str(d / "faults_per_bag.png")}
