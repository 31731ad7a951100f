"""The project's diesel reference models (LOLIMOT / ECU tables) as a discrepancy baseline.

``maf = eta_V,ref(n, rho2) * m_th``, ``m_th = n/120 * V_D * rho2`` (paper eq. 1-3), with the
look-up tables identified by ``fdi-ros identify`` (``build/models/diesel``). Mean-value only:
with crank-angle data the analysis runs on 180 deg CA segment means. Operating points outside
the identified region are NaN (masked).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fdi_ros.core.crank import segment_rates
from fdi_ros.core.discrepancy.context import LeakSpec
from fdi_ros.core.discrepancy.model import BASELINES
from fdi_ros.core.measured import Measured
from fdi_ros.plants.diesel.plant import T2_RATE_LAG, T2_RATE_ORDER, DieselParams

# as in the plant and the reference identification (one source: the plant's parameters)
R_DIESEL = DieselParams().R  # J/(kg K)
DISPLACEMENT_L = DieselParams().V_D * 1e3


@BASELINES.register("diesel_reference_baseline")
@dataclass(frozen=True)
class DieselReferenceBaseline:
    """Speed-density air flow with the identified reference eta_V tables."""

    path: str
    displacement_l: float = DISPLACEMENT_L
    use_tables: bool = True
    kind: str = field(default="diesel_reference_baseline", init=False)

    @property
    def _ref(self):
        from fdi_ros.plants.diesel.reference import ReferenceModelSet

        cache = self.__dict__.get("_cache")
        if cache is None:
            cache = ReferenceModelSet.load(self.path)
            object.__setattr__(self, "_cache", cache)
        return cache

    inputs = ("n", "p2", "T2")
    channels = ("maf",)
    orders = ()

    @property
    def leaks(self) -> tuple[LeakSpec, ...]:
        return (LeakSpec(channel="maf", p_in="p2", T_in="T2", p_amb=101325.0, T_amb=298.0,
                         flow_scale=3600.0, cd=0.65),)

    def _rho2(self, data: Measured) -> np.ndarray:
        """Boost density from p2 and T2, the T2 sensor's lag undone as the reference models
        were identified (``T2 + tau dT2/dt``, the rate taken as the crank preprocessor takes
        it: :func:`~fdi_ros.core.crank.segment_rates` over T2_RATE_LAG segments back)."""
        T2 = np.asarray(data["T2"], float)
        tau = self._ref.t2_tau
        if tau > 0 and T2.size > T2_RATE_LAG:
            t = np.asarray(data.t, float)
            ok = np.isfinite(T2) & np.isfinite(t) & np.r_[True, np.diff(t) > 0]
            rate = segment_rates(np.arange(T2.size), t, ok, T2, T2_RATE_LAG, T2_RATE_ORDER)
            T2 = T2 + tau * np.where(np.isfinite(rate), rate, 0.0)
        return np.asarray(data["p2"], float) / (R_DIESEL * T2)

    def region(self, data: Measured) -> dict[str, np.ndarray]:
        return {"n": data["n"], "rho2": self._rho2(data)}

    def without_pulsation(self) -> DieselReferenceBaseline:
        return self

    def predict(self, data: Measured) -> dict[str, np.ndarray]:
        n = np.asarray(data["n"], float)
        rho2 = self._rho2(data)
        ok = np.isfinite(n) & np.isfinite(rho2)
        eta = np.full(n.shape, np.nan)
        if ok.any():
            out, valid = self._ref.predict(n[ok], rho2[ok], use_tables=self.use_tables,
                                           phases=False)
            eta[ok] = np.where(valid, out["eta_v"], np.nan)
        m_th = n / 120.0 * self.displacement_l * 1e-3 * rho2 * 3600.0
        return {"maf": eta * m_th}

    def to_dict(self) -> dict:
        return {"type": self.kind, "path": self.path, "displacement_l": self.displacement_l,
                "use_tables": self.use_tables}

    @classmethod
    def from_dict(cls, d: dict) -> DieselReferenceBaseline:
        return cls(path=d["path"], displacement_l=float(d.get("displacement_l", DISPLACEMENT_L)),
                   use_tables=bool(d.get("use_tables", True)))
