"""Two-spool turbofan simulator (our stand-in for the GE XTE46 component-level model).

A quasi-steady component model with two shaft dynamics, vectorised over a batch of engines
(every array argument may carry a leading batch axis). Units: speeds in rpm, fuel flow WF36 in
kg/s, power in W, temperature in K, pressure in Pa, altitude in ft.

Operating condition c = (ALT [ft], XM [-], DTAMB [K], PC [-])
----------------------------------------------------------------
ISA troposphere plus a temperature deviation, and ram recovery at the fan face::

    T_amb = 288.15 - 1.9812e-3 ALT + DTAMB          p_amb = 101325 (1 - 6.8756e-6 ALT)^5.2559
    T2 = T_amb (1 + 0.2 XM^2)                      P2 = p_amb (1 + 0.2 XM^2)^3.5

The power code PC sets the scheduled fuel flow: WF_sched(c) trims the *nominal* engine to the
corrected fan speed ``nl = 1 + 0.012 (PC - 46)`` (see :meth:`Turbofan.scheduled_fuel`).

Quality parameters p (10, relative deviations, 0 = nominal)
-----------------------------------------------------------
``QUALITY_NAMES``: flow and efficiency of fan, compressor tip, compressor hub, HP turbine, LP
turbine. Each scales its characteristic by ``q = 1 + p``. Health = nominal + manufacturing
variation + deterioration index d * ``DETERIORATION_FULL`` + fault (:class:`Health`).

Components (design values in :class:`PlantConstants`; ``*0`` = design point)
----------------------------------------------------------------------------
Corrected relative speeds ``nl = NL / (NL0 sqrt(T2/T2_0))``, ``nh = NH / (NH0 sqrt(T25/T25_0))``.

* Fan:      ``W2 = qW_fan W2_0 (P2/P2_0) / sqrt(T2/T2_0) nl``;
  temperature-rise ratio ``tau_f = tau_f0 nl^2``; ``eta_f = qE_fan eta_f0 (1 - k_isl (nl-1)^2)``;
  ``P_fan = W2 cp T2 tau_f / eta_f``; core inlet ``T25 = T2 (1 + tau_f/eta_f)``,
  ``P25 = P2 (1 + tau_f)^3.5``.
* Compressor, two parallel annuli s in {tip, hub} with flow split a_s on the HP shaft:
  ``W_s = qW_s a_s Wc_0 (P25/P25_0)/sqrt(T25/T25_0) nh^1.5``; ``tau_c = tau_c0 nh^2``;
  ``eta_s = qE_s eta_c0 (1 - k_isl (nh-1)^2)``; ``P_comp = sum_s W_s cp T25 tau_c / eta_s``;
  core flow ``Wc = sum_s W_s``, ``T3 = T25 + P_comp / (Wc cp)``.
* Combustor: ``T4 = T3 + eta_b LHV WF / (cp_g (Wc + WF))``.
* HP turbine: temperature-drop fraction ``psi_h = psi_h0 qW_hpt^-0.3`` (a smaller nozzle
  throat raises the HP expansion); ``P_hpt = (Wc + WF) cp_g T4 qE_hpt eta_h0 psi_h``.
* LP turbine: ``T45 = T4 - P_hpt/((Wc+WF) cp_g)``, ``psi_l = psi_l0 (qW_hpt/qW_lpt)^0.3``,
  ``P_lpt = (Wc + WF) cp_g T45 qE_lpt eta_l0 psi_l``.

Shaft power balances (state equations, omega = N pi/30)::

    dNL/dt = (eta_m P_lpt - P_fan)  / (J_L (pi/30)^2 NL)      [rpm/s]
    dNH/dt = (eta_m P_hpt - P_comp) / (J_H (pi/30)^2 NH)

``psi_h0`` and ``psi_l0`` are calibrated so the nominal engine is in equilibrium at the design
point (ALT 15000 ft, XM 0.7, DTAMB 0, PC 46: NL0 = 10,700 rpm, NH0 = 14,150 rpm, WF0). The
plant integrates with classical RK4 at Ts = 0.02 s; sensors XN2 (= NL) and XNH add white
Gaussian noise.

Plausibility (checked in ``tests/test_turbofan_plant.py``): at constant fuel a fan efficiency
loss slows the fan; a compressor-hub efficiency loss slows the core; more fuel speeds both
spools; higher altitude (thinner air) at the same fuel runs the corrected fan speed up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

QUALITY_NAMES = ("fan_flow", "fan_eff", "tip_flow", "tip_eff", "hub_flow", "hub_eff",
                 "hpt_flow", "hpt_eff", "lpt_flow", "lpt_eff")
CONDITION_NAMES = ("ALT", "XM", "DTAMB", "PC")
#: climb region of the paper (section 2): the identified region of the models.
CLIMB_REGION = {"ALT": (12500.0, 17500.0), "XM": (0.6, 0.8), "DTAMB": (-35.0, 35.0),
                "PC": (45.0, 50.0)}
PAPER_CONDITION = (15000.0, 0.7, 0.0, 46.0)
#: the paper's initial engine variation (section 4), relative.
PAPER_MANUFACTURING = np.array([0.1, 0.1, 0.2, 0.1, -0.1, 0.0, -0.3, 0.3, -0.1, 0.1]) * 1e-2
#: quality shift at full deterioration (d = 1): efficiencies drop, compressor flows drop,
#: turbine flow capacities grow (erosion).
DETERIORATION_FULL = np.array([-1.5, -2.0, -1.5, -2.0, -1.5, -2.0, 1.0, -2.0, 1.0, -2.0]) * 1e-2
#: fault signatures: relative quality change of a *small* fault (one unit size).
FAULT_DIRECTIONS = {
    "fan": {"fan_flow": -0.75e-2, "fan_eff": -1.5e-2},
    "hub": {"hub_flow": -2.0e-2, "hub_eff": -6.0e-2},
}
#: size words in units of the small fault, per fault type. Chosen so that the 16 situations
#: give XN2 trajectories that differ by >= ~10 rpm within every on-line set of the bank (the
#: output is XN2 only, so the sizes must not add up to the same fan-speed drop; a hub fault
#: reaches the fan only through the core, hence its larger parameter changes).
FAULT_SIZES = {"fan": {"small": 1.0, "medium": 2.0, "large": 3.0},
               "hub": {"small": 1.0, "medium": 2.5, "large": 4.0}}

SQRT_T = math.sqrt


@dataclass(frozen=True)
class PlantConstants:
    """Design-point constants of the simulator (see the module docstring for the equations)."""

    NL0: float = 10700.0  # rpm
    NH0: float = 14150.0  # rpm
    W2_0: float = 55.0  # kg/s, fan flow at design
    Wc_0: float = 11.0  # kg/s, core flow at design
    tau_f0: float = 0.13  # fan isentropic temperature-rise ratio (pressure ratio ~1.53)
    tau_c0: float = 0.85  # core compressor (pressure ratio ~8.6)
    eta_f0: float = 0.88
    eta_c0: float = 0.84
    eta_h0: float = 0.89
    eta_l0: float = 0.90
    k_isl: float = 0.6  # efficiency island curvature
    split_tip: float = 0.45  # share of the core flow through the compressor tip annulus
    eta_b: float = 0.99
    LHV: float = 43.0e6  # J/kg
    cp: float = 1005.0  # J/(kg K), air
    cp_g: float = 1150.0  # J/(kg K), combustion gas
    eta_m: float = 0.99
    T4_0: float = 1300.0  # K, design turbine inlet temperature (sets WF0)
    J_L: float = 3.2  # kg m^2, low spool (fan, LPT)
    J_H: float = 0.8  # kg m^2, high spool
    noise_xnl: float = 1.0  # rpm, 1 sigma
    noise_xnh: float = 2.0  # rpm
    Ts: float = 0.02  # s


def ambient(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fan-face total temperature T2 [K] and pressure P2 [Pa] for conditions c (..., 4)."""
    c = np.asarray(c, dtype=float)
    alt, xm, dt = c[..., 0], c[..., 1], c[..., 2]
    t_amb = 288.15 - 1.9812e-3 * alt + dt
    p_amb = 101325.0 * (1.0 - 6.8756e-6 * alt) ** 5.2559
    ram = 1.0 + 0.2 * xm**2
    return t_amb * ram, p_amb * ram**3.5


