"""Mean-value intake model of a 2.0 L 4-cylinder turbocharged DI diesel, crank-resolved outputs.

The plant of Schwarte & Isermann (IFAC 2002): an Opel 2.0 L DTI (74 kW, 205 Nm) with EGR and
swirl flaps. Air path, in flow direction::

    ambient -> air filter -> air box -> duct [MAF sensor] -> duct -> junction (blow-by return,
    crank-case vent) -> compressor -> intercooler -> [leak, restriction] -> pipe -> intake
    manifold [p2, T2 sensors] (+ EGR from the exhaust manifold) -> swirl + filling ports
    -> 4 cylinders -> exhaust manifold -> VGT turbine (-> EGR valve back to the intake)

Two time scales are modelled separately and combined exactly:

1. **Slow mean-value states**, integrated with a fixed time step ``dt`` (5 ms): boost pressure
   ``p2`` [Pa] (filling and emptying of the boost volume), turbocharger rotational energy
   ``E_tc = J w^2 / 2`` [J], VGT actuator position, boost PI-controller integrator, intercooler
   outlet temperature [K] and the T2 sensor's state [K]. Algebraic: exhaust manifold pressure
   ``p3`` (turbine and EGR valve in parallel), compressor inlet pressure ``p1`` (filter, vent).

2. **Crank-angle pulsation**, linear acoustics around each slow operating point: the cylinders'
   suction is a periodic volume-flow source (period 180 deg CA) whose harmonics travel through
   the air path, represented as a chain of two-ports (transmission-line ducts, volumes,
   linearised resistances, the compressor, leak/vent/EGR admittances). The air path's
   Helmholtz-like resonance makes the MAF amplitude peak near 2000 rpm; duct propagation and
   the sensor lags make the phase drift with speed. Faults change the network (extra
   admittances, resistances, a throttled port) and so change the pulsation physically.

Main equations (SI units; ``n`` in rpm, flows in kg/s inside the model)
------------------------------------------------------------------------
Engine gas flow (speed-density):   ``m_cyl = eta_V(n, rho2) * n/120 * V_D * rho2``,
with ``rho2 = p2 / (R T2)`` and the true volumetric efficiency (see :func:`eta_true`)
``eta_V = c_eta * T2 / (T2 + dT_heat(n, rho2)) * (1 - c_fr (n/n_ref)^2) * (1 + a_ram g(n))``
times the swirl-port factor ``(1 - beta_rec dp_port/p2) / (1 - beta_rec dp_port,open/p2)``
(1 with open flaps), ``dp_port = (port_peak m_cyl / (Cd A_port))^2 / (2 rho2)``.

Boost volume (intercooler + pipe + manifold, isothermal filling):
``dp2/dt = R T2 / V_b * (m_c - m_leak - m_cyl + m_egr)``  (linearly implicit Euler).

Compressor (map with head coefficient ``psi = psi0 (1 - (phi/phi_max)^2)``):
``m_c = rho1 A_c phi_max sqrt(U^2 - dh_is / psi0)``, ``dh_is = cp T1 (PR^((k-1)/k) - 1)``,
``U = w r_c``, ``P_c = m_c dh_is / eta_c``.

Turbine (VGT nozzle, inlet-density orifice) and EGR valve in parallel from p3:
``m_t = A_t(vgt) sqrt(2 rho3 (p3 - p4))``, ``m_egr = A_egr sqrt(2 rho3 (p3 - p2))`` (below
the boost pressure the valve passes intake gas back: ``-A_egr sqrt(2 rho2 (p2 - p3))``),
``m_t + m_egr = m_cyl + m_fuel`` solved for p3 (Newton), ``P_t = eta_t m_t cp_e T3 (1 -
(p4/p3)^((k_e-1)/k_e))``, turbocharger ``dE_tc/dt = P_t - P_c - c_fr_tc w^2``.

Leaks/openings: compressible orifice ``m = Cd A p_up / sqrt(R T_up) Psi(p_dn/p_up)``.
Air filter and crank-case vent share the pressure drop ``p_amb - p1``:
``m_maf = sqrt(rho_amb dp / k_af)``, ``m_vent = Cd A_v sqrt(2 rho_amb dp)``.

Faults (ids fixed for the whole project; sizes in the units of :data:`FAULT_UNITS`) act only on
these physical elements: vent opening area, leak orifice, restriction loss (and its acoustic
resistance), filling-port area, EGR valve area.

Phase convention of the harmonics: ``x(alpha) = mean + A cos(2 pi alpha/180 + phi)``, alpha
from cylinder 1 TDC, ``phi`` in deg CA wrapped to [-90, 90) (as in ``fdi_ros.core.crank``).
The MAF phase falls by about 215 deg CA from 800 to 4000 rpm (duct delays, the two
resonances, sensor lag), so it wraps once (near 2350 rpm at mid load); the p2 phase spans
about 60 deg CA.

Simplifications: the exhaust manifold is a constant pressure for the acoustics (its blowdown
pulsation does not reach the intake through the EGR valve); the sensors are linear; T2 has
no crank-angle pulsation; the engine speed is an input (no torsional oscillation).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from fdi_ros.core.constants import R_AIR
from fdi_ros.core.crank import CrankSegmenter
from fdi_ros.core.types import FaultEvent, SampleBlock

# Slow steps between two finite-difference slopes of the boost balance (see _step).
JACOBIAN_EVERY = 4

FAULT_IDS = ("crankcase_vent_open", "leak_ic_engine", "restriction_ic_engine",
             "swirl_flap_closed", "egr_stuck_open", "egr_leaky")
FAULT_UNITS = {"crankcase_vent_open": "mm", "leak_ic_engine": "mm",
               "restriction_ic_engine": "1", "swirl_flap_closed": "1",
               "egr_stuck_open": "1", "egr_leaky": "mm"}
FAULT_LIMITS = {"crankcase_vent_open": (0.0, 40.0), "leak_ic_engine": (0.0, 40.0),
                "restriction_ic_engine": (0.0, 0.98), "swirl_flap_closed": (0.0, 1.0),
                "egr_stuck_open": (0.0, 1.0), "egr_leaky": (0.0, 20.0)}

CHANNELS = ("n", "p2", "T2", "maf", "fuel", "egr_cmd", "swirl_cmd", "vgt")
UNITS = ("rpm", "Pa", "K", "kg/h", "mg/stroke", "1", "1", "1")
PLANT_ID = "diesel"
SPEED_RANGE_RPM = (300.0, 5500.0)  # the engine's speed range (5500: its fuel cut-off)
TRUTH_LOG_KEYS = ("t", "n", "fuel", "egr_cmd", "swirl_cmd", "vgt_cmd", "eta_v", "m_maf",
                  "m_cyl", "m_egr", "m_leak", "m_vent", "m_bb", "m_c", "p1", "p_ic", "p2", "p3",
                  "T2", "T2s", "rho2", "vgt_pos", "w_tc", "p2_sp", "u_vent", "u_leak",
                  "u_restr", "u_swirl", "u_egr_stuck", "u_egr_leak")


@dataclass(frozen=True)
class DieselParams:
    """Physical parameters of the plant (SI units unless stated; defaults: 2.0 L DTI).

    Groups: ambient and gas properties; engine geometry and volumetric efficiency; air path
    geometry (volumes [m^3], duct lengths [m] and diameters [m]); component losses;
    turbocharger; boost control; sensors; integration.
    """

    # ambient and gases
    p_amb: float = 101325.0          # Pa
    T_amb: float = 298.0             # K
    R: float = R_AIR                 # J/(kg K), dry air (fdi_ros.core.constants)
    kappa: float = 1.4               # air
    cp: float = 1005.0               # J/(kg K)
    kappa_e: float = 1.33            # exhaust gas
    cp_e: float = 1150.0             # J/(kg K)
    # engine
    V_D: float = 2.0e-3              # displacement [m^3]
    n_cyl: int = 4
    lambda_cr: float = 0.28          # crank radius / connecting-rod length
    LHV: float = 42.5e6              # fuel lower heating value [J/kg]
    eta_ind: float = 0.42            # indicated efficiency
    f_exh: float = 0.30              # fraction of fuel energy in the exhaust gas enthalpy
    T_fr0: float = 10.0              # friction torque at 0 rpm [Nm]
    T_fr1: float = 4.0e-3            # friction torque slope [Nm/rpm]
    fuel_max: float = 45.0           # injected fuel limit [mg/stroke]
    # true volumetric efficiency eta_V(n, rho2)
    c_eta: float = 0.871             # scale
    dT_heat: float = 22.0            # charge heating at 1000 rpm, 1.2 kg/m^3 [K]
    heat_n_exp: float = 0.45         # dT_heat ~ (1000/n)^exp
    heat_rho_exp: float = 0.35       # dT_heat ~ (1.2/rho2)^exp
    c_fr: float = 0.035              # flow friction loss at n_ref
    n_ref: float = 4000.0            # rpm
    a_ram: float = 0.035             # ram/resonance gain
    n_ram: float = 2600.0            # rpm
    w_ram: float = 700.0             # rpm
    # air filter, air box, clean-air ducts
    k_af: float = 1.45e6             # filter + duct loss dp = k_af m^2 / rho [1/m^4]
    duct_loss_share: float = 0.15    # share of that loss in the clean-air duct (MAF, bends)
    V_ab: float = 6.0e-3             # air box (clean side)
    l_a: float = 0.15                # air box -> MAF
    d_a: float = 0.070
    l_b: float = 0.60                # MAF -> compressor inlet
    d_b: float = 0.055
    V_1: float = 2.5e-3              # compressor inlet hose and junction volume
    # blow-by
    bb_frac: float = 0.004           # blow-by / engine gas flow
    # crank-case vent opening (fault)
    Cd_vent: float = 0.7
    # compressor
    r_c: float = 0.020               # impeller tip radius [m]
    psi0: float = 0.72               # head coefficient at zero flow
    phi_max: float = 0.20            # flow coefficient at zero head
    eta_c_max: float = 0.74
    phi_opt: float = 0.11
    eta_c_min: float = 0.45
    # intercooler, boost pipe, manifold
    k_ic: float = 1.8e6              # intercooler core loss dp = k_ic m^2 / rho [1/m^4]
    V_co: float = 3.2e-3             # compressor outlet, hot pipe and intercooler core
    V_ic: float = 0.4e-3             # intercooler outlet tank (leak location)
    eps_ic: float = 0.62             # intercooler effectiveness
    tau_ic: float = 3.0              # intercooler thermal time constant [s]
    l_d: float = 1.00                # intercooler -> manifold pipe
    d_d: float = 0.050
    zeta_d: float = 1.2              # pipe loss coefficient (dynamic heads)
    Cd_restr: float = 0.7            # contraction coefficient of a restriction
    V_im: float = 2.2e-3             # intake manifold
    Cd_leak: float = 0.65
    # swirl and filling ports (per cylinder)
    A_swirl: float = 4.0e-4
    A_fill: float = 5.0e-4
    Cd_port: float = 0.6
    beta_rec: float = 0.25           # share of the port loss left at inlet valve closing
    V_cyl_eff: float = 3.0e-4        # mean cylinder volume during induction
    port_peak: float = 1.3           # port flow peak / mean engine flow
    # EGR
    d_egr: float = 0.025             # valve diameter
    Cd_egr: float = 0.7
    eps_egr: float = 0.70            # EGR cooler effectiveness
    T_cool: float = 360.0            # engine coolant [K]
    # exhaust and turbine
    A_t_open: float = 4.0e-4         # VGT effective area, vanes open [m^2]
    A_t_closed: float = 0.55e-4      # vanes closed
    eta_t: float = 0.65
    k_exh: float = 1.2e6             # after-treatment back pressure p4 - p_amb = k_exh m^2 [Pa]
    dp_lin: float = 150.0            # laminar regularisation of orifices near dp = 0 [Pa]
    # turbocharger
    J_tc: float = 1.4e-5             # [kg m^2]
    c_fr_tc: float = 2.0e-6          # bearing loss P = c w^2 [W s^2]
    w_tc_min: float = 500.0          # rad/s floor (idle)
    # boost control (set point p2_sp = p_amb + min(dp_n(n), k_sp * fuel))
    k_sp: float = 1.9e3              # Pa per mg/stroke
    dp_sp_max: float = 1.25e5        # Pa
    n_sp_lo: float = 1000.0          # rpm where boost demand starts
    n_sp_hi: float = 2300.0          # rpm where full boost demand is reached
    Kp: float = 0.6                  # 1/bar
    Ki: float = 2.0                  # 1/(bar s)
    tau_vgt: float = 0.12            # s
    # sensors
    tau_maf: float = 1.0e-3          # hot-film MAF time constant [s]
    tau_p2: float = 3.0e-4           # [s]
    tau_T2: float = 0.8              # [s]
    sigma_maf: float = 0.8           # kg/h
    sigma_p2: float = 120.0          # Pa
    sigma_T2: float = 0.15           # K
    sigma_n: float = 1.0             # rpm
    # numerics
    dt: float = 5.0e-3               # slow step [s]
    n_harmonics: int = 3             # orders of the 180 deg CA fundamental synthesised

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not np.isfinite(v):
                raise ValueError(f"DieselParams.{f.name} must be finite, got {v}")
        positive = ("p_amb", "T_amb", "R", "cp", "V_D", "dt", "J_tc", "V_im", "V_ic", "V_co",
                    "V_ab", "V_1", "r_c", "psi0", "phi_max", "A_t_open", "A_t_closed")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"DieselParams.{name} must be > 0")
        if not 1 <= self.n_harmonics <= 8:
            raise ValueError("n_harmonics must be within 1..8")
        if self.A_t_closed >= self.A_t_open:
            raise ValueError("A_t_closed must be smaller than A_t_open")

    @property
    def segment_deg(self) -> float:
        """One firing of the four-stroke engine [deg CA]: the crank-synchronous segment."""
        return 720.0 / self.n_cyl


# The boost-temperature sensor is slow (a thermistor in a housing): its segment mean gets a
# rate feature T2_rate over this many segments back (0.12 s at 2000 rpm), from which the
# reference models undo the sensor's lag (T2 + tau dT2/dt; tau identified with the models).
# The rate is the end-point slope of a quadratic fitted to the window (order 2): the backward
# difference is the slope half a window back, and in the sensor's step response after an EGR
# valve moved (dT2/dt up to 100 K/s) that lag left the compensated T2 0.5 % wrong (rms; 2.2 %
# at the 99th percentile; 1.7 % and 5.5 % with the time constant it made the identification
# choose) where the quadratic's slope leaves 0.1 % (0.44 %): segments with |dT2/dt| > 9 K/s
# of the realistic drive, against the plant's true charge temperature.
T2_RATE_LAG = 8
T2_RATE_ORDER = 2
# A rate beyond the gate's "too fast" limit anywhere in the rate's own window makes the
# segment too fast: at the kink of a temperature swing (+200 K/s to -110 K/s within 0.1 s at a
# hard tip-in) the fitted slope passes through zero for a segment, and that one segment read
# eta_V 0.23 off.
TOO_FAST_HOLD = T2_RATE_LAG + 1
# The VGT's command leads its vanes (an actuator lag, tau_vgt): the command's rate, taken the
# same way, lets the EGR-open models estimate the vanes' position (cmd - tau d(cmd)/dt); data
# without the VGT command (a CSV, a bench's blocks) get no vgt_rate and the command as it is.
RATE_CHANNELS = ("T2", "vgt")


def crank_segmenter(p: DieselParams | None = None, **options: Any) -> CrankSegmenter:
    """The crank-synchronous segmenter of this engine: segment length, displacement and gas
    constant from its parameters (their one source), and the rates of the T2 sensor's and the
    VGT command's means;
    ``options`` (n_harmonics, max_gap_deg, rate_channels, rate_lag, rate_order, or one of the
    three) go to :class:`~fdi_ros.core.crank.CrankSegmenter`."""
    p = DieselParams() if p is None else p
    return CrankSegmenter(**{"segment_deg": p.segment_deg, "V_D": p.V_D, "R": p.R,
                             "rate_channels": RATE_CHANNELS, "rate_optional": ("vgt",),
                             "rate_lag": T2_RATE_LAG,
                             "rate_order": T2_RATE_ORDER, **options})


# ----------------------------------------------------------------------------- static maps
def eta_true(n, rho2, p: DieselParams):
    """True volumetric efficiency with open swirl flaps [1] (vectorised).

    ``eta = c_eta * T2/(T2 + dT) * (1 - c_fr (n/n_ref)^2) * (1 + a_ram exp(-((n-n_ram)/w)^2))``
    with charge heating ``dT = dT_heat (1000/n)^a (1.2/rho2)^b`` relative to ``T2 = 320 K``:
    slower engines and thinner charges pick up more wall heat; flow friction grows with the
    square of the speed; the intake runners' ram effect adds a bump near ``n_ram``.
    """
    n = np.maximum(np.asarray(n, dtype=float), 100.0)
    rho2 = np.maximum(np.asarray(rho2, dtype=float), 0.2)
    dT = p.dT_heat * (1000.0 / n) ** p.heat_n_exp * (1.2 / rho2) ** p.heat_rho_exp
    heating = 320.0 / (320.0 + dT)
    friction = 1.0 - p.c_fr * (n / p.n_ref) ** 2
    ram = 1.0 + p.a_ram * np.exp(-((n - p.n_ram) / p.w_ram) ** 2)
    return p.c_eta * heating * friction * ram


def _eta_scalar(n: float, rho2: float, p: DieselParams) -> float:
    """:func:`eta_true` for scalars (the slow loop calls it twice per step)."""
    n = max(n, 100.0)
    rho2 = max(rho2, 0.2)
    dT = p.dT_heat * (1000.0 / n) ** p.heat_n_exp * (1.2 / rho2) ** p.heat_rho_exp
    return (p.c_eta * 320.0 / (320.0 + dT) * (1.0 - p.c_fr * (n / p.n_ref) ** 2)
            * (1.0 + p.a_ram * math.exp(-((n - p.n_ram) / p.w_ram) ** 2)))


def boost_setpoint(n, fuel_mg, p: DieselParams):
    """Boost pressure set point [Pa]: ``p_amb + min(dp_max * s(n), k_sp * fuel)``.

    ``s(n)`` rises linearly from 0 at ``n_sp_lo`` to 1 at ``n_sp_hi`` (the turbine cannot
    deliver boost at low exhaust flow, so the ECU does not ask for it).
    """
    s = np.clip((np.asarray(n, float) - p.n_sp_lo) / (p.n_sp_hi - p.n_sp_lo), 0.0, 1.0)
    return p.p_amb + np.minimum(p.dp_sp_max * s, p.k_sp * np.maximum(fuel_mg, 0.0))


def friction_torque(n, p: DieselParams):
    """Engine friction torque [Nm] at speed n [rpm]."""
    return p.T_fr0 + p.T_fr1 * np.asarray(n, float)


def torque_per_mg(p: DieselParams) -> float:
    """Indicated torque per injected mg/stroke [Nm]: ``LHV eta_ind 1e-6 n_cyl / (4 pi)``."""
    return p.LHV * p.eta_ind * 1e-6 * p.n_cyl / (4.0 * math.pi)


def fuel_for_torque(n, torque, p: DieselParams):
    """Injected fuel [mg/stroke] for a brake torque [Nm] at speed n [rpm] (clipped)."""
    fuel = (np.asarray(torque, float) + friction_torque(n, p)) / torque_per_mg(p)
    return np.clip(fuel, 0.0, p.fuel_max)


def suction_harmonics(p: DieselParams) -> np.ndarray:
    """Normalised complex harmonics ``c_k`` of the cylinders' total suction flow.

    Every 180 deg CA one cylinder performs its induction stroke; its gas flow follows the
    piston velocity ``v ~ sin(t) (1 + lambda cos(t) / sqrt(1 - lambda^2 sin^2 t))`` over
    0..180 deg after TDC. The total suction ``q(alpha) = q_mean (1 + sum_k Re(c_k exp(j k 2 pi
    alpha / 180)))``; for lambda = 0 this gives ``c_1 = -2/3``.
    """
    m = 7200
    th = (np.arange(m) + 0.5) * (math.pi / m)
    v = np.sin(th) * (1.0 + p.lambda_cr * np.cos(th)
                      / np.sqrt(1.0 - (p.lambda_cr * np.sin(th)) ** 2))
    v = np.maximum(v, 0.0)
    k = np.arange(1, p.n_harmonics + 1)
    # period of the 180 deg CA waveform mapped to th in [0, pi)
    basis = np.exp(-1j * 2.0 * np.outer(k, th))
    return 2.0 * (basis @ v) / m / v.mean()


def _psi(pr: float, kappa: float) -> float:
    """Compressible orifice flow function Psi(p_down/p_up) (critical pressure ratio capped)."""
    crit = (2.0 / (kappa + 1.0)) ** (kappa / (kappa - 1.0))
    pr = min(max(pr, crit), 1.0)
    val = 2.0 * kappa / (kappa - 1.0) * (pr ** (2.0 / kappa) - pr ** ((kappa + 1.0) / kappa))
    return math.sqrt(max(val, 0.0))


def _sroot(x: float, x0: float) -> tuple[float, float]:
    """Signed square root with a linear (laminar) part for ``|x| < x0``; returns (f, df/dx)."""
    if x >= x0:
        r = math.sqrt(x)
        return r, 0.5 / r
    if x <= -x0:
        r = math.sqrt(-x)
        return -r, 0.5 / r
    s = math.sqrt(x0)
    return x / s, 1.0 / s


def _area(d_mm: float) -> float:
    return math.pi / 4.0 * (d_mm * 1e-3) ** 2


# ----------------------------------------------------------------------------- fault schedule
@dataclass
class _FaultSchedule:
    """Fault sizes as functions of time from a list of :class:`FaultEvent`."""

    events: list[FaultEvent] = field(default_factory=list)

    def add(self, ev: FaultEvent) -> None:
        if ev.fault and ev.fault not in FAULT_IDS:
            raise ValueError(f"unknown diesel fault {ev.fault!r}; known: {', '.join(FAULT_IDS)}")
        if ev.fault and ev.active:
            unit = FAULT_UNITS[ev.fault]
            if ev.size_unit not in (unit, "") and not (unit == "1" and ev.size_unit == "fraction"):
                raise ValueError(f"fault {ev.fault} is sized in {unit!r}, got {ev.size_unit!r}")
            lo, hi = FAULT_LIMITS[ev.fault]
            if not (np.isfinite(ev.size) and lo <= ev.size <= hi):
                raise ValueError(f"fault {ev.fault} size {ev.size} outside [{lo}, {hi}] {unit}")
        if not np.isfinite(ev.t):
            raise ValueError("fault event time must be finite")
        self.events.append(ev)
        self.events.sort(key=lambda e: e.t)

    def sizes(self, t: float) -> dict[str, float]:
        out = dict.fromkeys(FAULT_IDS, 0.0)
        for ev in self.events:
            if ev.t > t:
                break
            if not ev.fault:
                out = dict.fromkeys(FAULT_IDS, 0.0)
                continue
            if not ev.active:
                out[ev.fault] = 0.0
                continue
            out[ev.fault] = ev.size_at(t, out[ev.fault])
        return out


# ----------------------------------------------------------------------------- the plant

class DieselIntakePlant:
    """The turbo-diesel intake plant, sampled at a fixed crank-angle increment.

    Parameters
    ----------
    params : physical parameters (defaults: 2.0 L DTI).
    seed : seed of the sensor noise generator.
    dalpha_deg : crank-angle sampling increment [deg CA] (must divide 180 for aligned
        segments; any positive value works).

    Use :meth:`set_inputs` (or :meth:`set_input_profile`), :meth:`inject` faults and
    :meth:`advance` to get :class:`SampleBlock` s with channels :data:`CHANNELS`.
    """

    def __init__(self, *, params: DieselParams | None = None, seed: int = 0,
                 dalpha_deg: float = 1.0, noise: bool = True,
                 noise_block: int | None = None) -> None:
        if not (np.isfinite(dalpha_deg) and 0.0 < dalpha_deg <= 90.0):
            raise ValueError("dalpha_deg must be within (0, 90] deg CA")
        self.p = params if params is not None else DieselParams()
        self.dalpha = float(dalpha_deg)
        self.rng = np.random.default_rng(seed)
        self.noise = bool(noise)
        # sensor noise is drawn per this many samples (None: per call of advance), so that a
        # run advanced in longer chunks draws exactly the noise of its logical blocks
        self.noise_block = None if noise_block is None else max(int(noise_block), 1)
        self._faults = _FaultSchedule()
        self._c_suction = suction_harmonics(self.p)
        self._inputs = dict(n=2000.0, fuel=26.0, egr_cmd=0.0, swirl_cmd=0.0)
        self._input_fn: Callable[[float], tuple[float, float, float, float]] | None = None
        self._block_index = 0
        self._sample_index = 0          # next sample number; alpha = index * dalpha
        self._hist: dict[str, np.ndarray] | None = None
        self._last: dict[str, float] = {}
        self._initialised = False
        #: when a list, every slow step's true quantities are appended (chunks of arrays)
        self.truth_log: list[dict[str, np.ndarray]] | None = None

    # ------------------------------------------------------------------ inputs and faults
    def set_inputs(self, *, n_rpm: float, fuel_mg: float, egr_cmd: float = 0.0,
                   swirl_cmd: float = 0.0) -> None:
        """Hold constant inputs: speed [rpm], fuel [mg/stroke], EGR and swirl commands [0..1].

        ``egr_cmd`` 0 = valve closed; ``swirl_cmd`` 0 = flaps open (filling ports open),
        1 = filling ports closed.
        """
        self._inputs = self._check_inputs(n_rpm, fuel_mg, egr_cmd, swirl_cmd)
        self._input_fn = None

    def set_input_profile(self, fn: Callable[[float], tuple[float, float, float, float]]) -> None:
        """Inputs as a function of plant time: ``fn(t) -> (n_rpm, fuel_mg, egr_cmd, swirl_cmd)``.

        Evaluated at every slow step (``params.dt``), so ramps come out smooth.
        """
        self._input_fn = fn

    @staticmethod
    def _check_inputs(n, fuel, egr, swirl) -> dict[str, float]:
        vals = dict(n=float(n), fuel=float(fuel), egr_cmd=float(egr), swirl_cmd=float(swirl))
        if not all(np.isfinite(v) for v in vals.values()):
            raise ValueError(f"inputs must be finite: {vals}")
        lo, hi = SPEED_RANGE_RPM
        if not lo <= vals["n"] <= hi:
            raise ValueError(f"engine speed {vals['n']} rpm outside {lo:g}..{hi:g} rpm")
        if not 0.0 <= vals["fuel"] <= 60.0:
            raise ValueError(f"fuel {vals['fuel']} mg/stroke outside 0..60")
        for k in ("egr_cmd", "swirl_cmd"):
            if not 0.0 <= vals[k] <= 1.0:
                raise ValueError(f"{k} {vals[k]} outside 0..1")
        return vals

    def inject(self, event: FaultEvent) -> None:
        """Schedule a fault event (takes effect at ``event.t`` of plant time)."""
        self._faults.add(event)

    @property
    def t(self) -> float:
        """Plant time up to which the slow states are integrated [s]."""
        return self._last.get("t", 0.0)

    # ------------------------------------------------------------------ slow dynamics
    def _current_inputs(self, t: float) -> dict[str, float]:
        if self._input_fn is None:
            return self._inputs
        return self._check_inputs(*self._input_fn(t))

    def _init_state(self, inp: dict[str, float]) -> None:
        """Start at (approximately) the steady state of the first inputs."""
        p = self.p
        self._x = dict(p2=float(boost_setpoint(inp["n"], inp["fuel"], p)), T_ic=320.0,
                       T2s=320.0, vgt=0.5, I=0.5, p3=p.p_amb * 1.3, m_c=0.03, p1=p.p_amb)
        self._x["E"] = 0.5 * p.J_tc * 12000.0 ** 2
        # settle the slow states (the first seconds of a warm engine at this point)
        for _ in range(int(8.0 / p.dt)):
            self._step(0.0, inp, dict.fromkeys(FAULT_IDS, 0.0), record=False)
        self._x["T2s"] = self._T2_last
        self._initialised = True

    def _algebra(self, p2: float, inp: dict, fz: dict, x: dict) -> dict:
        """All algebraic quantities at boost pressure p2 and the slow states x."""
        p = self.p
        n, fuel = inp["n"], inp["fuel"]
        # intake ports: swirl flaps throttle the filling ports
        closure = min(1.0, max(inp["swirl_cmd"], fz["swirl_flap_closed"]))
        a_port = p.Cd_port * (p.A_swirl + p.A_fill * (1.0 - closure))
        # manifold temperature from the intercooler outlet and the EGR gas (mixing below)
        T2 = x.get("T2", 320.0)
        rho2 = p2 / (p.R * T2)
        eta0 = _eta_scalar(n, rho2, p)
        m_th = n / 120.0 * p.V_D * rho2
        m_cyl0 = eta0 * m_th
        # port loss at the per-cylinder peak flow; the share left at IVC lowers the charge
        dp_port = (p.port_peak * m_cyl0 / a_port) ** 2 / (2.0 * rho2)
        dp_port0 = (p.port_peak * m_cyl0 / (p.Cd_port * (p.A_swirl + p.A_fill))) ** 2 / (
            2.0 * rho2)
        eta = eta0 * (1.0 - p.beta_rec * dp_port / p2) / (1.0 - p.beta_rec * dp_port0 / p2)
        m_cyl = eta * m_th
        m_fuel = fuel * 1e-6 * n / 120.0 * p.n_cyl
        # exhaust side: turbine and EGR valve in parallel from p3
        m_exh = m_cyl + m_fuel
        T3 = T2 + p.f_exh * p.LHV * m_fuel / (p.cp_e * max(m_exh, 1e-6))
        p4 = p.p_amb + p.k_exh * m_exh ** 2
        a_t = p.A_t_open - x["vgt"] * (p.A_t_open - p.A_t_closed)
        a_e = p.Cd_egr * (_area(p.d_egr * 1e3) * max(inp["egr_cmd"], fz["egr_stuck_open"])
                          + _area(fz["egr_leaky"]))
        k3 = math.sqrt(2.0 / (p.R * T3))
        # a valve below the boost pressure passes intake gas back, at the intake's density
        k2 = math.sqrt(2.0 * p2 / (p.R * T2))

        def egr_flow(p3: float) -> tuple[float, float]:
            fe, dfe = _sroot(p3 - p2, p.dp_lin)
            if p3 < p2:
                return a_e * k2 * fe, a_e * k2 * dfe
            sp = math.sqrt(p3)
            return k3 * sp * a_e * fe, k3 * a_e * (fe / (2.0 * sp) + sp * dfe)

        p3 = max(x["p3"], p4 + 1.0)
        for _ in range(30):
            sp = math.sqrt(p3)
            ft, dft = _sroot(p3 - p4, p.dp_lin)
            me, dme = egr_flow(p3)
            g = k3 * sp * a_t * ft + me - m_exh
            dg = k3 * a_t * (ft / (2.0 * sp) + sp * dft) + dme
            step = g / dg
            p3_new = max(p3 - step, p4 + 1e-3)
            if abs(p3_new - p3) < 1e-3:
                p3 = p3_new
                break
            p3 = p3_new
        sp = math.sqrt(p3)
        m_t = k3 * sp * a_t * _sroot(p3 - p4, p.dp_lin)[0]
        m_egr = egr_flow(p3)[0]
        T_egr = T3 - p.eps_egr * (T3 - p.T_cool)
        # fresh charge through the boost pipe (quasi-steady manifold)
        m_d = m_cyl - m_egr
        m_in = max(m_d, 0.0) + max(m_egr, 0.0)
        T2_new = (max(m_d, 0.0) * x["T_ic"] + max(m_egr, 0.0) * T_egr) / m_in if m_in > 1e-9 \
            else x["T_ic"]
        rho_ic = p2 / (p.R * x["T_ic"])
        a_d = math.pi / 4.0 * p.d_d ** 2
        dp_pipe = p.zeta_d * m_d * abs(m_d) / (2.0 * rho_ic * a_d ** 2)
        b = fz["restriction_ic_engine"]
        if b > 0.0:
            ratio = 1.0 / (p.Cd_restr * (1.0 - b))
            zeta_r = max(ratio - 1.0, 0.0) ** 2
        else:
            zeta_r = 0.0
        dp_restr = zeta_r * m_d * abs(m_d) / (2.0 * rho_ic * a_d ** 2)
        p_ic = p2 + dp_pipe + dp_restr
        # leak between intercooler and engine (compressible orifice to ambient)
        if fz["leak_ic_engine"] > 0.0 and p_ic > p.p_amb:
            m_leak = (p.Cd_leak * _area(fz["leak_ic_engine"]) * p_ic
                      / math.sqrt(p.R * x["T_ic"]) * _psi(p.p_amb / p_ic, p.kappa))
        else:
            m_leak = 0.0
        # compressor (inlet pressure from the previous step's flow: air box dynamics)
        p1 = x["p1"]
        T1 = p.T_amb
        m_c_guess = max(x["m_c"], 1e-5)
        rho_co = p_ic / (p.R * max(x["T_ic"], 250.0))
        p_co = p_ic + p.k_ic * m_c_guess ** 2 / rho_co
        pr = p_co / p1
        a_exp = (p.kappa - 1.0) / p.kappa
        dh = p.cp * T1 * (pr ** a_exp - 1.0)
        w = math.sqrt(2.0 * x["E"] / p.J_tc)
        u_tip = w * p.r_c
        a_c = math.pi * p.r_c ** 2
        rho1 = p1 / (p.R * T1)
        rad = u_tip ** 2 - dh / p.psi0
        m_c = rho1 * a_c * p.phi_max * math.sqrt(max(rad, 0.0))
        # d(p_co)/d(m_c) along the speed line (for the acoustic compressor two-port)
        if rad > 1.0 and m_c > 1e-6:
            ddh_dm = -2.0 * p.psi0 * rad / m_c  # from rad = (m_c / (rho1 a_c phi_max))^2
            dpr_dm = ddh_dm / (p.cp * T1 * a_exp * pr ** (a_exp - 1.0))
        else:
            dpr_dm = -1e3
        phi = m_c / (rho1 * a_c * max(u_tip, 1.0))
        eta_c = max(p.eta_c_min, p.eta_c_max - 8.0 * (phi - p.phi_opt) ** 2)
        if pr > 1.0:
            P_c = m_c * dh / eta_c
            T_co = T1 * (1.0 + (pr ** a_exp - 1.0) / eta_c)
        else:
            P_c = 0.0
            T_co = T1
        ae = (p.kappa_e - 1.0) / p.kappa_e
        P_t = p.eta_t * max(m_t, 0.0) * p.cp_e * T3 * (1.0 - (p4 / p3) ** ae)
        return dict(T2_mix=T2_new, rho2=rho2, eta=eta, m_cyl=m_cyl, m_fuel=m_fuel, T3=T3,
                    p4=p4, p3=p3, m_t=m_t, m_egr=m_egr, m_d=m_d, p_ic=p_ic, p_co=p_co,
                    dp_pipe=dp_pipe, dp_restr=dp_restr, m_leak=m_leak, m_c=m_c, pr=pr,
                    dpr_dm=dpr_dm, w=w, P_c=P_c, P_t=P_t, T_co=T_co, dp_port=dp_port,
                    a_port=a_port, closure=closure)

    def _step(self, t: float, inp: dict[str, float], fz: dict[str, float], *,
              record: bool = True) -> dict[str, float] | None:
        """One slow step of length dt from time t (linearly implicit for p2)."""
        p, x = self.p, self._x
        dt = p.dt
        p2 = x["p2"]
        p1_used = x["p1"]
        a = self._algebra(p2, inp, fz, x)
        net0 = a["m_c"] - a["m_leak"] - a["m_cyl"] + a["m_egr"]
        # d(net)/dp2 by a finite difference, refreshed every JACOBIAN_EVERY steps (a
        # linearly implicit step stays stable with a slightly old slope; it only damps)
        self._jac_age = getattr(self, "_jac_age", JACOBIAN_EVERY)
        if self._jac_age >= JACOBIAN_EVERY:
            dp = 5.0
            b = self._algebra(p2 + dp, inp, fz, x)
            net1 = b["m_c"] - b["m_leak"] - b["m_cyl"] + b["m_egr"]
            self._slope = min((net1 - net0) / dp, 0.0)
            self._jac_age = 0
        self._jac_age += 1
        slope = self._slope
        V_b = p.V_co + p.V_ic + p.V_im + math.pi / 4.0 * p.d_d ** 2 * p.l_d
        k = p.R * x.get("T2", 320.0) / V_b
        p2_new = p2 + dt * k * net0 / (1.0 - dt * k * slope)
        p2_new = max(p2_new, 0.5 * p.p_amb)
        # turbocharger energy
        w = a["w"]
        E = x["E"] + dt * (a["P_t"] - a["P_c"] - p.c_fr_tc * w ** 2)
        x["E"] = max(E, 0.5 * p.J_tc * p.w_tc_min ** 2)
        # boost PI controller on the (fast, unbiased) p2 sensor mean, anti-windup
        s_n = min(max((inp["n"] - p.n_sp_lo) / (p.n_sp_hi - p.n_sp_lo), 0.0), 1.0)
        p2_sp = p.p_amb + min(p.dp_sp_max * s_n, p.k_sp * max(inp["fuel"], 0.0))
        e = (p2_sp - p2) / 1e5
        u = p.Kp * e + x["I"]
        if (0.0 < u < 1.0) or (u >= 1.0 and e < 0) or (u <= 0.0 and e > 0):
            x["I"] = min(max(x["I"] + p.Ki * e * dt, -0.5), 1.5)
        u = min(max(u, 0.0), 1.0)
        x["vgt"] += (1.0 - math.exp(-dt / p.tau_vgt)) * (u - x["vgt"])
        # intercooler outlet temperature (thermal mass), manifold mixing, T2 sensor
        T_ic_ss = a["T_co"] - p.eps_ic * (a["T_co"] - p.T_amb)
        x["T_ic"] += (1.0 - math.exp(-dt / p.tau_ic)) * (T_ic_ss - x["T_ic"])
        x["T2"] = a["T2_mix"]
        self._T2_last = a["T2_mix"]
        x["T2s"] += (1.0 - math.exp(-dt / p.tau_T2)) * (a["T2_mix"] - x["T2s"])
        x["p3"] = a["p3"]
        # filter / crank-case vent split of the compressor inflow -> p1 for the next step
        m_c = a["m_c"]
        rho_a = p.p_amb / (p.R * p.T_amb)
        a_f = math.sqrt(rho_a / p.k_af)
        d_vent = fz["crankcase_vent_open"]
        m_bb = p.bb_frac * a["m_cyl"]
        if d_vent > 0.0:
            a_v = p.Cd_vent * _area(d_vent) * math.sqrt(2.0 * rho_a)
            root = m_c / (a_f + a_v)
            m_maf, m_vent, m_bb_in = a_f * root, a_v * root, 0.0
        else:
            m_bb_in = min(m_bb, 0.9 * m_c)
            m_maf = m_c - m_bb_in
            m_vent = 0.0
            root = m_maf / a_f
        dp_af = root * root
        x["p1"] = p.p_amb - dp_af
        x["m_c"] = m_c
        x["p2"] = p2_new
        if not record:
            return None
        return dict(t=t, n=inp["n"], fuel=inp["fuel"], egr_cmd=inp["egr_cmd"],
                    swirl_cmd=inp["swirl_cmd"], vgt_cmd=u, vgt_pos=x["vgt"], p1=p1_used,
                    p_co=a["p_co"], p_ic=a["p_ic"], p2=p2, p3=a["p3"],
                    p4=a["p4"], T_ic=x["T_ic"], T2=a["T2_mix"], T2s=x["T2s"], T3=a["T3"],
                    m_maf=m_maf, m_c=m_c, m_vent=m_vent, m_bb=m_bb_in, m_leak=a["m_leak"],
                    m_d=a["m_d"], m_cyl=a["m_cyl"], m_egr=a["m_egr"], m_t=a["m_t"],
                    eta_v=a["m_cyl"] / (inp["n"] / 120.0 * p.V_D * a["rho2"]), w_tc=w,
                    pr_c=a["pr"], dpr_dm=a["dpr_dm"],
                    dp_restr=a["dp_restr"], dp_pipe=a["dp_pipe"], dp_af=dp_af,
                    p2_sp=p2_sp, u_vent=d_vent, u_leak=fz["leak_ic_engine"],
                    u_restr=fz["restriction_ic_engine"], u_swirl=a["closure"],
                    u_egr_stuck=fz["egr_stuck_open"], u_egr_leak=fz["egr_leaky"],
                    a_port=a["a_port"], dp_port=a["dp_port"], rho2=a["rho2"])

    # ------------------------------------------------------------------ stepping and sampling
    def _run_until(self, alpha_end: float) -> dict[str, np.ndarray]:
        """Integrate slow steps until one lies beyond ``alpha_end`` [deg CA].

        Returns the per-step records incl. pulsation harmonics. The crank angle of each step
        follows from the recorded speeds (linear between steps, so the trapezoid is exact),
        also across a step change of :meth:`set_inputs`. At most one step is computed past
        the requested angle, so new inputs and faults act within one step (``params.dt``).
        """
        p = self.p
        recs = []
        t = self._last.get("t", 0.0)
        alpha = self._last.get("alpha")
        n_prev = self._last.get("n")
        while True:
            inp = self._current_inputs(t)
            if not self._initialised:
                self._init_state(inp)
            rec = self._step(t, inp, self._faults.sizes(t))
            assert rec is not None  # recorded steps return their record
            # the first step starts the crank angle (no speed before it)
            alpha = 0.0 if alpha is None or n_prev is None else \
                alpha + 3.0 * (n_prev + rec["n"]) * p.dt
            n_prev = rec["n"]
            rec["alpha"] = alpha
            recs.append(rec)
            t += p.dt
            if alpha > alpha_end:
                break
        self._last = dict(t=t, alpha=alpha, n=n_prev)
        out = {k: np.array([r[k] for r in recs], dtype=float) for k in recs[0]}
        out["X_maf"], out["X_p2"] = pulsation_harmonics(out, p, self._c_suction)
        if self.truth_log is not None:
            entry = {k: out[k] for k in TRUTH_LOG_KEYS}
            entry["eta_v_air"] = out["m_maf"] / (out["n"] / 120.0 * p.V_D * out["rho2"])
            for name in ("maf", "p2"):
                x1 = out[f"X_{name}"][:, 0]
                entry[f"{name}_amp"] = np.abs(x1)
                entry[f"{name}_phase"] = (np.degrees(np.angle(x1)) / 2.0 + 90.0) % 180.0 - 90.0
            self.truth_log.append(entry)
        return out

    def _append_hist(self, new: dict[str, np.ndarray]) -> None:
        if self._hist is None:
            self._hist = new
        else:
            self._hist = {k: np.concatenate([self._hist[k], new[k]]) for k in new}

    def advance(self, n_samples: int) -> SampleBlock:
        """Simulate the next ``n_samples`` crank-angle samples and return them as one block.

        Samples are at ``alpha = i * dalpha_deg`` (unwrapped, deg CA, cylinder 1 TDC at 0).
        Times are exact for the piecewise-linear speed of the slow steps.
        """
        n_samples = int(n_samples)
        if n_samples < 1:
            raise ValueError("n_samples must be >= 1")
        p = self.p
        i0 = self._sample_index
        alpha = (i0 + np.arange(n_samples)) * self.dalpha
        a_end = alpha[-1]
        while self._hist is None or self._hist["alpha"][-1] <= a_end:
            # chunks of at most ~1 s of engine time keep the record arrays small
            a_have = self._hist["alpha"][-1] if self._hist is not None else 0.0
            self._append_hist(self._run_until(min(a_end, a_have + 36000.0)))
        h = self._hist
        k = np.searchsorted(h["alpha"], alpha, side="right") - 1
        k = np.clip(k, 0, h["alpha"].size - 2)
        a0, a1 = h["alpha"][k], h["alpha"][k + 1]
        frac = (alpha - a0) / (a1 - a0)
        # time: alpha - a0 = 6 n0 tau + 3 (n1 - n0)/dt tau^2
        n0, n1 = h["n"][k], h["n"][k + 1]
        qa = 3.0 * (n1 - n0) / p.dt
        qb = 6.0 * n0
        da = alpha - a0
        disc = np.sqrt(np.maximum(qb * qb + 4.0 * qa * da, 0.0))
        tau = np.where(np.abs(qa) > 1e-12, 2.0 * da / (qb + disc), da / qb)
        t = h["t"][k] + tau
        lin = (lambda key: h[key][k] + frac * (h[key][k + 1] - h[key][k]))
        n_true = n0 + (n1 - n0) * tau / p.dt
        theta = np.exp(1j * (2.0 * math.pi / 180.0) * alpha)
        maf = 3600.0 * lin("m_maf")
        p2 = lin("p2")
        zk = np.ones_like(theta)
        for j in range(h["X_maf"].shape[1]):
            zk = zk * theta
            xm = h["X_maf"][k, j] + frac * (h["X_maf"][k + 1, j] - h["X_maf"][k, j])
            xp = h["X_p2"][k, j] + frac * (h["X_p2"][k + 1, j] - h["X_p2"][k, j])
            maf += (xm * zk).real
            p2 += (xp * zk).real
        T2 = lin("T2s")
        n_meas = n_true.copy()
        if self.noise:
            step = self.noise_block or n_samples
            r = np.concatenate([self.rng.standard_normal((4, min(step, n_samples - j)))
                                for j in range(0, n_samples, step)], axis=1)
            maf += p.sigma_maf * r[0]
            p2 += p.sigma_p2 * r[1]
            T2 += p.sigma_T2 * r[2]
            n_meas += p.sigma_n * r[3]
        values = np.vstack([n_meas, p2, T2, maf, h["fuel"][k], h["egr_cmd"][k],
                            h["swirl_cmd"][k], h["vgt_cmd"][k]])
        block = SampleBlock(plant=PLANT_ID, index=self._block_index, t=t, alpha=alpha,
                            channels=CHANNELS, units=UNITS, values=values)
        self._block_index += 1
        self._sample_index += n_samples
        # keep the history from the step holding the last sample on
        keep = int(k[-1])
        self._last_truth = {key: float(h[key][keep]) for key in h if key not in
                            ("X_maf", "X_p2")}
        self._last_harm = (h["X_maf"][keep].copy(), h["X_p2"][keep].copy())
        self._hist = {key: v[keep:] for key, v in h.items()}
        return block

    def truth(self) -> dict[str, float]:
        """True plant quantities at the last returned sample (noise-free, SI units).

        Keys include ``eta_v`` (engine gas flow / ideal displacement flow at the true manifold
        p2, T2), ``eta_v_air`` (metered-air share), flows ``m_maf, m_cyl, m_egr, m_leak,
        m_vent, m_bb, m_c`` [kg/s], pressures ``p1, p_ic, p2, p3`` [Pa], ``T2`` [K], ``vgt_pos``,
        the first-harmonic truths ``maf_amp`` [kg/h], ``maf_phase`` [deg CA], ``p2_amp`` [Pa],
        ``p2_phase`` [deg CA] (phase convention of :func:`fdi_ros.core.crank.segment_features`)
        and the active fault sizes ``fault:<id>``.
        """
        if not hasattr(self, "_last_truth"):
            raise RuntimeError("call advance() first")
        tr = dict(self._last_truth)
        xm, xp = self._last_harm
        p = self.p
        tr["eta_v_air"] = tr["m_maf"] / (tr["n"] / 120.0 * p.V_D * tr["p2"] / (p.R * tr["T2"]))
        tr["maf_amp"], tr["maf_phase"] = float(abs(xm[0])), _phase_deg(xm[0])
        tr["p2_amp"], tr["p2_phase"] = float(abs(xp[0])), _phase_deg(xp[0])
        for fid, key in zip(FAULT_IDS, ("u_vent", "u_leak", "u_restr", "u_swirl",
                                        "u_egr_stuck", "u_egr_leak")):
            tr[f"fault:{fid}"] = tr.pop(key)
        return tr


def _phase_deg(z: complex) -> float:
    """Phase of ``A cos(2 pi alpha/180 + phi)`` in deg CA, wrapped to [-90, 90)."""
    ph = math.degrees(math.atan2(z.imag, z.real)) / 2.0
    return (ph + 90.0) % 180.0 - 90.0


# ----------------------------------------------------------------------------- acoustics
def _line(beta_l: np.ndarray, z0) -> np.ndarray:
    m = np.empty(beta_l.shape + (2, 2), dtype=complex)
    c, s = np.cos(beta_l), np.sin(beta_l)
    m[..., 0, 0] = c
    m[..., 0, 1] = 1j * z0 * s
    m[..., 1, 0] = 1j * s / z0
    m[..., 1, 1] = c
    return m


def _unit_with(value: np.ndarray, row: int, col: int) -> np.ndarray:
    """Transfer matrices (..., 2, 2): the identity with ``value`` at (row, col)."""
    m = np.zeros(value.shape + (2, 2), dtype=complex)
    m[..., 0, 0] = 1.0
    m[..., row, col] = value
    m[..., 1, 1] = 1.0
    return m


def _series(z: np.ndarray) -> np.ndarray:
    """A series impedance ``z``: [[1, z], [0, 1]]."""
    return _unit_with(z, 0, 1)


def _shunt(y: np.ndarray) -> np.ndarray:
    """A shunt admittance ``y``: [[1, 0], [y, 1]]."""
    return _unit_with(y, 1, 0)


def pulsation_harmonics(rec: dict[str, np.ndarray], p: DieselParams,
                        c_suction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Complex harmonics of the MAF [kg/h] and p2 [Pa] sensor signals per slow step.

    Linear acoustics of the air path around each operating point (mass-flow two-ports
    ``[p_up, q_up] = M [p_down, q_down]``, chained from the ambient to the cylinders):

    ``R_af`` (filter, ``2 dp/m``) | air box ``j w C`` | duct a | **MAF** | duct b |
    inlet volume + vent admittance ``m_vent / (2 dp)`` | compressor ``[[1/PR, R_c/PR], [0, 1]]``
    with ``R_c = -p1 dPR/dm`` at frozen rotor speed | outlet volume | intercooler ``2 dp/m`` |
    intercooler volume + leak admittance | pipe and restriction ``2 (dp_pipe + dp_restr)/m_d``
    | duct d | manifold ``j w C_im`` + EGR admittance ``m_egr / (2 (p3 - p2))`` | **p2** |
    cylinders: suction source ``Q_k = m_cyl c_k / (1 + j w tau_port)``.

    Capacitances ``C = V / (kappa R T)``, ducts ``Z0 = c / A``, ``beta = w / c``. The ambient
    end is a pressure release. Harmonic k has ``w = k 2 pi n / 30`` rad/s. Returns arrays
    (steps, n_harmonics) with ``signal(alpha) = mean + sum_k Re(X_k exp(j k 2 pi alpha/180))``.
    """
    K = c_suction.size
    n = rec["n"]
    w = (2.0 * math.pi * n / 30.0)[:, None] * np.arange(1, K + 1)[None, :]
    kap, R = p.kappa, p.R
    T_amb = p.T_amb
    c_amb = math.sqrt(kap * R * T_amb)
    c_ic = np.sqrt(kap * R * rec["T_ic"])[:, None]
    eps = 1e-9
    col = (lambda v: np.asarray(v, float)[:, None])
    m_maf = np.maximum(rec["m_maf"], 1e-5)
    r_af = col(2.0 * (1.0 - p.duct_loss_share) * rec["dp_af"] / m_maf)
    r_duct = col(2.0 * p.duct_loss_share * rec["dp_af"] / m_maf)
    a_a, a_b, a_d = (math.pi / 4.0 * d ** 2 for d in (p.d_a, p.d_b, p.d_d))
    M = _series(r_af * np.ones_like(w))
    M = M @ _shunt(1j * w * p.V_ab / (kap * R * T_amb))
    M = M @ _line(w * p.l_a / c_amb, c_amb / a_a)
    A_up = M                                   # ambient .. MAF point
    y_vent = col(rec["m_vent"] / np.maximum(2.0 * rec["dp_af"], eps))
    B = _series(r_duct * np.ones_like(w)) @ _line(w * p.l_b / c_amb, c_amb / a_b)
    B = B @ _shunt(1j * w * p.V_1 / (kap * R * T_amb) + y_vent)
    pr = col(rec["pr_c"])
    r_c = col(-rec["p1"] * rec["dpr_dm"])
    comp = np.zeros(w.shape + (2, 2), dtype=complex)
    comp[..., 0, 0] = 1.0 / pr
    comp[..., 0, 1] = r_c / pr
    comp[..., 1, 1] = 1.0
    B = B @ comp
    T_hot = col(T_amb * rec["pr_c"] ** ((kap - 1.0) / kap) * 1.1)
    T_core = 0.5 * (T_hot + col(rec["T_ic"]))
    B = B @ _shunt(1j * w * p.V_co / (kap * R * T_core))
    m_c = np.maximum(rec["m_c"], 1e-5)
    B = B @ _series(col(2.0 * (rec["p_co"] - rec["p_ic"]) / m_c) * np.ones_like(w))
    dp_leak = np.maximum(rec["p_ic"] - p.p_amb, p.dp_lin)
    y_leak = col(rec["m_leak"] / (2.0 * dp_leak))
    B = B @ _shunt(1j * w * p.V_ic / (kap * R * col(rec["T_ic"])) + y_leak)
    m_d = np.maximum(np.abs(rec["m_d"]), 1e-5)
    B = B @ _series(col(2.0 * (np.abs(rec["dp_pipe"]) + np.abs(rec["dp_restr"])) / m_d)
                    * np.ones_like(w))
    B = B @ _line(w * p.l_d / c_ic, c_ic / a_d)
    dp_egr = np.maximum(np.abs(rec["p3"] - rec["p2"]), p.dp_lin)
    y_egr = col(np.abs(rec["m_egr"]) / (2.0 * dp_egr))
    B = B @ _shunt(1j * w * p.V_im / (kap * R * col(rec["T2"])) + y_egr)
    # cylinder suction through the (possibly throttled) ports: first-order port/cylinder lag
    r_port = 2.0 * rec["dp_port"] / np.maximum(p.port_peak * rec["m_cyl"], 1e-6)
    tau_port = r_port * p.V_cyl_eff / (kap * R * rec["T2"])
    q_n = col(rec["m_cyl"]) * c_suction[None, :] / (1.0 + 1j * w * col(tau_port))
    Mt = A_up @ B
    p_n = -Mt[..., 0, 1] / Mt[..., 0, 0] * q_n
    q_maf = B[..., 1, 0] * p_n + B[..., 1, 1] * q_n
    X_maf = 3600.0 * q_maf / (1.0 + 1j * w * p.tau_maf)
    X_p2 = p_n / (1.0 + 1j * w * p.tau_p2)
    return X_maf, X_p2
