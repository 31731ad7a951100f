"""Node models on a grid of (operating condition, quality parameters) and the global model.

Node model (paper eq. 12): at node j = (c_j, p_j)::

    XNLdot = F1_j(XNL, XNH, WF36),   XNHdot = F2_j(XNL, XNH, WF36)

each F a Takagi-Sugeno system (R rules, Gaussian premise on XNL, affine consequents) fitted by
Levenberg-Marquardt (:func:`~fdi_ros.core.tsfuzzy.fit_ts`) to 20 s of transient data
(1000 samples at Ts = 0.02 s) of the plant at that node. The training target is the one-step
difference ``(x(k+1) - x(k)) / Ts`` of the noise-free states, so that the Euler-integrated model
reproduces the sampled plant.

Global model (paper eq. 14): Gaussian memberships over the node coordinates
v = (ALT, XM, DTAMB, PC, d, fan size, hub size)::

    F(x, u; c, p) = sum_j mu_j(v) F_j(x, u) / sum_j mu_j(v),
    mu_j(v) = prod_i exp(-1/2 ((v_i - v_ij) / sigma_i)^2)

with sigma_ij = ``width`` * (local grid spacing of dimension i at node j). Normalised Gaussian
interpolation leaks a little of the neighbouring nodes into a node (a bias at the edges of the
grid, and towards the wider side where spacings change), so widths are kept at 0.3 spacings
(leak exp(-1/(2 0.3^2)) = 0.4 %) and grids are nearly uniform. Fault sizes are in units of
the small fault (bank models sit on those nodes, so a narrow width keeps them unblended);
deterioration and the operating condition vary continuously between nodes. The paper fits the
memberships by LM as well: :func:`fit_widths` does (``fdi-ros train turbofan --fit-widths``);
on our grid it lowers the off-node derivative error (RMS 42 -> 31 rpm/s) but blurs the bank
models on their own nodes, so the default keeps the grid widths.

Simulation (paper: open loop, Euler at Ts)::

    xhat(k+1) = xhat(k) + Ts F(xhat(k), WF36(k))

``measured=`` replaces xhat(k) by the measured states before each step (one-step prediction).
"""

from __future__ import annotations

import itertools
import json
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from fdi_ros.core.parallel import map_processes
from fdi_ros.core.tsfuzzy import StackedTS, TSFitResult, fit_ts
from fdi_ros.plants.turbofan import plant as tfp

DIMS = ("ALT", "XM", "DTAMB", "PC", "deterioration", "fan", "hub")
#: fixed input normalisation of every node model: (XNL [rpm], XNH [rpm], WF36 [kg/s])
NORM_OFFSET = np.array([10700.0, 14150.0, 0.195])
NORM_SCALE = np.array([300.0, 400.0, 0.02])


