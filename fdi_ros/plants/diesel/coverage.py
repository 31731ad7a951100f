"""How much of a drive the diesel diagnosis watches: valid segments per operating region, the
reasons for the rest, false symptoms, and a map of coverage over speed and load.

On-board diagnosis is judged by the share of real driving it watches without false alarms (OBD
rules set a minimum in-use monitor performance ratio). The regions are those of the ECU's
actuator maps: EGR open with the swirl flaps closed (low speed, part load), EGR open with the
flaps open (part load), EGR closed (full load, high speed) and overrun (no torque).
"""

from __future__ import annotations

import dataclasses
import sys
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["REGIONS", "coverage_figure", "coverage_report", "fault_case_report", "fault_effect",
           "observable", "realistic_drive", "reason_class", "region_of"]

REGIONS = ("egr_open_flaps_closed", "egr_open_flaps_open", "egr_closed", "overrun")


def region_of(fv) -> str:
    """Operating region of one segment from its speed, fuel and actuator commands."""
    names = fv.names
    egr = fv.get("egr_cmd") if "egr_cmd" in names else 0.0
    swirl = fv.get("swirl_cmd") if "swirl_cmd" in names else 0.0
    fuel = fv.get("fuel") if "fuel" in names else np.inf
    if fuel < 4.0:
        return "overrun"
    if egr > 0.002:   # the EGR valve's tolerance of the validity (a 1 mm hole)
        return "egr_open_flaps_closed" if swirl > 0.5 else "egr_open_flaps_open"
    return "egr_closed"


def reason_class(status: str) -> str:
    """The kind of a "not valid" status (the numbers stripped)."""
    s = status.lower()
    for key, label in (("changing too fast", "temperature changing too fast"),
                       ("transient", "transient inputs"), ("settling", "settling"),
                       ("rate unknown", "settling"),
                       ("egr_cmd", "EGR command outside the identified region"),
                       ("swirl_cmd", "swirl command outside the identified region"),
                       ("operating point", "(n, rho2) outside the identified coverage"),
                       ("nearly balanced", "EGR valve nearly balanced"),
                       ("n = ", "speed outside the identified range"),
                       ("rho2 = ", "boost density outside the identified range"),
                       ("feature", "features not valid")):
        if key in s:
            return label
    return status or "not valid"


def coverage_report(features: Sequence, states: Sequence) -> dict[str, Any]:
    """Valid share of the segments per region, the reasons of the invalid ones and the false
    symptom count (``states``: the nominal model's SymptomStates, fault-free data)."""
    regions = [region_of(fv) for fv in features]
    valid = np.array([s.valid for s in states], dtype=bool)
    sym = np.array([s.valid and any(s.levels) for s in states], dtype=bool)
    out: dict[str, Any] = {"segments": len(states), "valid_segments": int(valid.sum()),
                           "coverage": round(float(valid.mean()), 4) if len(states) else None,
                           "false_symptom_segments": int(sym.sum()),
                           "false_symptom_onsets": int(np.sum(sym[1:] & ~sym[:-1])
                                                       + (sym[0] if sym.size else 0)),
                           "regions": {}}
    for r in REGIONS:
        idx = [i for i, g in enumerate(regions) if g == r]
        if not idx:
            continue
        out["regions"][r] = {"segments": len(idx),
                             "share_of_drive": round(len(idx) / len(regions), 4),
                             "coverage": round(float(valid[idx].mean()), 4),
                             "false_symptom_segments": int(sym[idx].sum())}
    why = Counter(reason_class(s.status) for s in states if not s.valid)
    out["not_valid_reasons"] = dict(why.most_common())
    return out


# The coverage figure's cells: 250 rpm x 2 mg fuel
SPEED_BINS = np.arange(750.0, 5750.0, 250.0)
FUEL_BINS = np.arange(0.0, 48.0, 2.0)


