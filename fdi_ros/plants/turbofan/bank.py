"""The paper's bank of 16 turbofan models, its residuals, and the diagnosis scenarios.

Bank (Diao & Passino 2004, section 4): M0 nominal, M1-M3 fan fault small/medium/large, M4-M6
compressor-hub fault small/medium/large, M7-M15 the nine fan x hub double faults. Model i is
the global TS model (:mod:`~fdi_ros.plants.turbofan.models`) at the engine's operating condition,
its deterioration index (assumed known from the maintenance record, as the paper's design model
captures deterioration) and the fault sizes of situation i; manufacturing variation is left as
model uncertainty. Residual ``r_i(k) = XN2(k) - XN2hat_i(k)`` with the model run open loop
(Euler, Ts) from the measured state at its start.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fdi_ros.core.supervisor import BankModel, ExpertSupervisor, fault_type, sized_bank
from fdi_ros.core.types import FeatureVector, ResidualVector
from fdi_ros.plants.turbofan import plant as tfp
from fdi_ros.plants.turbofan.models import GlobalModel, Mixture

PAPER_BANK: tuple[BankModel, ...] = tuple(sized_bank(("fan", "hub")))
DEFAULT_MODEL_PATH = Path("build/turbofan/global_model.npz")


def faults_of(model_id: str) -> frozenset[str]:
    """Fault ids of a bank model id: ``"nominal" -> {}``, ``"fan_small+hub_large"`` -> both."""
    if model_id == "nominal":
        return frozenset()
    return frozenset(model_id.split("+"))


def fault_units(faults: Sequence[str] | frozenset[str]) -> dict[str, float]:
    """Fault sizes in units of the small fault per type: ``{"fan": 1.0, "hub": 4.0}``."""
    out = {"fan": 0.0, "hub": 0.0}
    for f in faults:
        kind = fault_type(f)
        size = f[len(kind) + 1:] if f != kind else "small"
        if kind not in out:
            raise ValueError(f"fault {f!r}: the turbofan bank knows only fan and hub faults")
        out[kind] = tfp.fault_size(kind, size)
    return out


def residual_norm(r_xnl, r_xnh, xnh_weight: float):
    """Residual norm ``sqrt(r_XN2^2 + (w r_XNH)^2)`` [rpm]; w = 0 is the paper's |r_XN2|."""
    if xnh_weight == 0:
        return np.abs(r_xnl)
    return np.hypot(r_xnl, xnh_weight * np.asarray(r_xnh))


def bank_mixture(gm: GlobalModel, model_ids: Sequence[str], *, condition,
                 deterioration: float) -> Mixture:
    """Interpolated dynamics of the given bank models at (condition, deterioration)."""
    vs = []
    for mid in model_ids:
        u = fault_units(faults_of(mid))
        vs.append(gm.coordinates(condition, deterioration, u["fan"], u["hub"]))
    return gm.mixture(np.array(vs))