@dataclass(frozen=True)
class GridSpec:
    """Node grid and interpolation widths (relative to the smallest spacing per dimension).

    ``region``: per operating-condition dimension, the (lo, hi) where the global model is
    valid (outside: residuals flagged invalid). Dimensions with one node need a region.
    """

    ALT: tuple[float, ...] = (12500.0, 15000.0, 17500.0)
    XM: tuple[float, ...] = (0.6, 0.7, 0.8)
    DTAMB: tuple[float, ...] = (0.0,)
    PC: tuple[float, ...] = (46.0,)
    deterioration: tuple[float, ...] = (0.0, 0.1, 0.2, 0.3, 0.4, 0.55, 0.7, 0.85, 1.0)
    fan: tuple[float, ...] = (0.0, 1.0, 2.0, 3.0)
    hub: tuple[float, ...] = (0.0, 1.0, 2.5, 4.0)
    width_condition: float = 0.3
    width_deterioration: float = 0.3
    width_fault: float = 0.3
    region: dict = field(default_factory=lambda: {
        "ALT": (12500.0, 17500.0), "XM": (0.6, 0.8), "DTAMB": (-5.0, 5.0), "PC": (45.5, 46.5)})

    def __post_init__(self) -> None:
        for name in DIMS:
            vals = tuple(float(v) for v in getattr(self, name))
            if not vals or any(np.diff(vals) <= 0):
                raise ValueError(f"grid {name} must be a non-empty increasing list")
            object.__setattr__(self, name, vals)
        for name in DIMS[:4]:
            lo, hi = self.region[name]
            if not lo <= min(getattr(self, name)) <= max(getattr(self, name)) <= hi:
                raise ValueError(f"region of {name} must contain its grid")
        if min(self.width_condition, self.width_deterioration, self.width_fault) <= 0:
            raise ValueError("interpolation widths must be > 0")

    def axes(self) -> list[tuple[float, ...]]:
        return [getattr(self, name) for name in DIMS]

    def nodes(self) -> np.ndarray:
        """(N, 7) node coordinates, C order over DIMS."""
        return np.array(list(itertools.product(*self.axes())), dtype=float)

    def widths(self) -> tuple[float, float, float]:
        return (self.width_condition, self.width_deterioration, self.width_fault)

    def sigmas(self, widths: tuple[float, ...] | None = None) -> np.ndarray:
        """(N, 7) membership widths per node: ``width`` * local grid spacing (shortest distance
        to the neighbouring grid values of that dimension; 1 for single-value dimensions).
        ``widths`` (condition, deterioration, fault) overrides the grid's."""
        wc, wd, wf = self.widths() if widths is None else widths
        per_axis = []
        for i, vals in enumerate(self.axes()):
            width = wc if i < 4 else wd if i == 4 else wf
            v = np.asarray(vals)
            if v.size == 1:
                per_axis.append(np.ones(1))
                continue
            gaps = np.diff(v)
            left = np.concatenate([[np.nan], gaps])
            right = np.concatenate([gaps, [np.nan]])
            per_axis.append(width * np.nanmin(np.stack([left, right]), axis=0))
        return np.array(list(itertools.product(*per_axis)), dtype=float)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> GridSpec:
        kw: dict[str, Any] = dict(d or {})
        unknown = set(kw) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown grid key(s): {sorted(unknown)}")
        if "region" in kw:
            kw["region"] = {k: tuple(v) for k, v in kw["region"].items()}
        args: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in kw.items()}
        return cls(**args)


def node_quality(node: np.ndarray) -> np.ndarray:
    """(..., 10) quality deviations of node coordinates (..., 7) (no manufacturing variation)."""
    node = np.asarray(node, dtype=float)
    return (node[..., 4, None] * tfp.DETERIORATION_FULL
            + node[..., 5, None] * tfp.fault_vector("fan")
            + node[..., 6, None] * tfp.fault_vector("hub"))


