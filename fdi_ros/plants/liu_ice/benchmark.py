"""The LiU-ICE benchmark: identify on fault-free data, diagnose every file with the graph's
core (:func:`fdi_ros.core.diagnoser.diagnose_offline`), score per sample as DX 2025 did."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from fdi_ros.core.scoring import Score, combine, score
from fdi_ros.plants.liu_ice import FAULT_FREE, FileTruth, truth_of
from fdi_ros.plants.liu_ice.identify import IdentSettings, identify, split
from fdi_ros.plants.liu_ice.live import LiuIcePreprocessor, blocks_of, load_record
from fdi_ros.plants.liu_ice.residuals import (
    ResidualStream,
    StructuredResidualModel,
    StructuredResiduals,
)


@dataclass
class FileResult:
    name: str
    truth: FileTruth
    t: np.ndarray
    detected: np.ndarray
    isolated: np.ndarray
    counted: np.ndarray
    score: Score
    wall_s: float
    events: list = field(default_factory=list)

    def as_dict(self) -> dict:
        tr = self.truth
        d = {"file": self.name, "fault": tr.fault or None,
             "onset_s": None if math.isnan(tr.onset_s) else tr.onset_s,
             "samples": int(self.t.size), "scored_samples": int(self.counted.sum()),
             **self.score.as_dict(),
             "run_time_per_sample_ms": round(1e3 * self.wall_s / max(self.t.size, 1), 4),
             "events": self.events}
        if tr.fault:
            d["size"] = tr.size
            d["size_unit"] = tr.size_unit
        return d


def bank_models(cfg, rs: StructuredResiduals) -> dict[str, StructuredResidualModel]:
    """Fresh models of the bank over one new residual stream (one stream per file)."""
    stream = ResidualStream(rs)
    out = {}
    for e in cfg.bank:
        extra = {k: float(e.model[k]) for k in ("quiet_penalty", "max_gain_log")
                 if k in e.model}
        out[e.id] = StructuredResidualModel(stream=stream, model_id=e.id,
                                            fault=str(e.model.get("fault", "") or ""), **extra)
    return out


def diagnose_record(cfg, rs: StructuredResiduals, rec, *, block_samples: int = 10):
    """Per-sample (t, detected, isolated) and the supervisor's events for one record, through
    the same preprocessor, bank models and diagnoser as the graph."""
    from fdi_ros.core.diagnoser import diagnose_offline

    pre = LiuIcePreprocessor()
    feats = [fv for b in blocks_of(rec, block_samples) for fv in pre.push(b)]
    steps = diagnose_offline(cfg, feats, models=bank_models(cfg, rs))
    t = np.array([fv.t_end for fv, _, _ in steps])
    det = np.array([s.diagnosis.state in ("detected", "isolated") for _, _, s in steps])
    iso = np.array([(s.diagnosis.isolated_faults[0] if s.diagnosis.state == "isolated"
                     and s.diagnosis.isolated_faults else "") for _, _, s in steps],
                   dtype=object)
    events, last = [], None
    for _, _, s in steps:
        d = s.diagnosis
        if d.state != last:
            events.append({"t": round(d.t, 3), "state": d.state,
                           "isolated": list(d.isolated_faults)})
            last = d.state
    return t, det, iso, events


def apply_gain(rec, signal: str, gain: float, onset_s: float):
    """A copy of the record whose ``signal`` reads ``gain`` x the true value from the onset on
    (as the benchmark's engine control unit injects its sensor gain faults)."""
    from fdi_ros.core.measured import Measured

    sig = dict(rec.signals)
    x = np.asarray(sig[signal], dtype=float).copy()
    x[rec.t >= onset_s] *= gain
    sig[signal] = x
    return Measured(t=rec.t, signals=sig, units=dict(rec.units), alpha=rec.alpha,
                    segment=rec.segment, source=f"{rec.source} ({signal} x {gain:g} from "
                    f"{onset_s:g} s)", mapped=rec.mapped)


def run_benchmark(data_dir: str | Path, *, config: str | Path, models_dir: str | Path,
                  settings: IdentSettings | None = None,
                  say: Callable[[str], None] = lambda s: None,
                  files: list[str] | None = None) -> tuple[dict, list[FileResult]]:
    """Identify on the fault-free files, diagnose every CSV of ``data_dir``, score."""
    from fdi_ros.core.graphconfig import load_graph_config

    settings = settings or IdentSettings()
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise FileNotFoundError(f"benchmark data directory {data_dir} not found")
    names = files or sorted(p.name for p in data_dir.glob("*.csv"))
    if not names:
        raise ValueError(f"{data_dir}: no CSV files")
    nf = [f for f in FAULT_FREE if (data_dir / f).is_file()]
    if not nf:
        raise ValueError(f"{data_dir}: none of the fault-free files {FAULT_FREE}")
    records = {n: load_record(data_dir / n) for n in set(names) | set(nf)}
    t0 = time.perf_counter()
    rs = identify([records[f] for f in nf], settings)
    rs.save(models_dir)
    ident_s = time.perf_counter() - t0
    say(f"identified {len(rs.specs)} residual models on the first {settings.fraction:.0%} of "
        f"{', '.join(nf)} in {ident_s:.1f} s -> {models_dir}")
    cfg = load_graph_config(config)
    cfg = replace(cfg, bank=tuple(replace(e, model={**e.model, "path": str(models_dir)})
                                  for e in cfg.bank))
    results = []
    for name in names:
        rec = records[name]
        truth = truth_of(name)
        w0 = time.perf_counter()
        t, det, iso, events = diagnose_record(cfg, rs, rec)
        wall = time.perf_counter() - w0
        counted = np.ones(t.size, dtype=bool)
        if not truth.faulty and name in nf:
            ident_part = split(rec, settings.fraction)[0]
            counted = t > ident_part.t[-1]   # only the held-out part counts
        sc = score(t, det, iso, truth.fault, truth.onset_s, counted)
        results.append(FileResult(name, truth, t, det, iso, counted, sc, wall, events))
        say(f"{name:28s} FAR {_pct(sc.false_alarm_rate)} TDR {_pct(sc.true_detection_rate)} "
            f"FIA {_pct(sc.isolation_accuracy)} delay {sc.detection_delay_s}")
    faulty = [r.score for r in results if r.truth.faulty]
    overall = combine([r.score for r in results])
    doc = {
        "benchmark": "LiU-ICE (arXiv:2408.13269), DX 2025 metrics, per sample",
        "data_dir": str(data_dir),
        "identification": {"files": nf, "part": f"first {settings.fraction:.0%} of each "
                           "fault-free file (the rest is held out and scored)",
                           "seconds": round(ident_s, 2), "models": rs.info["models"],
                           "thresholds_log": [list(r) for r in rs.threshold],
                           "speed_bands_rpm": list(rs.bands_rpm)},
        "fault_symptom_table": {"residuals": list(rs.names),
                                "columns": {f: list(c) for f, c in rs.table.items()},
                                "uses": {s.name: list(s.uses) for s in rs.specs}},
        "overall": {**overall.as_dict(),
                    "run_time_per_sample_ms": round(1e3 * sum(r.wall_s for r in results)
                                                    / max(sum(r.t.size for r in results), 1),
                                                    4)},
        "fault_files": combine(faulty).as_dict() if faulty else None,
        "files": [r.as_dict() for r in results],
    }
    return doc, results


def _pct(x: float | None) -> str:
    return "   -  " if x is None else f"{100 * x:5.1f}%"


def write_per_sample(path: str | Path, results: list[FileResult]) -> None:
    """CSV ``file,time,detected,isolated``, one row per diagnosed sample."""
    import csv

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    with open(p, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["file", "time", "detected", "isolated"])
        for r in results:
            for t, d, i in zip(r.t, r.detected, r.isolated):
                w.writerow([r.name, f"{t:.4f}", int(bool(d)), i])