def check_condition(c) -> np.ndarray:
    """Validate an operating condition (ALT, XM, DTAMB, PC); raise outside the climb region."""
    c = np.asarray(c, dtype=float)
    if c.shape[-1:] != (4,) or not np.all(np.isfinite(c)):
        raise ValueError(f"operating condition must be finite (ALT, XM, DTAMB, PC), got {c}")
    for j, name in enumerate(CONDITION_NAMES):
        lo, hi = CLIMB_REGION[name]
        if np.any(c[..., j] < lo - 1e-9) or np.any(c[..., j] > hi + 1e-9):
            raise ValueError(f"{name} = {c[..., j]} outside the identified climb region "
                             f"[{lo}, {hi}]")
    return c


@dataclass(frozen=True)
class Health:
    """Quality-parameter vector = manufacturing + deterioration + faults (relative, 10 values).

    Parameters
    ----------
    manufacturing : (10,) initial engine variation (relative).
    deterioration : index 0..1 scaling ``DETERIORATION_FULL``.
    faults : mapping fault type -> size (a size word or a number of unit sizes), e.g.
        ``{"fan": "small"}`` or ``{"hub": 1.5}``.
    """

    manufacturing: np.ndarray = field(default_factory=lambda: np.zeros(10))
    deterioration: float = 0.0
    faults: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        m = np.asarray(self.manufacturing, dtype=float)
        if m.shape != (10,) or not np.all(np.isfinite(m)):
            raise ValueError("manufacturing variation must be 10 finite values")
        object.__setattr__(self, "manufacturing", m)
        if not 0.0 <= self.deterioration <= 1.0:
            raise ValueError(f"deterioration index must be in [0, 1], not {self.deterioration}")
        for kind, size in self.faults.items():
            if kind not in FAULT_DIRECTIONS:
                raise ValueError(f"unknown fault {kind!r}; known: {sorted(FAULT_DIRECTIONS)}")
            fault_size(kind, size)

    def quality(self) -> np.ndarray:
        """(10,) relative quality deviations p."""
        p = self.manufacturing + self.deterioration * DETERIORATION_FULL
        for kind, size in self.faults.items():
            p = p + fault_size(kind, size) * fault_vector(kind)
        return p