@dataclass(frozen=True)
class TrainingReport:
    """Training figures: node count, TS fits, wall time [s] (simulation part separately), worst
    RMSE of the node fits [rpm/s], mean LM evaluations, and ``n_not_converged``: fits that
    stopped at ``max_nfev`` before scipy's tolerances were met (their RMSE is still the one
    reported; LM starts from the least-squares consequents, so most of the gain is early)."""

    n_nodes: int
    n_fits: int
    seconds: float
    simulate_seconds: float
    rmse_xnldot_max: float
    rmse_xnhdot_max: float
    nfev_mean: float
    n_not_converged: int

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass(frozen=True)
class GlobalModel:
    """Node models + Gaussian interpolation over (c, p)."""

    grid: GridSpec
    nodes: np.ndarray  # (N, 7)
    f1: StackedTS  # leading axis N
    f2: StackedTS
    xnl_range: tuple[float, float]  # premise range seen in training [rpm]
    report: TrainingReport | None = None
    signature: str = ""  # plant_signature() of the plant that generated the training data
    widths: tuple[float, ...] = ()  # fitted (condition, deterioration, fault) widths; () = grid's
    _sigmas: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.widths and (len(self.widths) != 3 or min(self.widths) <= 0):
            raise ValueError("widths must be three positive numbers")
        object.__setattr__(self, "_sigmas", self.grid.sigmas(tuple(self.widths) or None))

    def same_structure(self, grid: GridSpec) -> bool:
        """True if ``grid`` has this model's nodes and region (widths may differ)."""
        return replace(grid, width_condition=self.grid.width_condition,
                       width_deterioration=self.grid.width_deterioration,
                       width_fault=self.grid.width_fault) == self.grid

    # -- interpolation --------------------------------------------------------------------------
    def coordinates(self, condition, deterioration: float, fan: float, hub: float) -> np.ndarray:
        c = np.asarray(condition, dtype=float)
        return np.array([c[0], c[1], c[2], c[3], deterioration, fan, hub], dtype=float)

    def in_region(self, v: np.ndarray) -> tuple[bool, str]:
        for i, name in enumerate(DIMS[:4]):
            lo, hi = self.grid.region[name]
            if not lo - 1e-9 <= v[i] <= hi + 1e-9:
                return False, f"{name}={v[i]:g} outside the model region [{lo:g}, {hi:g}]"
        for i, name in enumerate(DIMS[4:], start=4):
            vals = getattr(self.grid, name)
            if not vals[0] - 1e-9 <= v[i] <= vals[-1] + 1e-9:
                return False, f"{name}={v[i]:g} outside the model grid [{vals[0]}, {vals[-1]}]"
        return True, ""

    def weights(self, v: np.ndarray) -> np.ndarray:
        """(N,) normalised memberships mu_j(v) / sum mu."""
        d = (self.nodes - np.asarray(v, dtype=float)) / self._sigmas
        logm = -0.5 * np.sum(d * d, axis=1)
        m = np.exp(logm - logm.max())
        return m / m.sum()

    def mixture(self, vs: np.ndarray, *, tol: float = 1e-4) -> Mixture:
        """The interpolated dynamics at coordinates ``vs`` (B, 7): one row per model."""
        vs = np.atleast_2d(np.asarray(vs, dtype=float))
        for v in vs:
            ok, why = self.in_region(v)
            if not ok:
                raise ValueError(why)
        ws = np.array([self.weights(v) for v in vs])
        ws[ws < tol] = 0.0
        ws /= ws.sum(axis=1, keepdims=True)
        k = int((ws > 0).sum(axis=1).max())
        idx = np.argsort(-ws, axis=1)[:, :k]
        w = np.take_along_axis(ws, idx, axis=1)
        return Mixture(weights=w, f1=self.f1.take(idx), f2=self.f2.take(idx),
                       xnl_range=self.xnl_range)

    # -- persistence ----------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        meta: dict[str, Any] = {"grid": {k: (list(v) if isinstance(v, tuple) else v)
                         for k, v in self.grid.__dict__.items()},
                "xnl_range": list(self.xnl_range), "premise": self.f1.premise,
                "signature": self.signature, "widths": list(self.widths),
                "report": self.report.as_dict() if self.report else None}
        meta["grid"]["region"] = {k: list(v) for k, v in self.grid.region.items()}
        np.savez_compressed(path, nodes=self.nodes, offset=self.f1.offset, scale=self.f1.scale,
                            f1_c=self.f1.centers, f1_s=self.f1.sigmas, f1_a=self.f1.coef,
                            f2_c=self.f2.centers, f2_s=self.f2.sigmas, f2_a=self.f2.coef,
                            meta=np.array(json.dumps(meta)))
        return path

    @classmethod
    def load(cls, path: str | Path) -> GlobalModel:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no turbofan model file {path} (run `fdi-ros train "
                                    "turbofan` first)")
        try:
            z = np.load(path, allow_pickle=False)
            meta = json.loads(str(z["meta"]))
            grid = GridSpec.from_dict(meta["grid"])

            def stacked(tag):
                return StackedTS(centers=z[f"{tag}_c"], sigmas=z[f"{tag}_s"],
                                 coef=z[f"{tag}_a"], offset=z["offset"], scale=z["scale"],
                                 premise=int(meta["premise"]))

            rep = TrainingReport(**meta["report"]) if meta.get("report") else None
            model = cls(grid=grid, nodes=z["nodes"], f1=stacked("f1"), f2=stacked("f2"),
                        xnl_range=tuple(meta["xnl_range"]), report=rep,
                        signature=str(meta.get("signature", "")),
                        widths=tuple(meta.get("widths", ())))
        except (KeyError, ValueError, TypeError, OSError) as exc:
            raise ValueError(f"{path}: not a turbofan global model file ({exc})") from exc
        if model.nodes.shape != (model.f1.centers.shape[0], 7):
            raise ValueError(f"{path}: inconsistent node arrays")
        return model


