"""The fresh-air volumetric efficiency with the EGR valve open, from the physics of the
exhaust side (a gray-box reference model).

With the valve closed the engine draws only fresh air, and the paper's map eta_V(n, rho2)
describes it. With the valve open the cylinders draw the same charge (the mixture at the
manifold's p2 and T2), but part of it is recirculated exhaust gas, which the MAF does not see:

    eta_fresh = eta_tot(n, rho2) - m_egr / m_th,      m_th = rho2 V_d n / 120.

``m_egr`` follows the exhaust manifold pressure p3, which no sensor gives. It is solved per
segment from the exhaust side's mass balance, the EGR valve and the VGT turbine in parallel
from p3 (isentropic orifices, the inlet density p3 / (R T3)):

    m_cyl + m_fuel = m_t + m_egr,
    m_t   = A_t(vgt) sqrt(2 p3 / (R T3)) sqrt(p3 - p4),
    m_egr = A_e egr^gamma sqrt(2 p3 / (R T3)) sqrt(p3 - p2)   (p3 > p2; below, the valve
            passes intake gas back: -A_e egr^gamma sqrt(2 p2 / (R T2)) sqrt(p2 - p3)),
    T3    = T2 + c_T m_fuel / (m_cyl + m_fuel)        (the fuel's heat in the exhaust),
    p4    = p_amb + k_x (m_cyl + m_fuel)^2             (the after-treatment's back pressure),
    A_t   = A_open - vgt (A_open - A_closed).

Six parameters (A_e, gamma, A_open, A_closed, c_T, k_x), identified by least squares on the
EGR-open segments of a fault-free drive (settled: the VGT command stands for its position, and
the temperature sensor's lag is undone); ``eta_tot`` is the EGR-closed reference map. A map of
six inputs learnt from data (LOLIMOT over n, rho2, egr, fuel, vgt, T2) learns the exhaust side
along the identification's trajectories only, and a drive lies between them; this structure
carries over (the README's coverage section has the figures).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from fdi_ros.core.constants import R_AIR

P_AMB = 1.013e5     # Pa, ambient (the model's reference; a sensor of it would replace it)
PARAMS = ("A_e", "gamma", "A_open", "A_closed", "c_T", "k_x")
# a starting point of the right orders of magnitude for a passenger-car diesel (not the
# answer: the fit moves every parameter by factors)
START = (2.0e-4, 1.0, 3.0e-4, 1.0e-4, 8000.0, 1.0e6)
LOWER = (1e-6, 0.3, 1e-6, 1e-7, 500.0, 1e3)
UPPER = (5e-3, 3.0, 5e-3, 5e-3, 5e4, 1e8)
INPUTS = ("n", "rho2", "T2", "fuel", "egr_cmd", "vgt")
# Pressure difference across the EGR valve [Pa] below which the flow model is not valid
BALANCED_PA = 1000.0


@dataclass(frozen=True)
class EgrFlowModel:
    """Fresh-air eta_V with the EGR valve open; ``theta`` by :data:`PARAMS`.

    ``eta_tot(n, rho2)``: the cylinders' total charge efficiency (the EGR-closed map).
    ``displacement_l``, ``n_cyl``: the engine's data.
    """

    theta: tuple[float, ...]
    displacement_l: float
    n_cyl: int
    #: the swirl flaps closed: the filling ports' loss takes the share
    #: ``port[0] + port[1] (n / 1000 rpm)^2 300 K / T2`` off the EGR-closed map's charge (the
    #: port's pressure drop ~ (flow / area)^2 / rho2, relative to p2 ~ n^2 / T2)
    port: tuple[float, float] = (0.0, 0.0)

    def charge(self, d: Mapping[str, np.ndarray], eta_tot: np.ndarray) -> np.ndarray:
        """The total charge efficiency: the EGR-closed map's, less the ports' loss."""
        if self.port == (0.0, 0.0):
            return np.asarray(eta_tot, dtype=float)
        x = (np.asarray(d["n"], dtype=float) / 1000.0) ** 2 * 300.0 / np.asarray(d["T2"],
                                                                                  dtype=float)
        return np.asarray(eta_tot, dtype=float) * (1.0 - self.port[0] - self.port[1] * x)

    def _exhaust(self, d: Mapping[str, np.ndarray], eta_tot: np.ndarray
                 ) -> dict[str, np.ndarray]:
        """The exhaust side's given quantities per segment: ``n, p2, T2, m_th, m_cyl, m_f,
        m_x, T3, p4, a_t`` (SI units)."""
        _, _, a_o, a_c, c_t, k_x = self.theta
        n = np.asarray(d["n"], dtype=float)
        rho2 = np.asarray(d["rho2"], dtype=float)
        T2 = np.asarray(d["T2"], dtype=float)
        m_th = rho2 * self.displacement_l * 1e-3 * n / 120.0
        m_cyl = self.charge(d, eta_tot) * m_th
        m_f = np.asarray(d["fuel"], dtype=float) * 1e-6 * n / 120.0 * self.n_cyl
        m_x = m_cyl + m_f
        vgt = np.clip(np.asarray(d["vgt"], dtype=float), 0.0, 1.0)
        return {"n": n, "p2": rho2 * R_AIR * T2, "T2": T2, "m_th": m_th, "m_cyl": m_cyl,
                "m_f": m_f, "m_x": m_x, "T3": T2 + c_t * m_f / np.maximum(m_x, 1e-9),
                "p4": P_AMB + k_x * m_x ** 2, "a_t": a_o - vgt * (a_o - a_c)}

    def closed_valve_p3(self, d: Mapping[str, np.ndarray], eta_tot: np.ndarray
                        ) -> np.ndarray:
        """p3 [Pa] per segment with the EGR valve closed: the turbine alone carries the exhaust
        flow, ``m_x^2 = a_t^2 (2 p3 / (R T3)) (p3 - p4)``, a quadratic in p3 (what
        :meth:`flows` solves by bisection with the valve at 0)."""
        return _closed_p3(self._exhaust(d, eta_tot))

    def closed_valve_margin(self, d: Mapping[str, np.ndarray], eta_tot: np.ndarray
                            ) -> np.ndarray:
        """``p3 - p2`` [Pa] per segment with the EGR valve closed: below 0 a valve that
        opened would pass boost air to the exhaust, a leak of the boost volume (``d``: the
        features of :data:`INPUTS`, the T2 lag undone)."""
        e = self._exhaust(d, eta_tot)
        return np.asarray(_closed_p3(e) - e["p2"])

    def closed_valve_leak(self, d: Mapping[str, np.ndarray], eta_tot: np.ndarray
                          ) -> np.ndarray:
        """Per segment, the flow through one square metre of leak across the closed EGR
        valve, relative to the cylinders' ``m_th`` [1/m^2]: ``sqrt(2 p3 / (R T3)) sqrt(p3 -
        p2) / m_th`` (exhaust gas into the manifold), negative where p2 exceeds p3 (intake gas
        to the exhaust, ``sqrt(2 p2 / (R T2)) sqrt(p2 - p3)``). A leak of effective area A
        lowers the fresh-air eta_V by A times this (the valve's own leak path: the exhaust
        side's p3 with the turbine alone carrying the flow, its change by the small leak
        neglected)."""
        e = self._exhaust(d, eta_tot)
        p3, p2 = _closed_p3(e), e["p2"]
        fwd = np.sqrt(2.0 * p3 / (R_AIR * e["T3"])) * np.sqrt(np.maximum(p3 - p2, 0.0))
        back = np.sqrt(2.0 * p2 / (R_AIR * e["T2"])) * np.sqrt(np.maximum(p2 - p3, 0.0))
        return np.asarray((fwd - back) / e["m_th"])

    def flows(self, d: Mapping[str, np.ndarray], eta_tot: np.ndarray
              ) -> dict[str, np.ndarray]:
        """Per segment: ``m_th, m_cyl, m_fuel, m_egr, m_t, p3, T3, p4`` (SI units)."""
        a_e, gam = self.theta[:2]
        e = self._exhaust(d, eta_tot)
        p2, T2, m_th, m_cyl, m_f, m_x = (e[k] for k in ("p2", "T2", "m_th", "m_cyl", "m_f",
                                                          "m_x"))
        T3, p4, a_t = e["T3"], e["p4"], e["a_t"]
        a_egr = a_e * np.clip(np.asarray(d["egr_cmd"], dtype=float), 0.0, 1.0) ** gam
        k3 = np.sqrt(2.0 / (R_AIR * T3))
        back = a_egr * np.sqrt(2.0 * p2 / (R_AIR * T2))  # intake gas, the other way

        def out(p3: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            s = k3 * np.sqrt(p3)
            return (s * a_t * np.sqrt(np.maximum(p3 - p4, 0.0)),
                    s * a_egr * np.sqrt(np.maximum(p3 - p2, 0.0))
                    - back * np.sqrt(np.maximum(p2 - p3, 0.0)))

        # the outflow grows with p3 from p4 on: bisection, vectorised over the segments
        lo = p4.copy()
        hi = p4 + 1e4
        for _ in range(60):
            short = sum(out(hi)) < m_x
            if not short.any():
                break
            hi = np.where(short, lo + 2.0 * (hi - lo), hi)
        for _ in range(48):
            mid = 0.5 * (lo + hi)
            below = sum(out(mid)) < m_x
            lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
        p3 = 0.5 * (lo + hi)
        m_t, m_egr = out(p3)
        return {"m_th": m_th, "m_cyl": m_cyl, "m_fuel": m_f, "m_egr": m_egr, "m_t": m_t,
                "p2": p2,
                "p3": p3, "T3": T3, "p4": p4}

    def eta_fresh(self, d: Mapping[str, np.ndarray], eta_tot: np.ndarray) -> np.ndarray:
        """The fresh-air volumetric efficiency the MAF sees (eta_V of the features)."""
        f = self.flows(d, eta_tot)
        return np.asarray((f["m_cyl"] - f["m_egr"]) / f["m_th"])

    def to_dict(self) -> dict:
        return {"type": "diesel_egr_flow", "params": dict(zip(PARAMS, map(float, self.theta))),
                "port": [float(v) for v in self.port],
                "displacement_l": self.displacement_l, "n_cyl": self.n_cyl}

    @classmethod
    def from_dict(cls, d: Mapping) -> EgrFlowModel:
        if d.get("type") != "diesel_egr_flow":
            raise ValueError(f"not an EGR flow model: type {d.get('type')!r}")
        p = d["params"]
        port = tuple(float(v) for v in d.get("port", (0.0, 0.0)))
        if len(port) != 2:
            raise ValueError(f"port: two coefficients, not {port}")
        return cls(theta=tuple(float(p[k]) for k in PARAMS),
                   displacement_l=float(d["displacement_l"]), n_cyl=int(d["n_cyl"]),
                   port=(port[0], port[1]))


@dataclass(frozen=True)
class EgrFlowFit:
    model: EgrFlowModel
    rmse: float
    n_segments: int
    nfev: int
    success: bool
    message: str


def fit(d: Mapping[str, np.ndarray], eta_tot: np.ndarray, eta_v: np.ndarray, *,
        displacement_l: float, n_cyl: int, start: tuple[float, ...] = START,
        port: bool = False, max_segments: int = 6000, seed: int = 0) -> EgrFlowFit:
    """Identify :data:`PARAMS` (and with ``port`` the two port-loss coefficients, the flaps
    closed) by least squares (scipy's trust-region reflective, the six on a log scale within
    :data:`LOWER`..:data:`UPPER`) on segments ``d`` (arrays of :data:`INPUTS`) with measured
    fresh-air ``eta_v``; at most ``max_segments`` of them, drawn at random."""
    from scipy.optimize import least_squares

    eta_v = np.asarray(eta_v, dtype=float)
    cols = {k: np.asarray(d[k], dtype=float) for k in INPUTS}
    ok = np.isfinite(eta_v) & np.isfinite(eta_tot) & np.all(
        [np.isfinite(v) for v in cols.values()], axis=0) & (cols["egr_cmd"] > 0)
    idx = np.flatnonzero(ok)
    if idx.size < 50:
        raise ValueError(f"{idx.size} usable EGR-open segments: too few to identify the "
                         "EGR flow model")
    if idx.size > max_segments:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_segments, replace=False))
    sub = {k: v[idx] for k, v in cols.items()}
    et, y = np.asarray(eta_tot, dtype=float)[idx], eta_v[idx]
    k = len(PARAMS)
    lo = np.r_[np.log(LOWER), [-0.5, -0.5][:2 * port]]
    hi = np.r_[np.log(UPPER), [0.5, 0.5][:2 * port]]
    x0 = np.clip(np.r_[np.log(start), [0.0, 0.0][:2 * port]], lo + 1e-9, hi - 1e-9)

    def model_of(x: np.ndarray) -> EgrFlowModel:
        pt = (float(x[k]), float(x[k + 1])) if port else (0.0, 0.0)
        return EgrFlowModel(tuple(float(v) for v in np.exp(x[:k])), displacement_l, n_cyl,
                            port=pt)

    r = least_squares(lambda x: model_of(x).eta_fresh(sub, et) - y, x0, bounds=(lo, hi),
                      method="trf", x_scale="jac", diff_step=1e-6, max_nfev=400)
    model = model_of(r.x)
    return EgrFlowFit(model, float(np.sqrt(np.mean(r.fun ** 2))), int(idx.size),
                      int(r.nfev), bool(r.success), str(r.message))


def settled(d: Mapping[str, np.ndarray], *, t2_rate: float = 3.0, window: int = 66,
            rel_step: float = 0.02) -> np.ndarray:
    """Segments in quasi-stationary operation for the exhaust side: the T2 sensor settled
    (``|T2_rate|`` at most ``t2_rate`` K/s), and speed, fuel, VGT and EGR commands within
    ``rel_step`` of their span over the last ``window`` segments (the VGT's and the
    turbocharger's lags, about a second)."""
    n = np.asarray(d["n"]).size
    if n <= window:
        return np.zeros(n, dtype=bool)
    ok = np.abs(np.nan_to_num(np.asarray(d.get("T2_rate", np.zeros(n)), dtype=float),
                              nan=np.inf)) <= t2_rate
    for k, scale in (("n", 5500.0), ("fuel", 60.0), ("vgt", 1.0), ("egr_cmd", 1.0)):
        w = sliding_window_view(np.asarray(d[k], dtype=float), window)
        span = np.full(n, np.inf)
        span[window - 1:] = w.max(axis=1) - w.min(axis=1)
        ok &= span <= rel_step * scale
    return ok


SUFFIX = ".egrflow.json"  # beside the regime's eta_v.npz: the flow model of that map


class EgrFlowEta:
    """The eta_V map of an EGR-open regime as the reference model set evaluates its maps
    (``predict(X)``, ``in_region(X)``, ``save(path)``; ``X``'s columns named by ``inputs``):
    :class:`EgrFlowModel` over the EGR-closed regime's map ``base`` (of n, rho2), saved with
    the regime's own data map ``region`` (a LOLIMOT of the same inputs). The flows of the last
    rows asked are kept: the model set asks for the region and then the values of the same
    rows, and solving p3 is most of the cost."""

    def __init__(self, flow: EgrFlowModel, base: Any, region: Any,
                 inputs: tuple[str, ...]) -> None:
        missing = [k for k in INPUTS if k not in inputs]
        if missing:
            raise ValueError(f"the EGR flow model needs the inputs {missing}")
        self.flow, self.base, self.region, self.inputs = flow, base, region, tuple(inputs)
        self._last: tuple[tuple[tuple[int, ...], bytes], dict[str, np.ndarray]] | None = None

    def _data(self, X: np.ndarray) -> dict[str, np.ndarray]:
        X = np.atleast_2d(np.asarray(X, dtype=float))
        return {k: X[:, self.inputs.index(k)] for k in INPUTS}

    def flows_of(self, X: np.ndarray) -> dict[str, np.ndarray]:
        """:meth:`EgrFlowModel.flows` at the rows ``X`` (the last rows' are kept)."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        key, last = (X.shape, X.tobytes()), self._last
        if last is not None and last[0] == key:
            return last[1]
        d = self._data(X)
        f = self.flow.flows(d, self.base.predict(np.column_stack([d["n"], d["rho2"]])))
        self._last = (key, f)
        return f

    def predict(self, X: np.ndarray) -> np.ndarray:
        f = self.flows_of(X)
        return np.asarray((f["m_cyl"] - f["m_egr"]) / f["m_th"])

    def in_region(self, X: np.ndarray) -> np.ndarray:
        """Within the regime's box of every input (its validity, checked apart; the structure
        carries over between the identification's passes and beyond the base map's (n, rho2)
        coverage, measured on a drive it never saw, README), but not with the valve nearly
        balanced: within :data:`BALANCED_PA` of p2 the exhaust pulses push the flow both ways
        in every cycle, and a mean-value orifice does not say how much passes."""
        return np.abs(self._valve_dp(X)) >= BALANCED_PA

    def _valve_dp(self, X: np.ndarray) -> np.ndarray:
        f = self.flows_of(X)
        return np.asarray(f["p3"] - f["p2"])

    def outside(self, X: np.ndarray) -> list[str]:
        """Why each row is outside :meth:`in_region` ("" inside)."""
        return ["" if abs(dp) >= BALANCED_PA else
                f"not valid here: EGR valve nearly balanced (p3 - p2 = {dp:.0f} Pa, within "
                f"{BALANCED_PA:.0f} Pa: the exhaust pulses push the flow both ways)"
                for dp in self._valve_dp(X)]

    def save(self, path: str | Path) -> None:
        path = Path(path)
        self.region.save(path)
        path.with_name(path.stem + SUFFIX).write_text(json.dumps(self.flow.to_dict(), indent=1))

    @classmethod
    def load_beside(cls, path: str | Path, region: Any, base: Any,
                    inputs: tuple[str, ...]) -> Any:
        """The map saved at ``path``: this class if a flow model was saved beside it, else
        ``region`` itself (a plain data map)."""
        path = Path(path)
        side = path.with_name(path.stem + SUFFIX)
        if not side.exists():
            return region
        try:
            flow = EgrFlowModel.from_dict(json.loads(side.read_text()))
        except (KeyError, TypeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{side}: malformed EGR flow model: {exc}") from exc
        return cls(flow, base, region, inputs)


def _closed_p3(e: Mapping[str, np.ndarray]) -> np.ndarray:
    """The root of ``m_x^2 = a_t^2 (2 p3 / (R T3)) (p3 - p4)`` from the exhaust side's given
    quantities ``e`` (:meth:`EgrFlowModel._exhaust`)."""
    c = e["m_x"] ** 2 * R_AIR * e["T3"] / (2.0 * np.maximum(e["a_t"], 1e-12) ** 2)
    return np.asarray(0.5 * (e["p4"] + np.sqrt(e["p4"] ** 2 + 4.0 * c)))