# -- live residual model (one bank model per node) ------------------------------------------------
class TurbofanResidualModel:
    """One bank model as a residual generator for the live graph (``type: turbofan_ts``).

    Each :class:`FeatureVector` is one sample with names ``XNL`` (or ``XN2``), ``XNH`` and
    ``WF36``. On the first sample after :meth:`reset` the model state is set to the measured
    (XNL, XNH); afterwards it runs open loop (``feed_measured=False``, the paper) or as a
    one-step predictor. Residuals ``(XN2 - XN2hat, XNH - XNHhat)`` [rpm], ``norm`` by
    :func:`residual_norm` (``xnh_weight = 0``: the paper's |r_XN2|).

    Invalid results (``valid=False``) with ``status``: ``invalid_input`` (NaN, missing
    channel, invalid feature vector), ``outside_region`` (fan speed outside the trained range).
    The operating condition and fault sizes are checked at construction (ValueError).
    """

    def __init__(self, *, global_model: GlobalModel, model_id: str, condition,
                 deterioration: float, faults: Sequence[str] | None = None, ts: float = 0.02,
                 feed_measured: bool = False, xnh_weight: float = 0.0,
                 region_margin_rpm: float = 150.0) -> None:
        self.model_id = model_id
        if not (math.isfinite(xnh_weight) and xnh_weight >= 0):
            raise ValueError("xnh_weight must be >= 0")
        self.xnh_weight = float(xnh_weight)
        self.faults = faults_of(model_id) if faults is None else frozenset(faults)
        units = fault_units(self.faults)
        cond = np.asarray(condition, dtype=float)
        self._mix = global_model.mixture(global_model.coordinates(
            cond, float(deterioration), units["fan"], units["hub"])[None])
        if not ts > 0:
            raise ValueError("ts must be > 0")
        self.ts = float(ts)
        self.feed_measured = bool(feed_measured)
        lo, hi = global_model.xnl_range
        self._range = (lo - region_margin_rpm, hi + region_margin_rpm)
        self.reset()

    def reset(self) -> None:
        self._x: np.ndarray | None = None
        self._t_last = math.nan
        self._u_last = math.nan

    def _result(self, fv: FeatureVector, r: np.ndarray, valid: bool,
                status: str) -> ResidualVector:
        norm = float(residual_norm(r[0], r[1], self.xnh_weight)) if valid else math.nan
        return ResidualVector(model_id=self.model_id, index=fv.index, t=float(fv.t_start),
                              valid=valid, status=status, names=("XN2", "XNH"),
                              units=("rpm", "rpm"), values=r, norm=norm)

    def residuals(self, fv: FeatureVector) -> ResidualVector:
        vals = fv.as_dict()
        xnl = vals.get("XNL", vals.get("XN2", math.nan))
        xnh, wf = vals.get("XNH", math.nan), vals.get("WF36", math.nan)
        t = float(fv.t_start)
        if not (fv.valid and math.isfinite(xnl) and math.isfinite(xnh) and math.isfinite(wf)
                and math.isfinite(t)):
            return self._result(fv, np.full(2, math.nan), False, "invalid_input")
        if not self._range[0] <= xnl <= self._range[1]:
            self.reset()
            return self._result(fv, np.full(2, math.nan), False, "outside_region")
        if self._x is None or self.feed_measured:
            self._x = np.array([[xnl, xnh]])
        else:
            # advance from the previous sample to this one with the previous input (ZOH)
            steps = int(round((t - self._t_last) / self.ts))
            if steps < 1 or steps > 50:
                self._x = np.array([[xnl, xnh]])  # time went back or a long gap: restart
            else:
                for _ in range(steps):
                    self._x = self._x + self.ts * self._mix.derivatives(self._x, self._u_last)
        r = np.array([xnl, xnh]) - self._x[0]
        self._t_last, self._u_last = t, wf
        if not np.all(np.isfinite(r)):
            self.reset()
            return self._result(fv, np.full(2, math.nan), False, "outside_region")
        return self._result(fv, r, True, "ok")


_MODEL_CACHE: dict[tuple[str, float], GlobalModel] = {}


def load_global_model(path: str | Path) -> GlobalModel:
    """Load (and cache per process) a global model file."""
    p = Path(path).resolve()
    key = (str(p), p.stat().st_mtime if p.exists() else 0.0)
    if key not in _MODEL_CACHE:
        _MODEL_CACHE[key] = GlobalModel.load(p)
    return _MODEL_CACHE[key]


def _register() -> None:
    from fdi_ros.core.residual_models import register_residual_model

    @register_residual_model("turbofan_ts")
    def make_turbofan_ts(spec: Mapping, *, base_dir: Path, model_id: str):
        known = {"path", "condition", "deterioration", "faults", "ts", "feed_measured",
                 "xnh_weight"}
        unknown = set(spec) - known
        if unknown:
            raise ValueError(f"turbofan_ts: unknown key(s) {sorted(unknown)}; known {known}")
        path = Path(spec.get("path", DEFAULT_MODEL_PATH))
        if not path.is_absolute():
            # relative to the spec's directory, else to the repository root
            cands = [base_dir / path, Path(__file__).resolve().parents[3] / path]
            path = next((c for c in cands if c.exists()), cands[0])
        cond = spec.get("condition", list(tfp.PAPER_CONDITION))
        faults = spec.get("faults")
        return TurbofanResidualModel(
            global_model=load_global_model(path), model_id=model_id, condition=cond,
            deterioration=float(spec.get("deterioration", 0.1)),
            faults=None if faults is None else list(faults), ts=float(spec.get("ts", 0.02)),
            feed_measured=bool(spec.get("feed_measured", False)),
            xnh_weight=float(spec.get("xnh_weight", 0.0)))


_register()