@dataclass(frozen=True)
class Mixture:
    """Interpolated dynamics of B models: ``weights`` (B, K), node models ``f1, f2`` (B, K)."""

    weights: np.ndarray
    f1: StackedTS
    f2: StackedTS
    xnl_range: tuple[float, float]

    @property
    def n_models(self) -> int:
        return int(self.weights.shape[0])

    def take(self, rows) -> Mixture:
        return Mixture(weights=self.weights[rows], f1=self.f1.take(rows),
                       f2=self.f2.take(rows), xnl_range=self.xnl_range)

    def derivatives(self, x: np.ndarray, u) -> np.ndarray:
        """(B, 2) state derivatives [rpm/s] for states x (B, 2) and fuel u (B,) or scalar."""
        x = np.asarray(x, dtype=float)
        u = np.broadcast_to(np.asarray(u, dtype=float), x.shape[:-1])
        inp = np.concatenate([x, u[..., None]], axis=-1)[:, None, :]  # (B, 1, 3)
        d1 = np.sum(self.weights * self.f1(inp), axis=1)
        d2 = np.sum(self.weights * self.f2(inp), axis=1)
        return np.stack([d1, d2], axis=-1)

    def equilibrium(self, u, x0=None) -> np.ndarray:
        """(B, 2) model states with zero derivative at constant fuel ``u``."""
        start = np.array([10700.0, 14150.0]) if x0 is None else x0
        x0 = np.broadcast_to(start, (self.n_models, 2))
        return tfp.newton_equilibrium(lambda x: self.derivatives(x, u), x0)

    def simulate(self, u: np.ndarray, x0: np.ndarray, *, ts: float = 0.02,
                 measured: np.ndarray | None = None) -> np.ndarray:
        """Euler simulation: (B, n, 2) predicted states, row k = xhat(k) (before input u(k)).

        ``x0`` (2,) or (B, 2); ``measured`` (n, 2) switches to one-step prediction.
        """
        u = np.asarray(u, dtype=float)
        x = np.broadcast_to(np.asarray(x0, dtype=float), (self.n_models, 2)).copy()
        out = np.empty((self.n_models, u.shape[0], 2))
        for k in range(u.shape[0]):
            if measured is not None:
                x = np.broadcast_to(measured[k], x.shape).copy()
            out[:, k] = x
            x = x + ts * self.derivatives(x, u[k])
        return out


def _fit_node(job: tuple[np.ndarray, np.ndarray, int, int]) -> TSFitResult:
    """One node's TS system for one output (a worker process)."""
    x, y, n_rules, max_nfev = job
    return fit_ts(x, y, n_rules=n_rules, premise=0, offset=NORM_OFFSET, scale=NORM_SCALE,
                  max_nfev=max_nfev)


def train_global(grid: GridSpec, *, n_rules: int = 3, seed: int = 0, duration_s: float = 20.0,
                 max_nfev: int = 40, plant: tfp.Turbofan | None = None,
                 progress: bool = True) -> GlobalModel:
    """Simulate every node of the grid on a random transient and fit its two TS systems.

    Data per node: ``duration_s`` of :func:`~fdi_ros.plants.turbofan.plant.training_input`
    around the node's scheduled fuel, noise-free (the paper trains on CLM data).
    """
    from tqdm import tqdm

    plant = plant or tfp.Turbofan()
    nodes = grid.nodes()
    n = nodes.shape[0]
    ts = plant.k.Ts
    steps = int(round(duration_s / ts))
    t0 = time.perf_counter()
    sched = {}
    for cond in {tuple(v[:4]) for v in nodes}:
        sched[cond] = plant.scheduled_fuel(np.array(cond))
    wf = np.empty((n, steps + 1))
    for j, v in enumerate(nodes):
        rng = np.random.default_rng([seed, j])
        wf[j] = tfp.training_input(sched[tuple(v[:4])], rng, duration_s=(steps + 1) * ts)
    sim = plant.simulate(wf, nodes[:, :4], node_quality(nodes), noise=False)
    t_sim = time.perf_counter() - t0
    x = sim["x"]
    inputs = np.concatenate([x[:, :-1], wf[:, :-1, None]], axis=-1)  # (N, steps, 3)
    target = np.diff(x, axis=1) / ts
    # the 2 N fits are independent: on every core (results equal the serial run's)
    jobs = [(inputs[j], target[j, :, out], n_rules, max_nfev) for j in range(n)
            for out in (0, 1)]
    with tqdm(total=len(jobs), desc="training TS node models", unit="fit",
              disable=not progress) as bar:
        fits = map_processes(_fit_node, jobs, progress=lambda k, _: bar.update(k - bar.n))
    fits1, fits2 = fits[0::2], fits[1::2]
    seconds = time.perf_counter() - t0
    allfits = fits1 + fits2
    report = TrainingReport(
        n_nodes=n, n_fits=len(allfits), seconds=round(seconds, 2),
        simulate_seconds=round(t_sim, 2),
        rmse_xnldot_max=float(max(f.rmse for f in fits1)),
        rmse_xnhdot_max=float(max(f.rmse for f in fits2)),
        nfev_mean=float(np.mean([f.nfev for f in allfits])),
        n_not_converged=int(sum(f.nfev >= max_nfev and not f.success for f in allfits)))
    xnl = inputs[..., 0]
    return GlobalModel(grid=grid, nodes=nodes,
                       f1=StackedTS.stack([f.model for f in fits1]),
                       f2=StackedTS.stack([f.model for f in fits2]),
                       xnl_range=(float(xnl.min()), float(xnl.max())), report=report,
                       signature=tfp.plant_signature(plant.k))