def coverage_cells(features: Sequence, states: Sequence) -> dict[str, np.ndarray]:
    """Per cell of :data:`SPEED_BINS` x :data:`FUEL_BINS`: the segments (``count``), the
    share with a valid diagnosis (``share``) and how many residuals the valid ones are judged
    on, on average (``judged``: a residual not judged in a regime has no finite threshold);
    NaN where a cell has no segment (no valid one for ``judged``)."""
    n = np.array([fv.get("n") for fv in features])
    fuel = np.array([fv.get("fuel") if "fuel" in fv.names else np.nan for fv in features])
    valid = np.array([s.valid for s in states], dtype=float)
    judged = np.array([np.isfinite(s.threshold_high).sum() if s.valid else 0.0
                       for s in states], dtype=float)
    bins = (SPEED_BINS, FUEL_BINS)
    cnt, _, _ = np.histogram2d(n, fuel, bins=bins)
    ok, _, _ = np.histogram2d(n, fuel, bins=bins, weights=valid)
    jn, _, _ = np.histogram2d(n, fuel, bins=bins, weights=judged)
    return {"count": cnt, "share": np.where(cnt > 0, ok / np.maximum(cnt, 1), np.nan),
            "judged": np.where(ok > 0, jn / np.maximum(ok, 1), np.nan)}


