"""The crank pulsations with the EGR valve open, relative to the EGR-closed maps (a gray-box
reference model).

The cylinders' suction drives the intake's pulsation; its harmonics travel up the air path
to the MAF and the p2 sensors (linear acoustics, module ``plant``). With the EGR valve open
the source is the same charge at the same (n, rho2): the EGR-closed map's. What changes is
the path: the valve is a shunt at the manifold that takes part of the pulsating flow, and the
fresh air's mean flow, which sets the air path's resistances, is smaller by the recirculated
share. So the EGR-open harmonic is the EGR-closed one times a transfer ratio of the speed
(the frequency), the recirculated share of the charge ``x_egr = m_egr / m_cyl`` and the
valve's acoustic admittance relative to the cylinders', ``y_egr = (m_egr / 2 |p3 - p2|) /
(m_cyl / p2) = x_egr p2 / (2 |p3 - p2|)`` (a linearised orifice: a wide-open valve nearly
balanced is a large shunt at the manifold; |p3 - p2| at least 1 kPa, where the flow model
holds):

    X_open(n, rho2, ...) = X_closed(n, rho2) * H(n, x_egr, log y_egr),
    log |H| and arg H: LOLIMOT maps, x_egr and p3 from the EGR flow model (module
    ``egrflow``: the exhaust side's physics, which no sensor gives).

Maps of the harmonics themselves over the six inputs the EGR flow needs (n, rho2, egr, fuel,
vgt, T2) learn the pulsation along the identification's passes only and miss a drive between
them (held-out NRMSE 0.2-0.9 on a drive they never saw); the ratio over the physical
inputs carries over (README). It is valid where the EGR-closed maps are (their (n, rho2)
coverage), its own (n, x_egr) coverage holds and the admittance lies within the identified
range (a random fault-free point with the valve at 0.69 near full load, 2 kPa from balance,
had log y_egr 2.28 against at most 1.84 in the passes, and its p2 amplitude 30 % below the
map's): elsewhere the EGR-open regime is judged on eta_V alone.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from fdi_ros.plants.diesel.egrflow import BALANCED_PA

__all__ = ["HARMONICS", "JUDGED", "RATIO_INPUTS", "PulsationRatio", "RatioContext",
           "base_harmonics", "fit_ratio_maps", "ratio_inputs", "ratio_targets"]

# The harmonics' outputs: amplitude [unit] and phase [deg CA] per sensor
HARMONICS = {"maf": ("maf_amp", "maf_phase"), "p2": ("p2_amp", "p2_phase")}
# (|p3 - p2| at least egrflow.BALANCED_PA for the admittance: the flow model does not hold
# nearer balance, and those segments are outside the EGR-open regimes)
RATIO_INPUTS = ("n", "x_egr", "log_y_egr")
# The outputs judged where the ratio holds: eta_V, both amplitudes and the p2 phase. Not the
# MAF phase: it falls steeply with speed near its wrap (about 2350 rpm), and its ratio map
# missed drives it never saw by 7-8.6 deg CA (99th percentile, three drives; the p2 phase's
# 3.6-6.8; on one a steady 5 deg at 2110 rpm with the valve at 0.45, a false symptom), while
# the faults move it by at most 3.5 deg where the valve and the flaps are open, but for
# those the amplitudes see anyway (flaps stuck closed, valve stuck open).
JUDGED = ("eta_v", "maf_amp", "p2_amp", "p2_phase")
# Fewest identification segments a cell of the ratio maps' (n, x_egr) coverage grid needs to
# count as identified (16 x 16 cells)
MIN_CELL_SEGMENTS = 30
# One period of the harmonics' phase [deg CA] (reference.PERIOD_DEG; this module is imported
# by reference and does not import it)
PERIOD_DEG = 180.0


def _wrap(x: np.ndarray) -> np.ndarray:
    return (np.asarray(x, dtype=float) + 0.5 * PERIOD_DEG) % PERIOD_DEG - 0.5 * PERIOD_DEG


def base_harmonics(base: Mapping[str, Any], n: np.ndarray, rho2: np.ndarray
                   ) -> dict[str, np.ndarray]:
    """The EGR-closed maps' amplitudes and phases at (n, rho2) (their LOLIMOT models; a phase
    from its phasor maps ``<phase>_cos``, ``<phase>_sin``)."""
    X = np.column_stack([n, rho2])
    out = {}
    for amp, ph in HARMONICS.values():
        out[amp] = np.asarray(base[amp].predict(X), dtype=float)
        u = base[f"{ph}_cos"].predict(X)
        v = base[f"{ph}_sin"].predict(X)
        out[ph] = np.degrees(np.arctan2(v, u)) * PERIOD_DEG / 360.0
    return out


def ratio_inputs(flow: Any, X: np.ndarray, inputs: tuple[str, ...]) -> np.ndarray:
    """The ratio maps' inputs (:data:`RATIO_INPUTS`) per row of ``X`` (columns ``inputs``),
    the share and the admittance from the EGR flow model ``flow``
    (:class:`.egrflow.EgrFlowEta`)."""
    X = np.atleast_2d(np.asarray(X, dtype=float))
    f = flow.flows_of(X)
    x = np.asarray(f["m_egr"] / np.maximum(f["m_cyl"], 1e-9))
    dp = np.maximum(np.abs(f["p3"] - f["p2"]), BALANCED_PA)
    y = np.maximum(np.abs(x) * f["p2"] / (2.0 * dp), 1e-6)
    return np.column_stack([X[:, inputs.index("n")], x, np.log(y)])


def ratio_targets(data: Mapping[str, np.ndarray], ref: Mapping[str, np.ndarray]
                  ) -> dict[str, np.ndarray]:
    """Per output, the ratio map's target: log of the amplitude ratio, the phase difference
    [deg CA] wrapped to +-90."""
    out = {}
    for amp, ph in HARMONICS.values():
        with np.errstate(divide="ignore", invalid="ignore"):
            out[amp] = np.log(np.asarray(data[amp], dtype=float) / ref[amp])
        out[ph] = _wrap(np.asarray(data[ph], dtype=float) - ref[ph])
    return out


class RatioContext:
    """The EGR-open harmonics of one regime: ``flow`` (its eta_V model,
    :class:`.egrflow.EgrFlowEta`, which gives ``x_egr``), ``base`` (the EGR-closed set's
    LOLIMOT maps by output) and ``ratio`` (the ratio maps by output, over
    :data:`RATIO_INPUTS`). Rows ``X`` are the regime's inputs (``inputs``); the last rows
    asked are kept (the model set asks each output in turn for the same rows)."""

    def __init__(self, flow: Any, base: Mapping[str, Any], ratio: Mapping[str, Any],
                 inputs: tuple[str, ...]) -> None:
        missing = [k for k in ("n", "rho2") if k not in inputs]
        if missing:
            raise ValueError(f"the pulsation ratio needs the inputs {missing}")
        self.flow, self.base, self.ratio, self.inputs = flow, dict(base), dict(ratio), inputs
        self._last: tuple[tuple[tuple[int, ...], bytes], dict[str, np.ndarray]] | None = None

    def evaluate(self, X: np.ndarray) -> dict[str, np.ndarray]:
        """The four harmonics' values and ``valid`` (within the EGR-closed maps' and the
        ratio maps' coverage) per row."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        key, last = (X.shape, X.tobytes()), self._last
        if last is not None and last[0] == key:
            return last[1]
        n, rho2 = X[:, self.inputs.index("n")], X[:, self.inputs.index("rho2")]
        ref = base_harmonics(self.base, n, rho2)
        R = ratio_inputs(self.flow, X, self.inputs)
        out = {"valid": self.base["eta_v"].in_region(np.column_stack([n, rho2]))
               & self.ratio[HARMONICS["maf"][0]].in_region(R)}
        for amp, ph in HARMONICS.values():
            out[amp] = ref[amp] * np.exp(self.ratio[amp].predict(R))
            out[ph] = _wrap(ref[ph] + self.ratio[ph].predict(R))
        self._last = (key, out)
        return out