@dataclass(frozen=True)
class WidthFitResult:
    """Result of :func:`fit_widths` (like scipy's OptimizeResult)."""

    x: tuple  # fitted (condition, deterioration, fault) widths, in grid spacings
    x0: tuple
    success: bool
    message: str
    nfev: int
    rms_before: float  # RMS derivative error on the validation data [rpm/s], XNLdot
    rms_after: float
    n_points: int

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def fit_widths(gm: GlobalModel, *, plant: tfp.Turbofan | None = None, n_random: int = 24,
               seed: int = 1, duration_s: float = 4.0,
               extra_points: np.ndarray | None = None) -> tuple[GlobalModel, WidthFitResult]:
    """Identify the interpolation widths by Levenberg-Marquardt (paper: the m_i(c, p) of the
    global model are LM-fitted too).

    Validation data: ``n_random`` points drawn uniformly in the model region (operating
    condition, deterioration and both fault sizes off the nodes) plus ``extra_points`` (e.g.
    the bank's own situations, on fault nodes), each simulated noise-free for ``duration_s``
    on a fresh random transient. Residuals: global-model derivative minus the one-step plant
    derivative, XNLdot and XNHdot / 3, over all samples. Three parameters (log widths); the
    Jacobian is a finite difference (cheap: node outputs on the validation data are computed
    once and reweighted).
    """
    plant = plant or tfp.Turbofan()
    rng = np.random.default_rng(seed)
    lo_hi = [gm.grid.region[name] for name in DIMS[:4]]
    axes = gm.grid.axes()
    pts = []
    for _ in range(n_random):
        v = [rng.uniform(lo, hi) for lo, hi in lo_hi]
        v += [rng.uniform(axes[i][0], axes[i][-1]) for i in (4, 5, 6)]
        pts.append(v)
    if extra_points is not None:
        pts += [list(p) for p in np.atleast_2d(extra_points)]
    pts_arr = np.array(pts, dtype=float)
    ts = plant.k.Ts
    steps = int(round(duration_s / ts))
    wf = np.array([tfp.training_input(plant.scheduled_fuel(v[:4]), rng,
                                      duration_s=(steps + 1) * ts) for v in pts_arr])
    sim = plant.simulate(wf, pts_arr[:, :4], node_quality(pts_arr), noise=False)
    x = sim["x"]
    inputs = np.concatenate([x[:, :-1], wf[:, :-1, None]], axis=-1)  # (P, n, 3)
    target = np.diff(x, axis=1) / ts  # (P, n, 2)
    outs = np.stack([np.stack([gm.f1(inp[:, None, :]), gm.f2(inp[:, None, :])], axis=-1)
                     for inp in inputs])  # (P, n, N, 2)
    scale = np.array([1.0, 1.0 / 3.0])

    def residual(logw):
        sig = gm.grid.sigmas(tuple(np.exp(logw)))
        d = (gm.nodes[None, :, :] - pts_arr[:, None, :]) / sig[None]
        logm = -0.5 * np.sum(d * d, axis=2)
        m = np.exp(logm - logm.max(axis=1, keepdims=True))
        m /= m.sum(axis=1, keepdims=True)  # (P, N)
        pred = np.einsum("pn,psnk->psk", m, outs)
        return ((pred - target) * scale).ravel()

    from scipy.optimize import least_squares

    x0 = np.log(np.array(gm.grid.widths()))
    r0 = residual(x0)
    sol = least_squares(residual, x0, method="lm", diff_step=1e-3, max_nfev=200)
    widths = tuple(float(w) for w in np.exp(sol.x))
    n = target.shape[0] * target.shape[1]

    def rms(r):
        return float(np.sqrt(np.mean(r.reshape(n, 2)[:, 0] ** 2)))

    result = WidthFitResult(x=widths, x0=tuple(np.exp(x0)), success=bool(sol.success),
                            message=sol.message, nfev=int(sol.nfev), rms_before=rms(r0),
                            rms_after=rms(sol.fun), n_points=len(pts_arr))
    return replace(gm, widths=widths), result