def coverage_figure(features: Sequence, states: Sequence, path: str | Path, *,
                    title: str = "") -> Path:
    """Share of valid segments over the speed-torque map (bins of 250 rpm x 2 mg fuel), with
    the segments' count as the marker size; beside it, how many residuals the valid segments
    are judged on there (the EGR-open regimes judge eta_V alone, or with the pulsations where
    the EGR-closed maps cover them: which faults can show where)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = coverage_cells(features, states)
    nb, fb, cnt = SPEED_BINS, FUEL_BINS, cells["count"]
    share, mean_judged = cells["share"], cells["judged"]
    valid = np.array([s.valid for s in states], dtype=float)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(15, 5))
    mesh = ax.pcolormesh(nb, fb, share.T, cmap="RdYlGn", vmin=0.0, vmax=1.0, shading="flat")
    fig.colorbar(mesh, ax=ax, label="share of segments with a valid diagnosis")
    m2 = bx.pcolormesh(nb, fb, mean_judged.T, cmap="viridis", vmin=0.0,
                       vmax=float(len(states[0].names)) if states else 5.0, shading="flat")
    fig.colorbar(m2, ax=bx, label="residuals judged (mean over the valid segments)")
    bx.set_xlabel("engine speed n [rpm]")
    bx.set_ylabel("injected fuel [mg/stroke] (load)")
    bx.set_title("what is judged where (1: eta_V alone, 5: eta_V and the pulsations)")
    # how much of the drive each cell holds: a cell crossed in a transient is as coloured as
    # one the engine cruises in
    cn, cf = np.meshgrid(0.5 * (nb[:-1] + nb[1:]), 0.5 * (fb[:-1] + fb[1:]), indexing="ij")
    has = cnt > 0
    ax.scatter(cn[has], cf[has], s=120.0 * np.sqrt(cnt[has] / cnt.max()), facecolors="none",
               edgecolors="k", linewidths=0.6, label="segments in the cell (area)")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_xlabel("engine speed n [rpm]")
    ax.set_ylabel("injected fuel [mg/stroke] (load)")
    ax.set_title(title or f"diagnosis coverage: {valid.mean():.1%} of {len(states)} segments")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


REALISTIC_DRIVE = "config/scenarios/diesel_realistic_drive.yaml"


def observable(fault: str, size: float, fv) -> bool:
    """Whether the fault can change anything at this segment's actuator commands: a valve stuck
    at ``size`` while the ECU opens it further, or flaps stuck closed while the ECU closes them,
    leave the plant as it is."""
    names = fv.names
    if fault == "egr_stuck_open" and "egr_cmd" in names:
        return bool(fv.get("egr_cmd") < size)
    if fault == "swirl_flap_closed" and "swirl_cmd" in names:
        return bool(fv.get("swirl_cmd") < min(size, 1.0) - 0.02)
    return True


def fault_effect(fault_states: Sequence, free_states: Sequence
                 ) -> tuple[np.ndarray, np.ndarray]:
    """What a fault changes, per segment, against its fault-free twin (the same drive and seed:
    the same noise, so the difference is the fault's alone): ``effect``, its largest change
    of a residual judged there in units of the residual's threshold (filtered residuals; NaN
    where either run is not valid or the two are in different regimes, a regime's residuals
    being relative to its own maps), and ``shown``, whether the fault's run crosses a
    threshold the twin stays within. A perfect detector with these thresholds sees the fault
    from its first ``shown`` segment on, and in no segment that is not."""
    if len(fault_states) != len(free_states):
        raise ValueError(f"fault run and twin differ in length ({len(fault_states)} vs "
                         f"{len(free_states)} segments): not the same drive")
    effect = np.full(len(fault_states), np.nan)
    shown = np.zeros(len(fault_states), dtype=bool)
    for k, (a, b) in enumerate(zip(fault_states, free_states)):
        if not (a.valid and b.valid and a.regime == b.regime):
            continue
        hi, lo = np.asarray(a.threshold_high, float), np.asarray(a.threshold_low, float)
        judged = np.isfinite(hi) & np.isfinite(lo) & (hi > lo)   # not judged: infinite
        if not judged.any():
            continue
        half, mid = 0.5 * (hi[judged] - lo[judged]), 0.5 * (hi[judged] + lo[judged])
        xa = (np.asarray(a.residuals, float)[judged] - mid) / half
        xb = (np.asarray(b.residuals, float)[judged] - mid) / half
        effect[k] = float(np.nanmax(np.abs(xa - xb), initial=0.0))
        shown[k] = bool(np.any((np.abs(xa) > 1.0) & ~(np.abs(xb) > 1.0)))
    return effect, shown


def fault_case_report(steps: Sequence, features: Sequence, fault: str, onset: float,
                      *, max_segments: int = 5, size: float = 1.0,
                      effect: tuple[np.ndarray, np.ndarray] | None = None
                      ) -> dict[str, Any]:
    """Detection and isolation of one fault opened at ``onset`` [s] (``steps``: the
    diagnoser's steps over ``features``). The delay counts the segments with a valid diagnosis
    from the onset on (a segment the models do not cover cannot detect anything).

    ``effect`` (:func:`fault_effect` against the fault-free twin: (effect, shown)) adds when
    the fault first showed (crossed a threshold the twin stays within), how many such
    segments passed before the detection (``detectable_segments_to_detection``: the
    detector's own delay, the operating point's aside), the share of the valid segments after
    the onset where it showed, and its largest effect in threshold units."""
    k0 = next((i for i, fv in enumerate(features) if fv.t_end > onset), len(features))
    before = sum(1 for _, _, s in steps[:k0] if s.symptoms.valid and any(s.symptoms.levels))
    valid_seen, det = 0, None
    for i in range(k0, len(steps)):
        s = steps[i][2].symptoms
        if s.valid:
            valid_seen += 1
            if any(s.levels):
                det = i
                break
    final = steps[-1][2].diagnosis if steps else None
    iso = list(final.isolated_faults) if final else []
    first_valid = next((i for i in range(k0, len(steps)) if steps[i][2].symptoms.valid), None)
    out: dict[str, Any] = {"fault": fault, "onset_s": round(onset, 2),
            "false_symptom_segments_before": before,
            "first_valid_after_onset_s": None if first_valid is None else
            round(features[first_valid].t_end - onset, 3),
            "detected": det is not None,
            "delay_valid_segments": valid_seen if det is not None else None,
            "delay_s": None if det is None else round(features[det].t_end - onset, 3),
            "within_segments": det is not None and valid_seen <= max_segments,
            "signature": steps[det][2].symptoms.signature if det is not None else None,
            "isolated": iso, "isolated_correctly": iso == [fault],
            "region_at_onset": region_of(features[min(k0, len(features) - 1)]),
            "observable_at_onset": observable(fault, size, features[min(k0, len(features) - 1)])}
    if effect is not None:
        e, shown = (np.asarray(x)[k0:] for x in effect)
        seen = np.flatnonzero(shown)
        valid_after = sum(1 for _, _, st in steps[k0:] if st.symptoms.valid)
        before_det = int(np.sum(shown[:det - k0])) if det is not None else None
        out.update({
            "first_detectable_after_onset_s": None if not seen.size else
            round(features[k0 + int(seen[0])].t_end - onset, 3),
            "detectable_segments_to_detection": before_det,
            "within_segments_detectable": before_det is not None and before_det < max_segments,
            "detectable_share": round(seen.size / valid_after, 4) if valid_after else None,
            "max_effect": None if not np.isfinite(e).any() else round(float(np.nanmax(e)), 3)})
    return out


def _fault_case(item: tuple[str, str, int, int, float, float]) -> dict[str, Any]:
    """Case ``i`` of the realistic drive (a fault opened at its seeded time) in a window
    around the onset, diagnosed with and without the fault (the twin: same window and seed)."""
    from fdi_ros.core.diagnoser import diagnose_offline
    from fdi_ros.core.graphconfig import load_graph_config
    from fdi_ros.plants.diesel.drive import window
    from fdi_ros.plants.diesel.identify import simulate_features
    from fdi_ros.plants.diesel.scenario import load_cases

    path, config, i, seed, before_s, after_s = item
    cfg = load_graph_config(config)
    sc = load_cases(path)[i]
    ev = sc.faults[0]
    t0 = max(0.0, ev.t - before_s)
    win = window(sc, t0, ev.t + after_s)
    fw, _ = simulate_features(win, seed=seed + i)
    steps = diagnose_offline(cfg, fw)
    twin, _ = simulate_features(dataclasses.replace(win, faults=()), seed=seed + i)
    effect = fault_effect([s.symptoms for _, _, s in steps],
                          [s.symptoms for _, _, s in diagnose_offline(cfg, twin)])
    return {**fault_case_report(steps, fw, ev.fault, ev.t - t0, size=ev.size, effect=effect),
            "onset_drive_s": ev.t}


def realistic_drive(config, *, seed: int = 202, progress: bool = False,
                    figures: str | Path | None = None, before_s: float = 20.0,
                    after_s: float = 600.0) -> dict[str, Any]:
    """The realistic drive diagnosed by the graph's bank (``config``: the graph configuration):
    coverage per region and false symptoms on the fault-free drive, and each fault case in a
    window around its onset (``before_s`` .. ``after_s``), measured against the same window
    without the fault (:func:`fault_effect`)."""
    from fdi_ros.core.diagnoser import diagnose_offline
    from fdi_ros.core.graphconfig import load_graph_config
    from fdi_ros.core.parallel import map_processes
    from fdi_ros.plants.diesel.identify import load_features
    from fdi_ros.plants.diesel.scenario import load_cases

    cfg = load_graph_config(config)
    path = cfg.resolve(REALISTIC_DRIVE)
    cases = load_cases(path)
    feats = load_features(path, seed=seed, case=cases[0].name)
    steps = diagnose_offline(cfg, feats)
    states = [s.symptoms for _, _, s in steps]
    out = coverage_report(feats, states)
    out["minutes"] = round((feats[-1].t_end - feats[0].t_start) / 60.0, 2)
    out["isolations"] = sorted({f for _, _, s in steps for f in s.diagnosis.isolated_faults})
    if figures:
        out["figure"] = str(coverage_figure(feats, states, Path(figures) / "coverage_map.png",
                                            title="realistic drive: share of segments with a "
                                                  f"valid diagnosis ({out['coverage']:.1%})"))
    # the fault windows and their twins on the cores there are (each a pure function of its
    # case: the same results as one after the other)
    def told(done: int, total: int) -> None:
        print(f"[realistic drive] fault windows and their twins: {done}/{total}",
              file=sys.stderr, flush=True)

    out["faults"] = map_processes(_fault_case, [(str(path), str(cfg.path), i, seed, before_s,
                                                 after_s) for i in range(1, len(cases))],
                                  progress=told if progress else None)
    return out