class PulsationRatio:
    """One output of :class:`RatioContext` as the reference model set evaluates its maps
    (``predict(X)``, ``valid_rows(X)``, ``save(path)``: the ratio map is what is saved)."""

    def __init__(self, context: RatioContext, output: str) -> None:
        if output not in context.ratio:
            raise ValueError(f"no ratio map of {output}")
        self.context, self.output = context, output

    def predict(self, X: np.ndarray) -> np.ndarray:
        return np.asarray(self.context.evaluate(X)[self.output])

    def valid_rows(self, X: np.ndarray) -> np.ndarray:
        return np.asarray(self.context.evaluate(X)["valid"])

    def save(self, path: Any) -> Any:
        return self.context.ratio[self.output].save(path)


def fit_ratio_maps(R: np.ndarray, targets: Mapping[str, np.ndarray], fit: np.ndarray,
                   strong: Mapping[str, np.ndarray], region: np.ndarray, *,
                   max_models: int = 12, coverage_min_count: int = MIN_CELL_SEGMENTS
                   ) -> dict[str, Any]:
    """LOLIMOT ratio maps over ``R`` (columns :data:`RATIO_INPUTS`) fitted on the rows
    ``fit``, a phase's only where its harmonic is strong enough to have one (``strong[phase]``,
    a flag per row); the coverage (kept by the MAF amplitude's map) from the rows ``region``
    (every row of the passes, the held-out ones included)."""
    from fdi_ros.core.lolimot import Lolimot

    maps = {}
    for amp, ph in HARMONICS.values():
        for k, use in ((amp, fit), (ph, fit[strong[ph][fit]])):
            ok = use[np.isfinite(targets[k][use]) & np.all(np.isfinite(R[use]), axis=1)]
            # the coverage grid over (n, x_egr), the admittance within its identified range
            m = Lolimot(max_models=max_models, min_samples_per_model=50,
                        coverage_min_count=coverage_min_count, coverage_inputs=2)
            m.fit(R[ok], targets[k][ok], input_names=RATIO_INPUTS, output_name=f"H_{k}")
            maps[k] = m
    maps[HARMONICS["maf"][0]].set_region(R[region])
    return maps
