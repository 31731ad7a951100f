"""Identification of the structured residual set on fault-free data only.

Every fault-free record is split in time: the first ``fraction`` identifies the LOLIMOT
models and the thresholds, the rest is held out (false-alarm count). No fault file is used.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fdi_ros.core.lolimot import Lolimot
from fdi_ros.core.measured import Measured
from fdi_ros.plants.liu_ice.residuals import (
    RAW_SIGNALS,
    RESIDUALS,
    Gate,
    MovingAverage,
    ResidualSpec,
    StructuredResiduals,
    derived_signals,
    regressors,
)


@dataclass(frozen=True)
class IdentSettings:
    """How the residual set is identified (all on fault-free data).

    fraction : leading share of each fault-free record used (the rest is held out).
    max_models : LOLIMOT local models per residual (chosen below it by AICc).
    filter_len : moving-average length [samples] of the residuals (20 = 1 s at 20 Hz).
    margin : threshold = margin x the largest filtered excursion seen on the fault-free
        records (identification part and held-out part: the thresholds are set for no false
        alarm there), per speed band ...
    k_sigma : ... but at least k_sigma robust standard deviations ...
    floor : ... and at least this (log units: 0.02 = a 2 % sensor gain).
    bands_rpm : edges of the engine-speed bands with thresholds of their own.
    transient : judge the residuals while the inputs move too, against transient thresholds
        (the same rule on the fault-free records, with the transient filter); else
        transients are "not valid here".
    transient_len : moving-average length [samples] while the inputs move.
    transient_margin : transient threshold = this x the largest transient excursion on the
        fault-free records (wider than ``margin``: transients are fewer and less alike).
    """

    fraction: float = 0.7
    max_models: int = 25
    filter_len: int = 40
    margin: float = 1.1
    k_sigma: float = 5.0
    floor: float = 0.02
    bands_rpm: tuple[float, ...] = (1100.0,)
    gate: Gate = Gate(samples=20, max_throttle=0.3, max_speed=50.0)
    transient: bool = True
    transient_len: int = 10
    transient_margin: float = 1.5

    def __post_init__(self) -> None:
        if not 0.1 <= self.fraction <= 1.0:
            raise ValueError("fraction must be within [0.1, 1]")
        if self.max_models < 1 or self.filter_len < 1:
            raise ValueError("max_models and filter_len must be >= 1")
        if not (self.margin >= 1.0 and self.k_sigma > 0 and self.floor > 0):
            raise ValueError("margin >= 1, k_sigma > 0 and floor > 0 are required")


def signals_of(rec: Measured) -> dict[str, np.ndarray]:
    missing = [k for k in RAW_SIGNALS if k not in rec.signals]
    if missing:
        raise ValueError(f"{rec.source}: the LiU-ICE residuals need signals {missing}")
    return {k: rec[k] for k in RAW_SIGNALS}


def split(rec: Measured, fraction: float) -> tuple[Measured, Measured | None]:
    """(identification part, held-out part or None) of one record, split in time."""
    cut = rec.t[0] + fraction * (rec.t[-1] - rec.t[0])
    ident = rec.window(rec.t[0], cut)
    held = rec.window(cut, rec.t[-1] + 1.0) if fraction < 1.0 else None
    return ident, held


def identify(records: Sequence[Measured], settings: IdentSettings = IdentSettings(), *,
             specs: Sequence[ResidualSpec] = RESIDUALS) -> StructuredResiduals:
    """LOLIMOT model of every residual and fault-free thresholds from the identification
    part of each (fault-free) record."""
    if not records:
        raise ValueError("identification needs at least one fault-free record")
    parts = [split(r, settings.fraction)[0] for r in records]
    sigs = [signals_of(p) for p in parts]
    ds = [derived_signals(s) for s in sigs]
    models: dict[str, Lolimot] = {}
    info: dict[str, Any] = {"fraction": settings.fraction,
                            "records": [r.source for r in records], "models": {}}
    specs = tuple(specs)
    for spec in specs:
        Xs, ys = zip(*(regressors(d, spec) for d in ds))
        X, y = np.vstack(Xs), np.concatenate(ys)
        ok = np.all(np.isfinite(X), axis=1) & np.isfinite(y)
        m = Lolimot(max_models=settings.max_models, coverage_bins=8, patience=4)
        res = m.fit(X[ok], y[ok], input_names=spec.input_names, output_name=spec.target)
        models[spec.name] = m
        info["models"][spec.name] = {"n_models": res.n_models, "train_rmse": res.train_rmse,
                                     "samples": int(ok.sum()), "dynamic": spec.dynamic,
                                     "inputs": list(spec.input_names), "uses": list(spec.uses)}
    n_res = len(specs)
    nb = len(settings.bands_rpm) + 1
    proto = StructuredResiduals(models=models, centre=(0.0,) * n_res,
                                threshold=((1.0,) * n_res,) * nb,
                                filter_len=settings.filter_len, gate=settings.gate,
                                bands_rpm=settings.bands_rpm, specs=specs,
                                transient_len=settings.transient_len)
    F = np.vstack([proto.filtered(s)[0] for s in sigs])
    ok = np.all(np.isfinite(F), axis=1)
    if ok.sum() < 100:
        raise ValueError(f"only {int(ok.sum())} valid identification samples: too few")
    c = np.median(F[ok], axis=0)
    # excursions over every fault-free sample: identification and held-out parts
    allsig = sigs + [signals_of(h) for h in (split(r, settings.fraction)[1] for r in records)
                     if h is not None]
    e_parts, b_parts = [], []
    for s in allsig:
        Fs = proto.filtered(s)[0]
        keep = np.all(np.isfinite(Fs), axis=1)
        e_parts.append(np.abs(Fs[keep] - c))
        b_parts.append(proto.band(s["n"][keep]))
    E, B = np.vstack(e_parts), np.concatenate(b_parts)
    thr, std, top = [], [], []
    for b in range(nb):
        Eb = E[b == B] if np.any(b == B) else E
        sb = 1.4826 * np.median(Eb, axis=0)
        std.append(sb.tolist())
        top.append(Eb.max(axis=0).tolist())
        thr.append(tuple(float(x) for x in np.maximum.reduce(
            [settings.k_sigma * sb, settings.margin * Eb.max(axis=0),
             np.full(n_res, settings.floor)])))
    thr_t = None
    if settings.transient:
        et_parts, bt_parts = [], []
        for s in allsig:
            Ft, settled, inside = proto.transient_filtered(s)
            keep = inside & ~settled & np.all(np.isfinite(Ft), axis=1)
            et_parts.append(np.abs(Ft[keep] - c))
            bt_parts.append(proto.band(s["n"][keep]))
        Et, Bt = np.vstack(et_parts), np.concatenate(bt_parts)
        thr_t = []
        for b in range(nb):
            Eb = Et[Bt == b] if np.any(Bt == b) else Et
            thr_t.append(tuple(float(x) for x in np.maximum(
                settings.transient_margin * Eb.max(axis=0), np.asarray(thr[b]))))
        info["max_excursion_transient"] = [list(r) for r in thr_t]
    info.update({"valid_samples": int(ok.sum()), "robust_std": std, "max_excursion": top,
                 "settings": {k: v for k, v in settings.__dict__.items() if k != "gate"},
                 "gate": settings.gate.__dict__})
    return StructuredResiduals(models=models, centre=tuple(float(x) for x in c),
                               threshold=tuple(thr), bands_rpm=settings.bands_rpm,
                               filter_len=settings.filter_len, gate=settings.gate, info=info,
                               specs=specs,
                               threshold_transient=None if thr_t is None else tuple(thr_t),
                               transient_len=settings.transient_len)


__all__ = ["IdentSettings", "MovingAverage", "identify", "signals_of", "split"]
