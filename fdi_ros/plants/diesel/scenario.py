"""Diesel scenarios (YAML) and the batch simulator.

A scenario file (``config/scenarios/diesel_*.yaml``)::

    name: diesel_paper_op
    description: free text
    seed: 1                      # sensor-noise seed (``simulate(seed=...)`` overrides)
    duration_s: 30.0             # optional; default: end of the input profile
    dalpha_deg: 1.0              # crank-angle sampling [deg CA]
    block_deg: 720.0             # samples per SampleBlock = block_deg / dalpha_deg
    inputs:
      kind: points               # piecewise-linear through the points (``hold: true`` -> steps)
      points:
        - {t: 0.0, n: 2000, torque: 130}          # torque [Nm] -> fuel via the torque model
        - {t: 10.0, n: 2500, fuel: 30, egr_cmd: 0.2, swirl_cmd: 0.0}
    faults:
      - {t: 5.0, fault: leak_ic_engine, size: 5.0, unit: mm, profile: step}
      - {t: 12.0, fault: leak_ic_engine, active: false}

``inputs.kind: sweep`` builds the quasi-stationary identification cycle: for each speed of
``n_levels`` [rpm] the fuel is ramped through ``fuel_levels`` [mg/stroke] and back, holding
``hold_s`` at each level and taking ``ramp_s`` between levels; speed changes take
``n_ramp_s``. ``egr_cmd`` and ``swirl_cmd`` are constants there. An optional
``fuel_limit: {n: [...], fuel: [...]}`` (full-load curve) caps the levels per speed.

``inputs.ecu: {...}`` lets the engine ECU command the EGR valve and the swirl flaps from its
maps of speed and load (:class:`~fdi_ros.plants.diesel.ecu.EcuSchedule`; ``{}`` = defaults)
wherever a point has ``ecu: true`` (the default when the block is given); such a point's
``egr_trim`` is added to the scheduled EGR command (closed-loop air-mass control), and its
torque demand is limited to the ECU's full-load fuel (the torque limiter: 74 kW at 4000 rpm).

``inputs.kind: zigzag`` ramps the speed slowly from ``n_min`` to ``n_max`` and back (each
way ``n_ramp_s``) while the fuel follows a raised-cosine wave (period about
``fuel_period_s``, adjusted so that ``n_ramp_s / period = k + 1/4``) between ``fuel_min`` and
the ``fuel_limit`` curve; the adjustment makes the way down pass each speed half a period
away from the way up, so the two passes interleave in the (n, rho2) plane. ``passes:`` (a list
of mappings with ``egr_cmd``, ``swirl_cmd``, ``ecu``, ``egr_trim`` (amplitude of a sinusoidal
trim) and ``trim_period_s``) repeats the cycle once per entry, one after the other.

Several cases can share one file under ``cases:`` (a list of partial scenarios merged over
the top-level keys); :func:`load_scenario` takes ``case=`` to pick one, and
:func:`load_cases` returns them all.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fdi_ros.core.crank import SegmentTable
from fdi_ros.core.types import FaultEvent, SampleBlock
from fdi_ros.plants.diesel.ecu import EcuSchedule
from fdi_ros.plants.diesel.plant import (
    CHANNELS,
    FAULT_IDS,
    FAULT_UNITS,
    UNITS,
    DieselIntakePlant,
    DieselParams,
    crank_segmenter,
    fuel_for_torque,
)

_TOP_KEYS = {"name", "description", "seed", "duration_s", "dalpha_deg", "block_deg", "inputs",
             "faults", "cases", "params"}
_POINT_KEYS = {"t", "n", "fuel", "torque", "egr_cmd", "swirl_cmd", "ecu", "egr_trim"}
_FAULT_KEYS = {"t", "fault", "size", "unit", "profile", "ramp_s", "active"}


@dataclass(frozen=True)
class Scenario:
    """A validated scenario: input profile breakpoints, fault events and sampling.

    ``t, n, fuel, egr_cmd, swirl_cmd`` are the profile breakpoints ([s], [rpm], [mg/stroke],
    [1], [1]); between them the inputs are linear (or held when ``hold``).
    """

    name: str
    t: np.ndarray
    n: np.ndarray
    fuel: np.ndarray
    egr_cmd: np.ndarray
    swirl_cmd: np.ndarray
    faults: tuple[FaultEvent, ...] = ()
    seed: int = 0
    duration_s: float = 0.0
    dalpha_deg: float = 1.0
    block_deg: float = 720.0
    hold: bool = False
    description: str = ""
    params: DieselParams = field(default_factory=DieselParams)
    ecu: EcuSchedule | None = None
    ecu_on: np.ndarray | None = None
    egr_trim: np.ndarray | None = None

    def inputs_at(self, t: float) -> tuple[float, float, float, float]:
        """(n [rpm], fuel [mg/stroke], egr_cmd, swirl_cmd) at time t [s]; the ECU's schedule
        commands EGR and swirl where it is on."""
        n, fuel, egr, swirl = self._profile_at(t)
        if self.ecu is not None and self.ecu_on is not None and self.egr_trim is not None:
            on = float(np.interp(t, self.t, self.ecu_on))
            if on >= 0.5:
                egr, swirl = self.ecu.commands(n, fuel, float(np.interp(t, self.t,
                                                                        self.egr_trim)))
        return n, fuel, egr, swirl

    def _profile_at(self, t: float) -> tuple[float, float, float, float]:
        if self.hold:
            i = max(int(np.searchsorted(self.t, t, side="right")) - 1, 0)
            return (float(self.n[i]), float(self.fuel[i]), float(self.egr_cmd[i]),
                    float(self.swirl_cmd[i]))
        i = int(np.searchsorted(self.t, t, side="right")) - 1
        if i < 0 or i >= self.t.size - 1:
            j = 0 if i < 0 else self.t.size - 1
            return (float(self.n[j]), float(self.fuel[j]), float(self.egr_cmd[j]),
                    float(self.swirl_cmd[j]))
        w = (t - self.t[i]) / (self.t[i + 1] - self.t[i]) if self.t[i + 1] > self.t[i] else 1.0
        return tuple(float(v[i] + w * (v[i + 1] - v[i]))   # type: ignore[return-value]
                     for v in (self.n, self.fuel, self.egr_cmd, self.swirl_cmd))


def _sweep_points(spec: Mapping[str, Any]) -> list[dict]:
    n_levels = [float(v) for v in spec["n_levels"]]
    fuel_levels = [float(v) for v in spec["fuel_levels"]]
    hold = float(spec.get("hold_s", 2.0))
    ramp = float(spec.get("ramp_s", 2.0))
    n_ramp = float(spec.get("n_ramp_s", 3.0))
    egr = float(spec.get("egr_cmd", 0.0))
    swirl = float(spec.get("swirl_cmd", 0.0))
    lim = spec.get("fuel_limit")
    pts: list[dict] = []
    t = 0.0
    for i, n in enumerate(n_levels):
        levels = list(fuel_levels)
        if lim:
            # full-load (smoke) limit: levels above it are dropped, the limit itself is kept
            f_max = float(np.interp(n, [float(v) for v in lim["n"]],
                                    [float(v) for v in lim["fuel"]]))
            levels = [f for f in levels if f < f_max] + [f_max]
        levels = levels if i % 2 == 0 else levels[::-1]
        for j, f in enumerate(levels):
            if pts:
                t += n_ramp if j == 0 else ramp
            pts.append(dict(t=t, n=n, fuel=f, egr_cmd=egr, swirl_cmd=swirl))
            t += hold
            pts.append(dict(t=t, n=n, fuel=f, egr_cmd=egr, swirl_cmd=swirl))
    return pts


# Settings of the zigzag that a pass may set for itself (its speed range, ramp and fuel wave:
# e.g. a pass over the part-load map where the ECU opens the EGR valve).
_PASS_OVERRIDES = ("n_min", "n_max", "n_ramp_s", "fuel_period_s", "fuel_min", "load_max")


def _zigzag_passes(spec: Mapping[str, Any]) -> list[dict]:
    """The zigzag cycle once per entry of ``passes`` (actuator settings per pass, and any of
    :data:`_PASS_OVERRIDES`)."""
    passes = spec.get("passes")
    if not passes:
        return _zigzag_points(spec)
    pts: list[dict] = []
    for i, ps in enumerate(passes):
        bad = set(ps) - {"egr_cmd", "swirl_cmd", "ecu", "egr_trim", "trim_period_s"} \
            - set(_PASS_OVERRIDES)
        if bad:
            raise ValueError(f"zigzag pass {i}: unknown keys {sorted(bad)}")
        one = _zigzag_points({**spec, **{k: ps[k] for k in _PASS_OVERRIDES if k in ps},
                              "egr_cmd": ps.get("egr_cmd", 0.0),
                              "swirl_cmd": ps.get("swirl_cmd", 0.0)})
        t0 = pts[-1]["t"] + float(spec.get("step_s", 0.5)) if pts else 0.0
        amp, period = float(ps.get("egr_trim", 0.0)), float(ps.get("trim_period_s", 23.0))
        for p in one:
            p["t"] += t0
            p["ecu"] = bool(ps.get("ecu", False))
            p["egr_trim"] = amp * float(np.sin(2.0 * np.pi * p["t"] / period))
        pts.extend(one)
    return pts


def _zigzag_points(spec: Mapping[str, Any]) -> list[dict]:
    """Slow speed ramp up and down with a triangular fuel wave up to the full-load limit."""
    n_min, n_max = float(spec["n_min"]), float(spec["n_max"])
    ramp = float(spec.get("n_ramp_s", 180.0))
    period = float(spec.get("fuel_period_s", 20.0))
    f_min = float(spec.get("fuel_min", 3.0))
    lim = spec.get("fuel_limit") or {"n": [n_min, n_max], "fuel": [40.0, 40.0]}
    # load_max: the wave's top as a share of the full-load limit (part-load passes)
    share = float(spec.get("load_max", 1.0))
    if not 0.0 < share <= 1.0:
        raise ValueError("load_max must be within (0, 1]")
    ln, lf = [float(v) for v in lim["n"]], [share * float(v) for v in lim["fuel"]]
    dt = float(spec.get("step_s", 0.5))
    egr = float(spec.get("egr_cmd", 0.0))
    swirl = float(spec.get("swirl_cmd", 0.0))
    # ramp / period = k + 1/4 makes the way down pass each speed half a fuel period away
    # from the way up (the passes interleave) while the wave stays continuous at the turn
    k = max(round(ramp / period - 0.25), 0)
    period = ramp / (k + 0.25)
    pts = []
    for t in np.arange(0.0, 2.0 * ramp + dt / 2, dt):
        n = n_min + (n_max - n_min) * (t / ramp if t <= ramp else 2.0 - t / ramp)
        # raised cosine: no corners in the boost set point that the turbocharger must chase
        wave = 0.5 * (1.0 - np.cos(2.0 * np.pi * t / period))
        f_max = float(np.interp(n, ln, lf))
        pts.append(dict(t=float(t), n=float(n), fuel=f_min + wave * (f_max - f_min),
                        egr_cmd=egr, swirl_cmd=swirl))
    return pts


def _parse(d: Mapping[str, Any], where: str) -> Scenario:
    unknown = set(d) - _TOP_KEYS
    if unknown:
        raise ValueError(f"{where}: unknown scenario keys {sorted(unknown)}")
    params = DieselParams(**dict(d.get("params") or {}))
    inp = d.get("inputs")
    if not isinstance(inp, Mapping):
        raise ValueError(f"{where}: 'inputs' must be a mapping with 'kind'")
    kind = inp.get("kind", "points")
    if kind == "points":
        pts = list(inp.get("points") or [])
    elif kind == "sweep":
        pts = _sweep_points(inp)
    elif kind == "zigzag":
        pts = _zigzag_passes(inp)
    else:
        raise ValueError(f"{where}: inputs.kind must be 'points', 'sweep' or 'zigzag', "
                         f"not {kind!r}")
    if not pts:
        raise ValueError(f"{where}: the input profile has no points")
    ecu = EcuSchedule.from_dict(inp["ecu"]) if inp.get("ecu") is not None else None
    cols: dict[str, list[float]] = {k: [] for k in ("t", "n", "fuel", "egr_cmd", "swirl_cmd",
                                                    "ecu", "egr_trim")}
    for i, p in enumerate(pts):
        bad = set(p) - _POINT_KEYS
        if bad:
            raise ValueError(f"{where}: input point {i} has unknown keys {sorted(bad)}")
        if "n" not in p or "t" not in p:
            raise ValueError(f"{where}: input point {i} needs 't' and 'n'")
        if ("fuel" in p) == ("torque" in p):
            raise ValueError(f"{where}: input point {i} needs exactly one of 'fuel', 'torque'")
        n = float(p["n"])
        fuel = float(p["fuel"]) if "fuel" in p else float(fuel_for_torque(n, p["torque"],
                                                                          params))
        if "torque" in p and ecu is not None and p.get("ecu", True):
            # the ECU's torque limiter: a demand above the full-load curve gets full load
            # (74 kW at 4000 rpm; the plant's own limit, fuel_max, is flat)
            fuel = min(fuel, ecu.full_load_fuel(n))
        cols["t"].append(float(p["t"]))
        cols["n"].append(n)
        cols["fuel"].append(fuel)
        cols["egr_cmd"].append(float(p.get("egr_cmd", 0.0)))
        cols["swirl_cmd"].append(float(p.get("swirl_cmd", 0.0)))
        cols["ecu"].append(float(bool(p.get("ecu", ecu is not None))))
        cols["egr_trim"].append(float(p.get("egr_trim", 0.0)))
    if ecu is None and any(cols["ecu"]):
        raise ValueError(f"{where}: points with 'ecu: true' need an 'inputs.ecu' schedule")
    arr = {k: np.asarray(v, dtype=float) for k, v in cols.items()}
    if not np.all(np.isfinite(np.concatenate(list(arr.values())))):
        raise ValueError(f"{where}: input points must be finite numbers")
    if np.any(np.diff(arr["t"]) < 0) or arr["t"][0] != 0.0:
        raise ValueError(f"{where}: input times must start at 0 and not decrease")
    DieselIntakePlant._check_inputs(arr["n"].min(), arr["fuel"].min(), arr["egr_cmd"].min(),
                                    arr["swirl_cmd"].min())
    DieselIntakePlant._check_inputs(arr["n"].max(), arr["fuel"].max(), arr["egr_cmd"].max(),
                                    arr["swirl_cmd"].max())
    faults = []
    for i, f in enumerate(d.get("faults") or []):
        bad = set(f) - _FAULT_KEYS
        if bad:
            raise ValueError(f"{where}: fault {i} has unknown keys {sorted(bad)}")
        fid = str(f.get("fault", ""))
        if fid and fid not in FAULT_IDS:
            raise ValueError(f"{where}: unknown fault {fid!r} (known: {', '.join(FAULT_IDS)})")
        unit = str(f.get("unit", FAULT_UNITS.get(fid, "1")))
        faults.append(FaultEvent(t=float(f["t"]), fault=fid, size=float(f.get("size", 1.0)),
                                 size_unit=unit, profile=str(f.get("profile", "step")),
                                 ramp_s=float(f.get("ramp_s", 0.0)),
                                 active=bool(f.get("active", True))))
    duration = float(d.get("duration_s", arr["t"][-1]))
    if not duration > 0:
        raise ValueError(f"{where}: duration_s must be > 0")
    dalpha = float(d.get("dalpha_deg", 1.0))
    block_deg = float(d.get("block_deg", 720.0))
    if not (dalpha > 0 and block_deg >= dalpha):
        raise ValueError(f"{where}: need dalpha_deg > 0 and block_deg >= dalpha_deg")
    sc = Scenario(name=str(d.get("name", "scenario")), t=arr["t"], n=arr["n"], fuel=arr["fuel"],
                  egr_cmd=arr["egr_cmd"], swirl_cmd=arr["swirl_cmd"], faults=tuple(faults),
                  seed=int(d.get("seed", 0)), duration_s=duration, dalpha_deg=dalpha,
                  block_deg=block_deg, hold=bool(inp.get("hold", False)),
                  description=str(d.get("description", "")), params=params, ecu=ecu,
                  ecu_on=arr["ecu"], egr_trim=arr["egr_trim"])
    # the plant validates sizes and units when the events are injected: do it now
    probe = DieselIntakePlant(params=params)
    for ev in sc.faults:
        probe.inject(ev)
    return sc


def _read(path_or_dict) -> tuple[dict, str]:
    if isinstance(path_or_dict, Mapping):
        return dict(path_or_dict), "scenario"
    import yaml
    path = Path(path_or_dict)
    if not path.is_file():
        raise FileNotFoundError(f"scenario file not found: {path}")
    with open(path) as fh:
        d = yaml.safe_load(fh)
    if not isinstance(d, Mapping):
        raise ValueError(f"{path}: a scenario must be a YAML mapping")
    return dict(d), str(path)


def load_cases(path_or_dict) -> list[Scenario]:
    """All scenarios of a file: the top level, or each entry of ``cases`` merged over it."""
    d, where = _read(path_or_dict)
    cases = d.pop("cases", None)
    if not cases:
        return [_parse(d, where)]
    out = []
    for i, c in enumerate(cases):
        merged = copy.deepcopy(d)
        merged.update(c)
        out.append(_parse(merged, f"{where} case {i} ({c.get('name', '?')})"))
    return out


def load_scenario(path_or_dict, *, case: str | int | None = None) -> Scenario:
    """One scenario from a YAML file or a dict (``case``: name or index within ``cases``)."""
    cases = load_cases(path_or_dict)
    if case is None:
        if len(cases) > 1:
            raise ValueError(f"the file holds {len(cases)} cases; pick one with case= "
                             f"({', '.join(c.name for c in cases)})")
        return cases[0]
    if isinstance(case, int):
        return cases[case]
    for c in cases:
        if c.name == case:
            return c
    raise ValueError(f"no case {case!r} (have {', '.join(c.name for c in cases)})")


@dataclass
class SimResult:
    """Result of :func:`simulate`.

    Attributes
    ----------
    scenario : the scenario run; seed : the noise seed used.
    blocks : the SampleBlocks (empty when ``keep_blocks=False``).
    faults : the fault events (ground truth).
    truth : per slow step (``params.dt``) arrays of true plant quantities: ``t`` [s],
        ``eta_v``, ``m_maf``/``m_cyl``/``m_egr``/``m_leak``/``m_vent`` [kg/s], ``p2`` [Pa],
        ``T2`` [K], ``maf_amp`` [kg/h], ``maf_phase`` [deg CA], ``p2_amp`` [Pa],
        ``p2_phase`` [deg CA], fault sizes ``u_*`` ...
    features : crank-synchronous features of the whole run (``fdi_ros.core.crank``).
    """

    scenario: Scenario
    seed: int
    blocks: list[SampleBlock]
    faults: list[FaultEvent]
    truth: dict[str, np.ndarray]
    features: Any = None

    def arrays(self) -> dict[str, np.ndarray]:
        """Concatenated samples: ``t``, ``alpha`` and one array per channel."""
        if not self.blocks:
            raise ValueError("no blocks kept (simulate with keep_blocks=True)")
        out = {"t": np.concatenate([b.t for b in self.blocks]),
               "alpha": np.concatenate([b.alpha for b in self.blocks])}
        vals = np.concatenate([b.values for b in self.blocks], axis=1)
        for i, c in enumerate(self.blocks[0].channels):
            out[c] = vals[i]
        return out

    def truth_at(self, t) -> dict[str, np.ndarray]:
        """Truth interpolated (linearly) at times t [s]."""
        return {k: np.interp(t, self.truth["t"], v) for k, v in self.truth.items() if k != "t"}


# Scenario blocks advanced at once by a simulation that keeps features only (same numbers).
SIM_CHUNK = 50


def iter_simulate(scenario: Scenario, *, seed: int | None = None, noise: bool = True,
                  chunk: int = 1) -> Iterator[tuple[SampleBlock, DieselIntakePlant]]:
    """Yield ``(block, plant)`` for the whole scenario (streaming; plant.truth() is current).

    ``chunk`` > 1 advances the plant by that many of the scenario's blocks at a time (one
    block of ``chunk`` times the samples; the last one ends where the scenario's own last
    block ends): the same samples and noise as ``chunk=1`` with less overhead per block, for
    runs that keep features only."""
    sd = scenario.seed if seed is None else int(seed)
    per_block = max(int(round(scenario.block_deg / scenario.dalpha_deg)), 1)
    plant = DieselIntakePlant(params=scenario.params, seed=sd, dalpha_deg=scenario.dalpha_deg,
                              noise=noise, noise_block=per_block)
    plant.set_input_profile(scenario.inputs_at)
    for ev in scenario.faults:
        plant.inject(ev)
    plant.truth_log = []
    chunk = max(int(chunk), 1)
    while True:
        block = plant.advance(per_block * chunk)
        ends = block.t[per_block - 1::per_block]
        done = np.flatnonzero(ends >= scenario.duration_s)
        if done.size:   # the block of chunk=1 that reaches the end is the last one
            block = _head(block, per_block * (int(done[0]) + 1))
        yield block, plant
        if done.size:
            break


def _head(block: SampleBlock, n: int) -> SampleBlock:
    """The first ``n`` samples of a block."""
    if n >= block.t.size:
        return block
    return dataclasses.replace(block, t=block.t[:n], alpha=block.alpha[:n],
                               values=block.values[:, :n])


def simulate(scenario, *, seed: int | None = None, progress: bool = False,
             keep_blocks: bool = True, features: bool = True, noise: bool = True) -> SimResult:
    """Run a scenario (a :class:`Scenario`, a YAML path or a dict) and collect the result.

    ``seed`` overrides the scenario's noise seed. With ``keep_blocks=False`` only truth and
    features are kept (10 min at 2000 rpm are ~7 M samples, ~0.5 GB as blocks).
    """
    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    sd = sc.seed if seed is None else int(seed)
    seg = crank_segmenter(sc.params) if features else None
    tables: list[SegmentTable] = []
    blocks: list[SampleBlock] = []
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=round(sc.duration_s, 3), unit="s", desc=sc.name)
    plant = None
    chunk = 1 if keep_blocks else SIM_CHUNK
    for block, plant in iter_simulate(sc, seed=sd, noise=noise,  # noqa: B007 (kept: last)
                                      chunk=chunk):
        if keep_blocks:
            blocks.append(block)
        if seg is not None:
            tables.append(seg.push_table(block))
        if bar is not None:
            bar.update(round(min(block.t[-1], sc.duration_s) - bar.n, 3))
    if bar is not None:
        bar.close()
    assert plant is not None
    truth = {k: np.concatenate([c[k] for c in plant.truth_log]) for k in
             plant.truth_log[0]} if plant.truth_log else {}
    feats = _concat_tables(tables) if seg is not None else None
    return SimResult(scenario=sc, seed=sd, blocks=blocks, faults=list(sc.faults), truth=truth,
                     features=feats)


def _concat_tables(tables):
    tabs = [t for t in tables if t.index.size]
    if not tabs:
        return tables[0] if tables else None
    first = tabs[0]
    return SegmentTable(plant=first.plant, index=np.concatenate([t.index for t in tabs]),
                        t_start=np.concatenate([t.t_start for t in tabs]),
                        t_end=np.concatenate([t.t_end for t in tabs]),
                        alpha_start=np.concatenate([t.alpha_start for t in tabs]),
                        valid=np.concatenate([t.valid for t in tabs]),
                        status=np.concatenate([t.status for t in tabs]),
                        names=first.names, units=first.units,
                        values=np.concatenate([t.values for t in tabs]))


def simulate_to_bag(scenario, path, *, seed: int | None = None) -> None:
    """A scenario (Scenario, YAML path or mapping) into a new bag: its sensor blocks and its
    fault ground truth (``fdi-ros simulate --out`` without the options)."""
    from fdi_ros import bag

    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    with bag.BagWriter(path) as w:
        for block, _ in iter_simulate(sc, seed=seed):
            w.write_block(block)
        for ev in sc.faults:
            w.write_fault(ev)


__all__ = ["Scenario", "SimResult", "load_scenario", "load_cases", "simulate", "iter_simulate",
           "simulate_to_bag", "CHANNELS", "UNITS"]