def fault_size(kind: str, size) -> float:
    """Number of unit (small) fault sizes for a size word or number (0 = no fault)."""
    if kind not in FAULT_SIZES:
        raise ValueError(f"unknown fault {kind!r}; known: {sorted(FAULT_SIZES)}")
    if isinstance(size, str):
        if size not in FAULT_SIZES[kind]:
            raise ValueError(f"unknown fault size {size!r}; known: {list(FAULT_SIZES[kind])}")
        return FAULT_SIZES[kind][size]
    s = float(size)
    if not (math.isfinite(s) and s >= 0):
        raise ValueError(f"fault size must be >= 0, not {size}")
    return s


def fault_vector(kind: str) -> np.ndarray:
    """(10,) quality change of one unit size of fault ``kind``."""
    v = np.zeros(10)
    for name, val in FAULT_DIRECTIONS[kind].items():
        v[QUALITY_NAMES.index(name)] = val
    return v


class Turbofan:
    """The plant: state derivatives, trim, simulation. Stateless apart from its constants."""

    def __init__(self, *, constants: PlantConstants | None = None) -> None:
        self.k = constants or PlantConstants()
        k = self.k
        self._T2_0, self._P2_0 = (float(v) for v in ambient(np.array(PAPER_CONDITION)))
        self._T25_0 = self._T2_0 * (1 + k.tau_f0 / k.eta_f0)
        self._P25_0 = self._P2_0 * (1 + k.tau_f0) ** 3.5
        # calibrate the turbine work fractions: equilibrium at the design point
        T3 = self._T25_0 * (1 + k.tau_c0 / k.eta_c0)
        wf0 = k.cp_g * k.Wc_0 * (k.T4_0 - T3) / (k.eta_b * k.LHV - k.cp_g * (k.T4_0 - T3))
        self.WF0 = wf0
        p_fan = k.W2_0 * k.cp * self._T2_0 * k.tau_f0 / k.eta_f0
        p_comp = k.Wc_0 * k.cp * self._T25_0 * k.tau_c0 / k.eta_c0
        wg = k.Wc_0 + wf0
        self._psi_h0 = p_comp / k.eta_m / (wg * k.cp_g * k.T4_0 * k.eta_h0)
        T45 = k.T4_0 - p_comp / k.eta_m / (wg * k.cp_g)
        self._psi_l0 = p_fan / k.eta_m / (wg * k.cp_g * T45 * k.eta_l0)

    # -- physics --------------------------------------------------------------------------------
    def components(self, x: np.ndarray, wf: np.ndarray, c: np.ndarray, p: np.ndarray) -> dict:
        """All component quantities for states x (..., 2) = (NL, NH), fuel wf (...) [kg/s],
        conditions c (..., 4), quality deviations p (..., 10). Returns a dict of arrays."""
        k = self.k
        nl_rpm, nh_rpm = x[..., 0], x[..., 1]
        q = 1.0 + np.asarray(p, dtype=float)
        T2, P2 = ambient(c)
        th2 = T2 / self._T2_0
        nl = nl_rpm / (k.NL0 * np.sqrt(th2))
        W2 = q[..., 0] * k.W2_0 * (P2 / self._P2_0) / np.sqrt(th2) * nl
        tau_f = k.tau_f0 * nl**2
        eta_f = q[..., 1] * k.eta_f0 * (1 - k.k_isl * (nl - 1) ** 2)
        p_fan = W2 * k.cp * T2 * tau_f / eta_f
        T25 = T2 * (1 + tau_f / eta_f)
        P25 = P2 * (1 + tau_f) ** 3.5
        th25 = T25 / self._T25_0
        nh = nh_rpm / (k.NH0 * np.sqrt(th25))
        w_base = k.Wc_0 * (P25 / self._P25_0) / np.sqrt(th25) * nh**1.5
        tau_c = k.tau_c0 * nh**2
        isl = 1 - k.k_isl * (nh - 1) ** 2
        w_tip = q[..., 2] * k.split_tip * w_base
        w_hub = q[..., 4] * (1 - k.split_tip) * w_base
        eta_tip = q[..., 3] * k.eta_c0 * isl
        eta_hub = q[..., 5] * k.eta_c0 * isl
        wc = w_tip + w_hub
        p_comp = k.cp * T25 * tau_c * (w_tip / eta_tip + w_hub / eta_hub)
        T3 = T25 + p_comp / (wc * k.cp)
        wg = wc + wf
        T4 = T3 + k.eta_b * k.LHV * wf / (k.cp_g * wg)
        psi_h = self._psi_h0 * q[..., 6] ** -0.3
        p_hpt = wg * k.cp_g * T4 * q[..., 7] * k.eta_h0 * psi_h
        T45 = T4 - p_hpt / (wg * k.cp_g)
        psi_l = self._psi_l0 * (q[..., 6] / q[..., 8]) ** 0.3
        p_lpt = wg * k.cp_g * T45 * q[..., 9] * k.eta_l0 * psi_l
        return {"nl": nl, "nh": nh, "W2": W2, "Wc": wc, "T25": T25, "T3": T3, "T4": T4,
                "T45": T45, "P_fan": p_fan, "P_comp": p_comp, "P_hpt": p_hpt, "P_lpt": p_lpt}

    def derivatives(self, x, wf, c, p) -> np.ndarray:
        """State derivatives (..., 2) = (dNL/dt, dNH/dt) [rpm/s]."""
        k = self.k
        x = np.asarray(x, dtype=float)
        comp = self.components(x, np.asarray(wf, dtype=float), c, p)
        scale = (math.pi / 30.0) ** 2
        dnl = (k.eta_m * comp["P_lpt"] - comp["P_fan"]) / (k.J_L * scale * x[..., 0])
        dnh = (k.eta_m * comp["P_hpt"] - comp["P_comp"]) / (k.J_H * scale * x[..., 1])
        return np.stack([dnl, dnh], axis=-1)

    # -- equilibrium ----------------------------------------------------------------------------
    def trim(self, wf, c, p, *, x0=None) -> np.ndarray:
        """Equilibrium states (..., 2) [rpm] for constant fuel ``wf``.

        Raises ValueError if the iteration does not converge (fuel outside the engine's range).
        """
        wf = np.asarray(wf, dtype=float)
        shape = np.broadcast_shapes(wf.shape, np.shape(c)[:-1], np.shape(p)[:-1])
        start = np.broadcast_to(np.array([self.k.NL0, self.k.NH0]) if x0 is None else x0,
                                shape + (2,))
        return newton_equilibrium(lambda x: self.derivatives(x, wf, c, p), start)

    def scheduled_fuel(self, c) -> float:
        """Fuel flow WF_sched [kg/s] that trims the nominal engine to ``nl = 1 + 0.012 (PC-46)``
        (corrected fan speed demanded by the power code) at condition c."""
        c = check_condition(c)
        T2, _ = ambient(c)
        nl_target = (1.0 + 0.012 * (c[3] - 46.0)) * self.k.NL0 * math.sqrt(T2 / self._T2_0)
        wf, p0 = self.WF0, np.zeros(10)
        x = None
        for _ in range(30):  # secant/Newton on NL(wf)
            x = self.trim(wf, c, p0, x0=x)
            x2 = self.trim(wf * 1.001, c, p0, x0=x)
            slope = (x2[0] - x[0]) / (wf * 0.001)
            dwf = (nl_target - x[0]) / slope
            wf = wf + dwf
            if abs(dwf) < 1e-9:
                return float(wf)
        raise ValueError(f"no fuel schedule found for condition {c}")

    # -- simulation -----------------------------------------------------------------------------
    def step(self, x, wf, c, p) -> tuple[np.ndarray, np.ndarray]:
        """One classical RK4 step of Ts with fuel held: (x(k+1), dx/dt at x(k))."""
        ts = self.k.Ts
        k1 = self.derivatives(x, wf, c, p)
        k2 = self.derivatives(x + 0.5 * ts * k1, wf, c, p)
        k3 = self.derivatives(x + 0.5 * ts * k2, wf, c, p)
        k4 = self.derivatives(x + ts * k3, wf, c, p)
        return x + ts / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4), k1

    def simulate(self, wf: np.ndarray, c, p, *, x0=None, rng: np.random.Generator | None = None,
                 noise: bool = True) -> dict:
        """Simulate fuel profile(s) ``wf`` (..., n) [kg/s] with RK4 at Ts.

        Parameters
        ----------
        wf : (n,) or (batch, n) fuel flow per sample (zero-order hold).
        c : (4,) or (batch, 4) operating condition (checked against the climb region).
        p : quality deviations, (10,), (batch, 10), or per sample (n, 10) / (batch, n, 10)
            for faults that appear or grow during the run.
        x0 : initial states (..., 2); default: trim at ``wf[..., 0]`` with the first p.
        rng : noise generator (``np.random.default_rng(seed)``); required if ``noise``.

        Returns
        -------
        dict with ``t`` (n,) [s], ``x`` (..., n, 2) true states [rpm], ``xdot`` (..., n, 2)
        [rpm/s], ``y`` (..., n, 2) measured XN2 and XNH [rpm], ``wf`` (..., n).
        """
        wf = np.asarray(wf, dtype=float)
        if not np.all(np.isfinite(wf)) or np.any(wf <= 0):
            raise ValueError("fuel flow must be finite and positive")
        c = check_condition(c)
        p = np.asarray(p, dtype=float)
        n = wf.shape[-1]
        per_step = p.ndim >= 2 and p.shape[-2] == n and (p.ndim == 3 or wf.ndim == 1)
        p_at = (lambda k: p[..., k, :]) if per_step else (lambda k: p)
        x = self.trim(wf[..., 0], c, p_at(0)) if x0 is None else np.asarray(x0, dtype=float)
        xs = np.empty(wf.shape + (2,))
        xd = np.empty(wf.shape + (2,))
        for k in range(n):
            xs[..., k, :] = x
            x, xd[..., k, :] = self.step(x, wf[..., k], c, p_at(k))
        if not np.all(np.isfinite(xs)):
            raise ValueError("turbofan simulation diverged")
        y = xs.copy()
        if noise:
            if rng is None:
                raise ValueError("simulate(noise=True) needs rng=np.random.default_rng(seed)")
            y[..., 0] += rng.normal(0.0, self.k.noise_xnl, y.shape[:-1])
            y[..., 1] += rng.normal(0.0, self.k.noise_xnh, y.shape[:-1])
        return {"t": np.arange(n) * self.k.Ts, "x": xs, "xdot": xd, "y": y, "wf": wf}


