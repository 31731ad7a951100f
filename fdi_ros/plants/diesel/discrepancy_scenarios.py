"""Measured data from our diesel plant with a hidden effect, for tests and benchmarks.

:func:`plant_record` runs :class:`fdi_ros.plants.diesel.plant.DieselIntakePlant` through a seeded,
smoothly varying operating cycle (speed, fuel; EGR closed, swirl flaps open, as in the paper's
identification cycle) and returns a crank-angle sampled :class:`Measured` record with two extra,
unmapped columns (``T_amb``, ``u_aux``: slowly varying quantities the model does not use).

:func:`hide` applies one catalogue effect to a record. The implementations here are written
independently of :mod:`fdi_ros.core.discrepancy.effects` (plain loops and textbook formulas),
so that a test finding the effect does not just re-run the code that put it there. The leak is
not applied here: it is a physical plant fault (``leak_ic_engine``) injected into the plant.
:func:`draw` draws an effect's parameters at random within stated ranges.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from fdi_ros.core.measured import Measured, segments_from_gaps
from fdi_ros.plants.diesel.discrepancy import DISPLACEMENT_L as DIESEL_DISPLACEMENT_L


def _smooth_random(rng: np.random.Generator, t: np.ndarray, lo: float, hi: float,
                   periods=(7.0, 60.0), n_waves: int = 4) -> np.ndarray:
    """A sum of random sinusoids scaled into [lo, hi]."""
    x = np.zeros_like(t)
    for _ in range(n_waves):
        per = rng.uniform(*periods)
        x += rng.uniform(0.5, 1.0) * np.sin(2 * np.pi * t / per + rng.uniform(0, 2 * np.pi))
    x = (x - x.min()) / max(x.max() - x.min(), 1e-12)
    return lo + (hi - lo) * x


def operating_profile(seed: int, duration_s: float):
    """Seeded input profile ``fn(t) -> (n_rpm, fuel_mg, egr, swirl)``: smooth variations."""
    rng = np.random.default_rng(seed)
    waves_n = [(rng.uniform(6, 40), rng.uniform(0, 2 * np.pi), rng.uniform(0.4, 1))
               for _ in range(4)]
    waves_f = [(rng.uniform(5, 30), rng.uniform(0, 2 * np.pi), rng.uniform(0.4, 1))
               for _ in range(4)]
    sn = sum(w for _, _, w in waves_n)
    sf = sum(w for _, _, w in waves_f)

    def fn(t: float):
        u = sum(w * math.sin(2 * math.pi * t / p + ph) for p, ph, w in waves_n) / sn
        v = sum(w * math.sin(2 * math.pi * t / p + ph) for p, ph, w in waves_f) / sf
        return (2200.0 + 900.0 * u, 24.0 + 12.0 * v, 0.0, 0.0)

    return fn


def plant_record(seed: int, *, duration_s: float = 60.0, dalpha_deg: float = 20.0,
                 faults=(), profile_seed: int | None = None) -> Measured:
    """Simulate the diesel plant for ``duration_s`` and return the measured record.

    ``faults``: :class:`~fdi_ros.core.types.FaultEvent` s injected before the run.
    """
    from fdi_ros.plants.diesel.plant import DieselIntakePlant

    plant = DieselIntakePlant(seed=seed, dalpha_deg=dalpha_deg)
    plant.set_input_profile(operating_profile(seed if profile_seed is None else profile_seed,
                                              duration_s))
    for ev in faults:
        plant.inject(ev)
    blocks: list[Any] = []
    while not blocks or blocks[-1].t[-1] < duration_s:
        blocks.append(plant.advance(2000))
    t = np.concatenate([b.t for b in blocks])
    alpha = np.concatenate([b.alpha for b in blocks])
    vals = np.concatenate([b.values for b in blocks], axis=1)
    keep = t <= duration_s
    sig = {c: vals[i, keep] for i, c in enumerate(blocks[0].channels)}
    units = dict(zip(blocks[0].channels, blocks[0].units))
    rng = np.random.default_rng(10_000 + seed)
    tk = t[keep]
    sig["T_amb"] = _smooth_random(rng, tk, 288.0, 303.0, periods=(20.0, 120.0))
    sig["u_aux"] = _smooth_random(rng, tk, 0.0, 1.0, periods=(5.0, 40.0))
    units.update(T_amb="K", u_aux="1")
    return Measured(t=tk, signals=sig, units=units, alpha=alpha[keep],
                    segment=segments_from_gaps(tk, 0.1), source=f"diesel plant seed {seed}",
                    mapped=tuple(blocks[0].channels))


def diesel_baseline(seed: int = 1000, *, runs: int = 3, duration_s: float = 90.0,
                    dalpha_deg: float = 20.0):
    """The speed-density + pulsation baseline identified on fault-free plant runs.

    Several runs with different operating profiles: one profile is a path through the
    (n, p2) plane, and maps identified on one path extrapolate badly off it.
    """
    data = [plant_record(seed + i, duration_s=duration_s, dalpha_deg=dalpha_deg)
            for i in range(runs)]
    return diesel_model_template().fit(data)


def diesel_model_template():
    """The diesel baseline before identification: the speed-density air flow with the MAF's
    crank-angle pulsation, and the boost pressure's pulsation over speed and air flow as a check
    (a p2 sensor's gain scales it, a lag damps it, a MAF error moves its prediction; a T2
    error leaves it alone)."""
    from fdi_ros.core.meanvalue import SpeedDensityModel
    from fdi_ros.core.residualset import PulsationMapModel, ResidualSet

    flow = SpeedDensityModel(displacement_l=DIESEL_DISPLACEMENT_L, n="n", p="p2", T="T2",
                             channel="maf", flow_scale=3600.0, degree=3, storage=("p2",),
                             derivative_window_s=0.05, orders=(1.0,), harmonic_degree=1,
                             harmonic_knots=16, leak_p_amb=101325.0, leak_T_amb=298.0,
                             leak_cd=0.65)
    boost = PulsationMapModel(channel="p2", n="n", load="maf", orders=(1.0, 2.0),
                              harmonic_degree=1, harmonic_knots=16)
    return ResidualSet(models=(flow, boost), checks=(boost.name,))


# ----------------------------------------------------------------------------- hidden effects
RANGES = {
    "offset": {"offset": (3.0, 8.0)},                 # kg/h, random sign
    "gain_error": {"gain": (1.04, 1.12)},              # or its reciprocal
    "drift": {"rate_per_s": (0.08, 0.2)},              # kg/h per s, random sign
    "sensor_lag": {"tau_s": (0.05, 0.4)},
    "dead_time": {"delay_s": (0.03, 0.3)},
    "input_dependence": {"coef": (4.0, 8.0)},          # kg/h per unit of the scaled column
    "missing_harmonic": {"amplitude": (3.0, 6.0)},     # kg/h, order drawn from 2..4
    "local_region": {"offset": (6.0, 12.0)},
    "leak": {"diameter_mm": (5.0, 9.0)},
}


def draw(effect: str, seed: int) -> dict:
    """Random parameters of a hidden effect (seeded), within :data:`RANGES`."""
    rng = np.random.default_rng(seed)
    sign = 1.0 if rng.uniform() < 0.5 else -1.0
    if effect == "offset":
        return {"offset": sign * rng.uniform(*RANGES["offset"]["offset"])}
    if effect == "gain_error":
        g = rng.uniform(*RANGES["gain_error"]["gain"])
        return {"gain": g if sign > 0 else 1.0 / g}
    if effect == "drift":
        return {"rate_per_s": sign * rng.uniform(*RANGES["drift"]["rate_per_s"])}
    if effect == "sensor_lag":
        return {"tau_s": rng.uniform(*RANGES["sensor_lag"]["tau_s"])}
    if effect == "dead_time":
        return {"delay_s": rng.uniform(*RANGES["dead_time"]["delay_s"])}
    if effect == "input_dependence":
        return {"input": str(rng.choice(["T_amb", "u_aux"])),
                "coef": sign * rng.uniform(*RANGES["input_dependence"]["coef"])}
    if effect == "missing_harmonic":
        return {"order": float(rng.integers(2, 5)),
                "amplitude": rng.uniform(*RANGES["missing_harmonic"]["amplitude"]),
                "phase_deg": rng.uniform(-180.0, 180.0)}
    if effect == "local_region":
        n0 = rng.uniform(1700.0, 2500.0)
        return {"n": (n0, n0 + rng.uniform(400.0, 700.0)),
                "offset": sign * rng.uniform(*RANGES["local_region"]["offset"])}
    if effect == "leak":
        return {"diameter_mm": rng.uniform(*RANGES["leak"]["diameter_mm"])}
    raise ValueError(f"no hidden-effect generator for {effect!r}")


def hide(data: Measured, effect: str, params: dict, channel: str = "maf") -> Measured:
    """A copy of ``data`` with ``effect`` applied to ``channel`` (independent implementation)."""
    y = np.array(data[channel], dtype=float)
    t = data.t
    if effect == "offset":
        y = y + params["offset"]
    elif effect == "gain_error":
        y = y * params["gain"]
    elif effect == "drift":
        y = y + params["rate_per_s"] * (t - t[0])
    elif effect == "sensor_lag":
        tau = params["tau_s"]
        out = np.empty_like(y)
        out[0] = y[0]
        for k in range(1, y.size):  # the textbook recursion, sample by sample
            a = math.exp(-(t[k] - t[k - 1]) / tau)
            out[k] = a * out[k - 1] + (1.0 - a) * y[k]
        y = out
    elif effect == "dead_time":
        y = np.interp(t - params["delay_s"], t, y)
    elif effect == "input_dependence":
        x = data[params["input"]]
        y = y + params["coef"] * (x - x.mean()) / x.std()
    elif effect == "missing_harmonic":
        y = y + params["amplitude"] * np.cos(2 * np.pi * params["order"] * data.alpha / 180.0
                                             + np.radians(params["phase_deg"]))
    elif effect == "local_region":
        lo, hi = params["n"]
        n = data["n"]
        y = y + params["offset"] * ((n >= lo) & (n < hi))
    else:
        raise ValueError(f"cannot hide {effect!r} in measured data (a leak is a plant fault)")
    sig = dict(data.signals)
    sig[channel] = y
    return Measured(t=data.t, signals=sig, units=dict(data.units), alpha=data.alpha,
                    segment=data.segment, source=f"{data.source} + hidden {effect}",
                    mapped=data.mapped)