# -- offline scenarios ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Scenario:
    """A diagnosis run: fault events ``(t [s], {type: size})`` (sizes replace earlier ones)."""

    name: str
    events: tuple = ()
    duration_s: float = 20.0
    condition: tuple = tfp.PAPER_CONDITION
    deterioration: float = 0.1
    manufacturing: np.ndarray = field(default_factory=lambda: tfp.PAPER_MANUFACTURING.copy())
    seed: int = 0
    paper: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.duration_s > 0:
            raise ValueError("duration_s must be > 0")
        times = [float(t) for t, _ in self.events]
        if any(t < 0 or t >= self.duration_s for t in times) or times != sorted(times):
            raise ValueError(f"scenario {self.name}: event times must be sorted in "
                             f"[0, {self.duration_s})")
        for _, faults in self.events:
            tfp.Health(faults=dict(faults))  # validates fault names and sizes
        tfp.check_condition(np.asarray(self.condition, dtype=float))

    def faults_at(self, t: float) -> dict:
        out: dict = {}
        for te, faults in self.events:
            if t >= te - 1e-9:
                out.update(faults)
        return {k: v for k, v in out.items() if tfp.fault_size(k, v) > 0}

    def true_model(self, t: float) -> str:
        f = self.faults_at(t)
        parts = [f"{k}_{f[k]}" for k in ("fan", "hub") if k in f]
        return "+".join(parts) if parts else "nominal"

    def quality_profile(self, n: int, ts: float) -> np.ndarray:
        """(n, 10) quality deviations per sample."""
        out = np.empty((n, 10))
        for k in range(n):
            out[k] = tfp.Health(manufacturing=self.manufacturing,
                                deterioration=self.deterioration,
                                faults=self.faults_at(k * ts)).quality()
        return out


@dataclass
class ScenarioResult:
    scenario: Scenario
    t: np.ndarray
    y: np.ndarray  # (n, 2) measured XN2, XNH
    wf: np.ndarray
    yhat: np.ndarray  # (16, n) model XN2
    residuals: np.ndarray  # (16, n) XN2 residuals [rpm]
    norms: np.ndarray  # (16, n) residual norms the supervisor compares
    min_index: np.ndarray  # (n,) I*(k), bank position
    fault_index: np.ndarray  # (n,) F*(k), bank position
    online: list  # (n,) tuple of model ids on line
    history: list
    model_ids: tuple

    def summary(self) -> dict:
        """Detection / isolation times per fault event and whether F* was ever wrong."""
        sc = self.scenario
        events = []
        wrong = False
        for k, t in enumerate(self.t):
            # F* is wrong when it names a situation that never was true up to now (F* may lag:
            # nominal or the previous situation until the new one is isolated)
            seen = {"nominal"} | {sc.true_model(float(te)) for te, _ in sc.events
                                  if te <= t + 1e-9}
            if self.model_ids[self.fault_index[k]] not in seen:
                wrong = True
                break
        onsets = [float(te) for te, _ in sc.events]
        for i, te in enumerate(onsets):
            t_next = onsets[i + 1] if i + 1 < len(onsets) else math.inf
            truth = sc.true_model(te)
            window = [(t, kind, m) for t, kind, m in self.history if te - 1e-9 <= t < t_next]
            det = next((t for t, kind, _ in window if kind == "detected"), math.nan)
            isos = [(t, m) for t, kind, m in window if kind == "isolated"]
            hit = next((t for t, m in isos if m == truth), math.nan)
            events.append({"fault_at_s": te, "true_situation": truth,
                           "detected_s": _r(det), "isolated_s": _r(hit),
                           "isolation_delay_s": _r(hit - te),
                           "isolated_model": isos[-1][1] if isos else "",
                           "wrong_isolations": [m for _, m in isos if m != truth],
                           "correct": bool(isos) and isos[-1][1] == truth})
        false_iso = [m for t, kind, m in self.history
                     if kind == "isolated" and m != sc.true_model(t)]
        return {"case": sc.name, "events": events, "fault_index_ever_wrong": wrong,
                "false_isolations": false_iso,
                "final_fault_model": self.model_ids[self.fault_index[-1]],
                "max_nominal_residual_fault_free_rpm": _r(self._max_fault_free_nominal()),
                "paper": sc.paper}

    def _max_fault_free_nominal(self) -> float:
        mask = np.array([self.scenario.true_model(float(t)) == "nominal" for t in self.t])
        mask &= self.t >= 2.0  # after the start transient of the open-loop models
        return float(self.norms[0, mask].max()) if mask.any() else math.nan


def _r(v: float) -> float | None:
    return None if not math.isfinite(v) else round(float(v), 2)


def simulate_plant(scenario: Scenario, *, plant: tfp.Turbofan | None = None) -> dict:
    """Run the plant through a scenario (paper input profile, seeded sensor noise)."""
    plant = plant or tfp.Turbofan()
    c = np.asarray(scenario.condition, dtype=float)
    ts = plant.k.Ts
    wf = tfp.paper_input(plant.scheduled_fuel(c), duration_s=scenario.duration_s, ts=ts)
    p = scenario.quality_profile(wf.size, ts)
    return plant.simulate(wf, c, p, rng=np.random.default_rng(scenario.seed))