def plant_signature(constants: PlantConstants | None = None) -> str:
    """Short hash of everything that shapes the simulated data (constants, deterioration and
    fault definitions): a model trained on another plant version is stale."""
    import hashlib
    import json

    k = constants or PlantConstants()
    doc = {"k": k.__dict__, "det": DETERIORATION_FULL.tolist(), "dirs": FAULT_DIRECTIONS,
           "sizes": FAULT_SIZES}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


def newton_equilibrium(fun, x0: np.ndarray, *, h: float = 0.5, tol: float = 1e-3,
                       max_iter: int = 50, max_step: float = 1500.0) -> np.ndarray:
    """Batch Newton iteration for ``fun(x) = 0`` with x (..., 2) speeds [rpm].

    The Jacobian is a forward difference with step ``h`` [rpm]; steps are clipped to
    ``max_step``. Converged when every step is below ``tol`` [rpm]; else ValueError.
    """
    x = np.array(x0, dtype=float)
    for _ in range(max_iter):
        f = fun(x)
        jac = np.empty(x.shape + (2,))
        for j in range(2):
            xp = x.copy()
            xp[..., j] += h
            jac[..., :, j] = (fun(xp) - f) / h
        try:
            step = np.linalg.solve(jac, f[..., None])[..., 0]
        except np.linalg.LinAlgError:
            break
        step = np.clip(step, -max_step, max_step)
        x = x - step
        if not np.all(np.isfinite(x)):
            break
        if np.all(np.abs(step) < tol):
            if np.all(x > 0):
                return x
            break
    raise ValueError("equilibrium not found (fuel flow outside the engine's or model's range?)")


