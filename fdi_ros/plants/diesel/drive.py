"""A realistic drive of the diesel: a seeded speed-load walk through city, suburban, motorway and
hill driving, the EGR valve and the swirl flaps commanded by the ECU's maps, and the same drive
with each fault opened at a random time.

``python -m fdi_ros.plants.diesel.drive --write config/scenarios/diesel_realistic_drive.yaml``
regenerates the scenario file (the numbers depend on the seed only).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from fdi_ros.plants.diesel.plant import FAULT_IDS, FAULT_UNITS
from fdi_ros.plants.diesel.scenario import Scenario

__all__ = ["DRIVE_FAULT_SIZES", "PHASES", "drive_document", "tips_document", "window"]

# (name, share of the drive, speed range [rpm], torque range [Nm], hold range [s])
PHASES = (("city", 0.30, (800.0, 2200.0), (0.0, 120.0), (3.0, 15.0)),
          ("suburban", 0.25, (1200.0, 3000.0), (20.0, 160.0), (4.0, 15.0)),
          ("motorway", 0.25, (2000.0, 4000.0), (60.0, 190.0), (6.0, 25.0)),
          ("hills", 0.20, (1400.0, 4500.0), (100.0, 205.0), (4.0, 15.0)))
# Sizes of the faults opened on the drive (plant units; within the hypotheses' range).
DRIVE_FAULT_SIZES = {"crankcase_vent_open": 10.0, "leak_ic_engine": 5.0,
                     "restriction_ic_engine": 0.8, "swirl_flap_closed": 1.0,
                     "egr_stuck_open": 1.0, "egr_leaky": 4.0}


# Ramp durations [s] between two points (before the speed change stretches them).
RAMP_S = (0.8, 4.0)


def _walk(rng: np.random.Generator, minutes: float,
          ramp_s: tuple[float, float] = RAMP_S) -> list[dict[str, Any]]:
    pts: list[dict[str, Any]] = [{"t": 0.0, "n": 800.0, "torque": 10.0}]
    t = 0.0
    total = 60.0 * minutes
    for _name, share, (n_lo, n_hi), (q_lo, q_hi), (h_lo, h_hi) in PHASES:
        end = t + share * total
        while t < end:
            n = float(rng.uniform(n_lo, n_hi))
            q = float(rng.uniform(q_lo, q_hi))
            if rng.random() < 0.15:           # overrun / idle stop in traffic
                q = 0.0
            ramp = float(rng.uniform(*ramp_s)) * (1.0 + abs(n - pts[-1]["n"]) / 2000.0)
            t += ramp
            pts.append({"t": round(t, 2), "n": round(n), "torque": round(q)})
            t += float(rng.uniform(h_lo, h_hi))
            pts.append({"t": round(t, 2), "n": round(n), "torque": round(q)})
    return pts


def drive_document(*, seed: int = 2026, minutes: float = 21.0, fault_seed: int = 16,
                   name: str = "diesel_realistic_drive", faults: bool = True,
                   ramp_s: tuple[float, float] = RAMP_S) -> dict[str, Any]:
    """The realistic drive as a scenario mapping: the fault-free drive and (``faults``) one
    case per fault (opened at a random time between 10 % and 85 % of the drive, then left
    in); ``ramp_s``: the range the ramps between the points are drawn from."""
    rng = np.random.default_rng(seed)
    pts = _walk(rng, minutes, ramp_s)
    frng = np.random.default_rng(fault_seed)
    duration = float(pts[-1]["t"])
    cases: list[dict[str, Any]] = [{"name": name}]
    for fault in FAULT_IDS if faults else ():
        t = round(float(frng.uniform(0.1, 0.85) * duration), 2)
        cases.append({"name": f"{name}_{fault}",
                      "faults": [{"t": t, "fault": fault, "size": DRIVE_FAULT_SIZES[fault],
                                  "unit": FAULT_UNITS[fault], "profile": "step"}]})
    doc: dict[str, Any] = {
        "name": name, "seed": 21, "dalpha_deg": 1.0, "block_deg": 720.0,
        "description": f"{minutes:g} min seeded drive (city, suburban, motorway, hills), EGR "
                      "and swirl by the ECU maps",
        "inputs": {"kind": "points", "ecu": {}, "points": pts}}
    if faults:
        doc["cases"] = cases
    return doc


def tips_document(*, seed: int, events: int, name: str) -> dict[str, Any]:
    """A fault-free scenario of hard tip-ins and tip-outs as the ECU runs them: ``events``
    times, at a random speed (1200-3400 rpm), from part load (0-80 Nm) to near full load
    (140-205 Nm) in 0.2-1 s, held 3-6 s, and back in 0.2-1 s (the EGR valve closing and
    opening, the flaps switching, the VGT saturating: what a hard driver does at every
    junction)."""
    rng = np.random.default_rng(seed)
    pts: list[dict[str, Any]] = [{"t": 0.0, "n": 1500.0, "torque": 20.0}]
    t = 0.0
    for _ in range(int(events)):
        n = round(float(rng.uniform(1200.0, 3400.0)))
        low = round(float(rng.uniform(0.0, 80.0)))
        high = round(float(rng.uniform(140.0, 205.0)))
        for dt, q in ((2.0, low), (4.0, low), (float(rng.uniform(0.2, 1.0)), high),
                      (float(rng.uniform(3.0, 6.0)), high), (float(rng.uniform(0.2, 1.0)), low)):
            t += dt
            pts.append({"t": round(t, 2), "n": n, "torque": q})
    return {"name": name, "seed": 21, "dalpha_deg": 1.0, "block_deg": 720.0,
            "description": f"{events} hard tip-ins and tip-outs, EGR and swirl by the ECU maps",
            "inputs": {"kind": "points", "ecu": {}, "points": pts}}


def window(sc: Scenario, t0: float, t1: float) -> Scenario:
    """The part ``t0 .. t1`` [s] of a scenario as a scenario of its own, starting at 0 (the
    plant starts settled at the inputs of ``t0``; fault times shift with it)."""
    t0, t1 = max(0.0, float(t0)), min(float(t1), sc.duration_s)
    if not t1 > t0:
        raise ValueError("window needs t1 > t0 within the scenario")
    inner = sc.t[(sc.t > t0) & (sc.t < t1)]
    ts = np.concatenate([[t0], inner, [t1]])
    prof = np.array([sc._profile_at(float(t)) for t in ts])
    on = np.interp(ts, sc.t, sc.ecu_on) if sc.ecu_on is not None else None
    trim = np.interp(ts, sc.t, sc.egr_trim) if sc.egr_trim is not None else None
    faults = tuple(dataclasses.replace(e, t=max(e.t - t0, 0.0)) for e in sc.faults
                   if e.t < t1)
    return dataclasses.replace(sc, t=ts - t0, n=prof[:, 0], fuel=prof[:, 1],
                               egr_cmd=prof[:, 2], swirl_cmd=prof[:, 3], ecu_on=on,
                               egr_trim=trim, faults=faults, duration_s=t1 - t0, hold=False)


def main(argv: list[str] | None = None) -> int:
    import yaml

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", required=True, help="scenario YAML to write")
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--minutes", type=float, default=21.0)
    ap.add_argument("--name", default="diesel_realistic_drive")
    ap.add_argument("--no-faults", action="store_true", help="the fault-free drive only")
    ap.add_argument("--ramp", default=None,
                    help="LO,HI: range of the ramp durations [s] (default "
                         f"{RAMP_S[0]:g},{RAMP_S[1]:g}; shorter: a harder driver)")
    ap.add_argument("--tips", type=int, default=0,
                    help="write N hard tip-ins and tip-outs instead of a drive (fault-free)")
    args = ap.parse_args(argv)
    if args.tips > 0:
        head = ("# Hard tip-ins and tip-outs of the diesel (generated by `python -m "
                f"fdi_ros.plants.diesel.drive --write {args.write} --seed {args.seed} --tips "
                f"{args.tips} --name {args.name}`):\n# fault-free, the EGR valve and the swirl "
                "flaps commanded by the ECU maps (fdi_ros/plants/diesel/ecu.py).\n")
        doc = tips_document(seed=args.seed, events=args.tips, name=args.name)
        Path(args.write).write_text(head + yaml.safe_dump(doc, sort_keys=False,
                                                          default_flow_style=None, width=99))
        return 0
    ramp = RAMP_S if args.ramp is None else tuple(float(v) for v in args.ramp.split(","))
    if len(ramp) != 2 or not 0 < ramp[0] <= ramp[1]:
        ap.error("--ramp needs LO,HI with 0 < LO <= HI")
    doc = drive_document(seed=args.seed, minutes=args.minutes, name=args.name,
                         faults=not args.no_faults, ramp_s=ramp)
    head = ("# Realistic drive of the diesel (generated by `python -m fdi_ros.plants.diesel.drive"
            f" --write {args.write} --seed {args.seed} --minutes {args.minutes:g} --name "
            f"{args.name}{' --no-faults' if args.no_faults else ''}"
            f"{'' if args.ramp is None else ' --ramp ' + args.ramp}`):\n"
            "# a seeded speed-load walk through city, suburban, motorway and hill driving "
            f"(ramps {ramp[0]:g}-{2 * ramp[1]:g} s,\n# holds 3-25 s, 15 % overrun), the EGR valve "
            "and the swirl flaps commanded by the ECU maps\n# (fdi_ros/plants/diesel/ecu.py)." + (
                "" if args.no_faults else " Case 0 is fault-free; each further case opens one "
                "fault\n# at a random (seeded) time and leaves it in.") + "\n")
    Path(args.write).write_text(head + yaml.safe_dump(doc, sort_keys=False,
                                                      default_flow_style=None, width=99))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