def run_scenario(gm: GlobalModel, scenario: Scenario, *, t0_s: float,
                 plant: tfp.Turbofan | None = None, bank: Sequence[BankModel] = PAPER_BANK,
                 feed_measured: bool = False, sim: dict | None = None,
                 xnh_weight: float = 0.0) -> ScenarioResult:
    """Plant + all bank models (open loop from the measured initial state) + supervisor.

    ``xnh_weight`` > 0 adds the core-speed residual to the norm (:func:`residual_norm`).
    """
    sim = sim or simulate_plant(scenario, plant=plant)
    ids = tuple(m.id for m in bank)
    mix = bank_mixture(gm, ids, condition=scenario.condition,
                       deterioration=scenario.deterioration)
    y = sim["y"]
    pred = mix.simulate(sim["wf"], y[0], measured=y if feed_measured else None)
    res = y[None, :, 0] - pred[:, :, 0]
    norm = residual_norm(res, y[None, :, 1] - pred[:, :, 1], xnh_weight)
    sup = ExpertSupervisor(bank=bank, t0_s=t0_s)
    n = y.shape[0]
    min_idx = np.empty(n, dtype=int)
    f_idx = np.empty(n, dtype=int)
    online = []
    for k in range(n):
        d = sup.update(float(sim["t"][k]), {mid: float(norm[i, k]) for i, mid in enumerate(ids)})
        min_idx[k], f_idx[k] = d.min_residual_index, d.fault_index
        online.append(d.models_online)
    return ScenarioResult(scenario=scenario, t=sim["t"], y=y, wf=sim["wf"], yhat=pred[:, :, 0],
                          residuals=res, norms=norm, min_index=min_idx, fault_index=f_idx,
                          online=online,
                          history=list(sup.history), model_ids=ids)


def fault_free_batch(gm: GlobalModel, *, n_runs: int, seed: int, condition=tfp.PAPER_CONDITION,
                     deterioration_range: tuple[float, float] = (0.0, 0.3),
                     manufacturing_sigma: float = 0.15e-2,
                     duration_s: float = 20.0, plant: tfp.Turbofan | None = None,
                     bank: Sequence[BankModel] = PAPER_BANK, xnh_weight: float = 0.0) -> dict:
    """Fault-free runs with random manufacturing variation and deterioration (seeded).

    Returns the residual norms of the initially on-line models (nominal + single faults) per
    run, ``res`` (runs, models, n), and the model ids. Manufacturing variation ~ N(0, sigma) per
    quality parameter, clipped at +-2 sigma; deterioration ~ U(range), known to the bank.
    """
    from fdi_ros.core.supervisor import models_online

    plant = plant or tfp.Turbofan()
    rng = np.random.default_rng(seed)
    c = np.asarray(condition, dtype=float)
    ts = plant.k.Ts
    wf = tfp.paper_input(plant.scheduled_fuel(c), duration_s=duration_s, ts=ts)
    man = np.clip(rng.normal(0.0, manufacturing_sigma, (n_runs, 10)),
                  -2 * manufacturing_sigma, 2 * manufacturing_sigma)
    det = rng.uniform(*deterioration_range, n_runs)
    p = man + det[:, None] * tfp.DETERIORATION_FULL
    sim = plant.simulate(np.broadcast_to(wf, (n_runs, wf.size)), np.broadcast_to(c, (n_runs, 4)),
                         p, rng=rng)
    ids = models_online(bank, [])
    res = np.empty((n_runs, len(ids), wf.size))
    for r in range(n_runs):
        mix = bank_mixture(gm, ids, condition=c, deterioration=float(det[r]))
        pred = mix.simulate(wf, sim["y"][r, 0])
        yr = sim["y"][r, None]
        res[r] = residual_norm(yr[..., 0] - pred[..., 0], yr[..., 1] - pred[..., 1], xnh_weight)
    return {"res": res, "ids": ids, "t": sim["t"], "deterioration": det,
            "manufacturing": man}


def longest_wrong_hold(res: np.ndarray, *, ts: float, nominal: int = 0) -> np.ndarray:
    """Per run, the longest time [s] one non-nominal model held the minimum |residual|.

    With the fixed fault-free bank this decides false isolation exactly as the supervisor
    does: a run is falsely isolated at hold time T0 iff ``longest >= T0``.
    """
    idx = np.argmin(res, axis=1)  # (runs, n); res holds norms (>= 0)
    out = np.zeros(idx.shape[0])
    for r, seq in enumerate(idx):
        change = np.flatnonzero(np.diff(seq)) + 1
        starts = np.concatenate([[0], change])
        ends = np.concatenate([change, [seq.size]])
        for s, e in zip(starts, ends):
            if seq[s] != nominal:
                out[r] = max(out[r], (e - 1 - s) * ts)
    return out