def paper_input(wf_sched: float, *, duration_s: float = 20.0, ts: float = 0.02) -> np.ndarray:
    """The transient fuel profile of the diagnosis runs (deterministic): WF36(t) [kg/s].

    ``WF = WF_sched (1 + 0.05 sin(2 pi t / 9) + 0.03 sin(2 pi t / 3.1 + 1) + 0.02 s(t))`` with
    s(t) a +-1 square wave of period 6 s: slow and fast content as in the paper's Fig. 4.
    """
    t = np.arange(int(round(duration_s / ts))) * ts
    sq = np.sign(np.sin(2 * np.pi * t / 6.0 + 0.3))
    shape = (0.05 * np.sin(2 * np.pi * t / 9.0) + 0.03 * np.sin(2 * np.pi * t / 3.1 + 1.0)
             + 0.02 * sq)
    return wf_sched * (1.0 + shape)


def training_input(wf_sched: float, rng: np.random.Generator, *, duration_s: float = 20.0,
                   ts: float = 0.02) -> np.ndarray:
    """Random transient for identification: steps every 0.5-2 s in +-8 % of WF_sched plus a
    slow sine, so XNL sweeps the region the diagnosis input visits."""
    n = int(round(duration_s / ts))
    t = np.arange(n) * ts
    levels = np.empty(n)
    k = 0
    while k < n:
        dur = int(rng.uniform(0.5, 2.0) / ts)
        levels[k:k + dur] = rng.uniform(-0.08, 0.08)
        k += dur
    return wf_sched * (1.0 + levels + 0.03 * np.sin(2 * np.pi * t / 7.0 + rng.uniform(0, 6)))
