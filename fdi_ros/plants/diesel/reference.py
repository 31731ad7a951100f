"""The five static reference models of the diesel intake system (Schwarte & Isermann 2002).

Each model maps the operating point (engine speed ``n`` [rpm], boost density ``rho2``
[kg/m^3]) to one characteristic value of a 180 deg CA segment (paper eqs. 3, 5, 6, 8, 9):

=============  ==============================================  ==========
output         meaning                                         unit
=============  ==============================================  ==========
``eta_v``      volumetric efficiency m_air / m_th              1
``maf_amp``    first-harmonic amplitude of the MAF signal      kg/h
``maf_phase``  phase of that harmonic                          deg CA
``p2_amp``     first-harmonic amplitude of the boost pressure  Pa
``p2_phase``   phase of that harmonic                          deg CA
=============  ==============================================  ==========

They are identified with LOLIMOT from fault-free identification-cycle features and then sampled
into ECU look-up tables (:mod:`fdi_ros.core.lut`) on a user grid. When the identification data
span the commanded actuators (EGR valve ``egr_cmd``, swirl flaps ``swirl_cmd``), these are model
inputs as well (N-D maps and tables); whatever the data held fixed bounds the models' validity
region instead (:class:`~fdi_ros.core.validity.ValidityRegion`, stored in the manifest and
checked per segment: a model identified with the EGR valve closed is "not valid here" with it
open). Phases are periodic (one
period is 180 deg CA); they are fitted on a branch of width 180 deg CA centred on the data's
circular mean, and residuals are wrapped to +-90 deg CA.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fdi_ros.core.lolimot import Lolimot, LolimotResult
from fdi_ros.core.lut import LookupTable, table_error
from fdi_ros.core.types import FeatureVector
from fdi_ros.core.validity import ValidityRegion

__all__ = ["ACTUATORS", "INPUTS", "OUTPUTS", "UNITS", "IdentificationConfig",
           "IdentificationResult", "ReferenceModelSet", "actuator_breakpoints", "feature_table",
           "identify_reference_models", "nrmse", "split_blocks", "wrap_phase"]

INPUTS = ("n", "rho2")
# Commanded actuators: model inputs when the identification spans them, else validity bounds.
ACTUATORS = ("egr_cmd", "swirl_cmd")
# Accepted deviation of an actuator command from the value the identification held [1]. An
# EGR valve commanded 2 % open passes as much exhaust gas as a 3.5 mm leak past a closed one
# (a fault the models detect), so its tolerance is 0.2 % (about a 1 mm hole).
ACTUATOR_TOL = {"egr_cmd": 0.002, "swirl_cmd": 0.02}
OUTPUTS = ("eta_v", "maf_amp", "maf_phase", "p2_amp", "p2_phase")
UNITS = {"n": "rpm", "rho2": "kg/m^3", "egr_cmd": "1", "swirl_cmd": "1", "eta_v": "1",
         "maf_amp": "kg/h", "maf_phase": "deg CA", "p2_amp": "Pa", "p2_phase": "deg CA"}
PHASES = ("maf_phase", "p2_phase")
AMPLITUDE_OF = {"maf_phase": "maf_amp", "p2_phase": "p2_amp"}
PERIOD_DEG = 180.0
MANIFEST = "reference_models.json"


def wrap_phase(x, centre=0.0):
    """Wrap phases [deg CA] to ``(centre - 90, centre + 90]`` (period 180 deg CA)."""
    x = np.asarray(x, dtype=float)
    return centre - ((centre - x + 0.5 * PERIOD_DEG) % PERIOD_DEG) + 0.5 * PERIOD_DEG


def circular_mean(x) -> float:
    """Circular mean of phases [deg CA] with period 180 deg CA."""
    a = 2.0 * np.pi * np.asarray(x, dtype=float) / PERIOD_DEG
    return float(np.angle(np.mean(np.exp(1j * a))) * PERIOD_DEG / (2.0 * np.pi))


def branch_centre(x) -> float:
    """Centre of the 180 deg CA branch whose cut lies in the widest gap of the phases [deg CA]
    (a phase that drifts over most of a period must not be cut through its data)."""
    v = np.sort(np.mod(np.asarray(x, dtype=float), PERIOD_DEG))
    if v.size == 0:
        return 0.0
    gaps = np.diff(np.concatenate([v, [v[0] + PERIOD_DEG]]))
    i = int(np.argmax(gaps))
    cut = v[i] + 0.5 * gaps[i]
    return float(wrap_phase(cut + 0.5 * PERIOD_DEG, 0.0))


def nrmse(y, yhat) -> float:
    """Root-mean-square error divided by the standard deviation of y (0: perfect, 1: mean)."""
    y = np.asarray(y, dtype=float)
    e = y - np.asarray(yhat, dtype=float)
    sd = float(np.std(y))
    return float(np.sqrt(np.mean(e ** 2)) / sd) if sd > 0 else float("nan")


def feature_table(features: Iterable[FeatureVector],
                  names: tuple[str, ...] = INPUTS + OUTPUTS) -> dict[str, np.ndarray]:
    """Stack feature vectors into arrays per name; invalid or non-finite segments dropped.

    Also returns ``t`` (segment end time [s]) and ``index``.
    """
    rows, t, idx = [], [], []
    for fv in features:
        if not fv.valid:
            continue
        try:
            row = [fv.get(k) for k in names]
        except KeyError as exc:
            raise ValueError(f"feature vectors lack a reference-model signal: {exc}") from None
        if np.all(np.isfinite(row)):
            rows.append(row)
            t.append(fv.t_end)
            idx.append(fv.index)
    if not rows:
        raise ValueError("no valid feature vectors with finite values")
    arr = np.asarray(rows, dtype=float)
    out = {k: arr[:, j] for j, k in enumerate(names)}
    out["t"] = np.asarray(t)
    out["index"] = np.asarray(idx)
    return out


def split_blocks(n_samples: int, *, block: int = 200, n_folds: int = 5, seed: int = 0):
    """Contiguous-block split into train / validation / test index arrays (60/20/20 %).

    Neighbouring segments are strongly correlated; whole blocks keep the held-out data honest.
    """
    n_blocks = max(1, int(np.ceil(n_samples / block)))
    rng = np.random.default_rng(seed)
    fold = np.resize(rng.permutation(n_folds), n_blocks)
    rng.shuffle(fold)
    per = np.repeat(fold, block)[:n_samples]
    return (np.flatnonzero(per >= 2), np.flatnonzero(per == 1), np.flatnonzero(per == 0))


@dataclass(frozen=True)
class IdentificationConfig:
    """Settings of the identification of the five models.

    lut_n, lut_rho2 : ECU table breakpoints [rpm], [kg/m^3]; empty -> a 17 x 13 grid over the
        identified range.
    actuator_inputs : the commanded actuators that the data span become model inputs (those
        held fixed only bound the validity region); False: (n, rho2) only, as in the paper.
    lut_actuator : breakpoints per actuator input (a command has few distinct settings: its
        distinct values when there are at most this many, else this many equidistant ones).
    extra_inputs : further measured features that every model takes as inputs (e.g. the
        injected fuel and the VGT command where the EGR valve is open: the recirculated gas
        follows the exhaust back pressure); their identified ranges bound the validity too.
    tables : sample the models into ECU look-up tables (False: the models are evaluated
        directly, for maps of more inputs than a table holds).
    """

    max_models: int = 20
    k_sigma: float = 0.35
    ridge: float = 1e-6
    min_samples_per_model: int = 40
    patience: int = 4
    coverage_bins: int = 16
    coverage_min_count: int = 3
    compress_bins: int = 64
    block: int = 200
    seed: int = 0
    lut_n: tuple[float, ...] = ()
    lut_rho2: tuple[float, ...] = ()
    storage_correction: bool = True
    rate_lag: int = 2
    phase_min_amp_frac: float = 0.1
    actuator_inputs: bool = True
    lut_actuator: int = 6
    extra_inputs: tuple[str, ...] = ()
    tables: bool = True
    coverage_inputs: int = 0

    def __post_init__(self) -> None:
        if self.block < 1:
            raise ValueError("block must be >= 1")
        for name in ("lut_n", "lut_rho2"):
            bp = np.asarray(getattr(self, name), dtype=float)
            if bp.size and (bp.size < 2 or np.any(np.diff(bp) <= 0)):
                raise ValueError(f"{name} must be strictly increasing with >= 2 entries")

    def lolimot(self) -> Lolimot:
        return Lolimot(max_models=self.max_models, k_sigma=self.k_sigma, ridge=self.ridge,
                       min_samples_per_model=self.min_samples_per_model,
                       patience=self.patience, coverage_bins=self.coverage_bins,
                       coverage_min_count=self.coverage_min_count,
                       compress_bins=self.compress_bins,
                       coverage_inputs=self.coverage_inputs)


_LOADED: dict[tuple[str, int], ReferenceModelSet] = {}  # see ReferenceModelSet.load


@dataclass
class ReferenceModelSet:
    """The five LOLIMOT models, their look-up tables and the phase branch centres.

    ``inputs`` are the models' inputs (``n, rho2`` and the actuator commands the identification
    spanned); ``validity`` the per-input region of the identification data (incl. the actuator
    commands it held fixed). ``predict`` evaluates the tables (as the ECU does) or the LOLIMOT
    models themselves.
    """

    models: dict[str, Lolimot]
    tables: dict[str, LookupTable]
    phase_centre: dict[str, float] = field(default_factory=dict)
    info: dict = field(default_factory=dict)
    inputs: tuple[str, ...] = INPUTS
    validity: ValidityRegion | None = None
    #: further operating regimes, each a model set of its own (e.g. the EGR valve open), tried
    #: in order after this one (see :meth:`assign`); saved under ``regimes/<name>/``
    regimes: list[ReferenceModelSet] = field(default_factory=list)

    @property
    def regime(self) -> str:
        """This set's operating regime ("" for a set identified as one regime)."""
        return str(self.info.get("regime", ""))

    @property
    def t2_tau(self) -> float:
        """Time constant [s] of the T2 sensor's lag that the models undo (0: none)."""
        return float(self.info.get("t2_tau", 0.0))

    def regime_sets(self) -> list[ReferenceModelSet]:
        """This set and its further regimes, in the order they are tried."""
        return [self, *self.regimes]

    @property
    def vgt_tau(self) -> float:
        """Time constant [s] of the VGT vanes behind their command (0: not undone)."""
        return float(self.info.get("vgt_tau", 0.0))

    def compensate(self, data: Mapping[str, object]) -> dict[str, np.ndarray]:
        """The features with the T2 sensor's lag undone (``T2 + tau dT2/dt`` from the
        ``T2_rate`` feature; rho2 and eta_v follow, both ~ 1/T2): what the models were
        identified on; and, with a VGT time constant and the ``vgt_rate`` feature, ``vgt``
        the vanes' estimated position (``cmd - tau_vgt d(cmd)/dt`` within 0..1). Without
        time constants: the features as they are."""
        out = {k: np.atleast_1d(np.asarray(v, dtype=float)) for k, v in data.items()}
        if self.vgt_tau > 0 and "vgt" in out and "vgt_rate" in out:
            out["vgt"] = vgt_position(out["vgt"], out["vgt_rate"], self.vgt_tau)
        tau = self.t2_tau
        if tau <= 0.0:
            return out
        if "T2_rate" not in out or "T2" not in out:
            raise KeyError("T2_rate")
        T2 = out["T2"]
        T2c = T2 + tau * out["T2_rate"]
        ratio = T2c / T2
        out["T2"] = T2c
        out["rho2"] = out["rho2"] / ratio
        out["eta_v"] = out["eta_v"] * ratio
        return out

    def assign(self, data: Mapping[str, object], size: int) -> np.ndarray:
        """Per segment, the position in :meth:`regime_sets` of the first regime whose
        identified region (every input's range) holds it; -1 where none does."""
        out = np.full(size, -1, dtype=int)
        for j, ms in enumerate(self.regime_sets()):
            free = out < 0
            if not free.any():
                break
            inside = ms.validity.contains(data, size) if ms.validity is not None else \
                np.ones(size, dtype=bool)
            if ms.info.get(WHERE_COVERED) and (free & inside).any():
                # a regime tried only where its maps cover the segment (else the next one)
                rows = np.flatnonzero(free & inside)
                sub = {k: np.broadcast_to(np.atleast_1d(np.asarray(data[k], dtype=float)),
                                          (size,))[rows]
                       for k in ("n", "rho2", *ms.extra_inputs) if k in data}
                inside = inside.copy()
                inside[rows] = ms.predict(sub["n"], sub["rho2"], phases=False, extra={
                    k: sub[k] for k in ms.extra_inputs if k in sub})[1]
            out[free & inside] = j
        return out

    @property
    def outputs(self) -> tuple[str, ...]:
        return tuple(k for k in OUTPUTS if k in self.models or f"{k}_cos" in self.models)

    @property
    def extra_inputs(self) -> tuple[str, ...]:
        """Model inputs besides (n, rho2): the spanned actuator commands."""
        return self.inputs[2:]

    def _one(self, name: str, X: np.ndarray, use_tables: bool):
        if use_tables and name in self.tables:
            return self.tables[name].evaluate(X)
        m = self.models[name]
        # a gray-box map with a coverage of its own (the EGR-open pulsation ratio) says it
        rows = getattr(m, "valid_rows", None)
        return m.predict(X), (rows(X) if rows is not None else np.ones(X.shape[0], dtype=bool))

    def _matrix(self, n, rho2, extra: Mapping[str, object] | None) -> np.ndarray:
        """Model input rows; an extra input not given takes the low end of its identified
        range (EGR closed, swirl flaps open: the paper's reference condition)."""
        cols = [np.atleast_1d(np.asarray(n, dtype=float)),
                np.atleast_1d(np.asarray(rho2, dtype=float))]
        size = max(cols[0].size, cols[1].size)
        for k in self.extra_inputs:
            if extra is not None and k in extra:
                v = np.atleast_1d(np.asarray(extra[k], dtype=float))
            else:
                v = np.array([self.validity[k].lo if self.validity is not None
                              and k in self.validity.names else 0.0])
            cols.append(v)
        return np.column_stack([np.broadcast_to(c, (size,)) for c in cols]).astype(float)

    def in_region(self, n, rho2, extra: Mapping[str, object] | None = None) -> np.ndarray:
        """Identified region of the eta_v model's training data (all five share the data)."""
        return self.models[self.outputs[0]].in_region(self._matrix(n, rho2, extra))

    def check(self, data: Mapping[str, object], size: int) -> tuple[np.ndarray, list[str]]:
        """Per-input validity of ``size`` segments (``data``: arrays by feature name): a flag
        and a reason per segment ("" where valid). The joint (n, rho2, ...) coverage is
        :meth:`predict`'s flag."""
        if self.validity is None:
            return np.ones(size, dtype=bool), [""] * size
        return self.validity.contains(data, size), self.validity.reasons(data, size)

    def predict(self, n, rho2, *, use_tables: bool = True,
                extra: Mapping[str, object] | None = None, phases: bool = True
                ) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """Reference values at the operating points and a validity flag per point.

        ``extra``: values of the extra model inputs (actuator commands) by name. ``phases``:
        also the phase maps (they do not decide the validity; a caller that needs only eta_V
        and the flag leaves them out). One operating
        point at a time (the per-segment path) is memoised for the last point: the bank's
        hypothesis models all ask for the reference at the same segment."""
        X = self._matrix(n, rho2, extra)
        if not phases:
            return self._predict(X, use_tables=use_tables, phases=False)
        if X.shape[0] == 1:
            key = (tuple(X[0].tolist()), bool(use_tables))
            memo = self.__dict__.get("_memo")
            if memo is not None and memo[0] == key:
                return {k: v.copy() for k, v in memo[1].items()}, memo[2].copy()
            out, valid = self._predict(X, use_tables=use_tables)
            object.__setattr__(self, "_memo", (key, {k: v.copy() for k, v in out.items()},
                                               valid.copy()))
            return out, valid
        return self._predict(X, use_tables=use_tables)

    def _predict(self, X: np.ndarray, *, use_tables: bool, phases: bool = True
                 ) -> tuple[dict[str, np.ndarray], np.ndarray]:
        valid = self.models[self.outputs[0]].in_region(X)
        out = {}
        for k in self.outputs:
            if k in PHASES and not phases:
                continue  # phases do not decide the validity
            if k in PHASES and f"{k}_cos" in self.models:
                # Phase from the phasor maps: no wrap-around anywhere in the map. Phases have
                # their own (amplitude) validity, so their tables do not decide it.
                u, _ = self._one(f"{k}_cos", X, use_tables)
                v, _ = self._one(f"{k}_sin", X, use_tables)
                out[k] = np.degrees(np.arctan2(v, u)) * PERIOD_DEG / 360.0
                continue
            v, ok = self._one(k, X, use_tables)
            if k not in PHASES:
                valid &= ok
            out[k] = v
        return out, valid

    def save(self, directory) -> Path:
        """Write one ``<output>.npz`` model and ``<output>.lut.json`` table per output plus a
        manifest ``reference_models.json``."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        for k, m in self.models.items():
            m.save(d / f"{k}.npz")
        for k, t in self.tables.items():
            t.save(d / f"{k}.lut.json")
        manifest = {"type": "diesel_reference", "inputs": list(self.inputs),
                    "outputs": list(self.models), "tables": list(self.tables),
                    "phase_centre": self.phase_centre, "info": self.info,
                    "validity": self.validity.to_dict() if self.validity else None,
                    "regimes": [r.regime for r in self.regimes]}
        for r in self.regimes:
            if not r.regime or r.regimes:
                raise ValueError("a further regime needs a name and no regimes of its own")
            r.save(d / "regimes" / r.regime)
        (d / MANIFEST).write_text(json.dumps(manifest, indent=1))
        return d

    @classmethod
    def load(cls, directory) -> ReferenceModelSet:
        """Load a model set; the models of one bank in one process share one instance (the
        files are read once; a changed manifest is read again)."""
        d = Path(directory)
        mf = d / MANIFEST
        if mf.exists():
            key = (str(d.resolve()), mf.stat().st_mtime_ns)
            if key not in _LOADED:
                _LOADED[key] = cls._load(d)
            return _LOADED[key]
        return cls._load(d)

    @classmethod
    def _load(cls, d: Path, base: Mapping[str, Lolimot] | None = None) -> ReferenceModelSet:
        """``base``: for a further regime, the base regime's maps (an EGR-open regime's
        eta_V is a flow model over its eta_V map, :class:`.egrflow.EgrFlowEta`, and its
        pulsations may be ratios to its pulsation maps, :mod:`.pulsation`)."""
        mf = d / MANIFEST
        if not mf.exists():
            raise FileNotFoundError(f"no reference model set in {d} (missing {MANIFEST}); "
                                    "run `fdi-ros identify --plant diesel` first")
        try:
            manifest = json.loads(mf.read_text())
            models = {k: Lolimot.load(d / f"{k}.npz") for k in manifest["outputs"]}
            tables = {k: LookupTable.load(d / f"{k}.lut.json") for k in manifest["tables"]}
        except (KeyError, json.JSONDecodeError) as exc:
            raise ValueError(f"{mf}: malformed manifest: {exc}") from exc
        validity = manifest.get("validity")
        inputs = tuple(manifest.get("inputs", INPUTS))
        base_eta = None if base is None else base.get("eta_v")
        if base_eta is not None and "eta_v" in models:
            from fdi_ros.plants.diesel.egrflow import EgrFlowEta

            models["eta_v"] = EgrFlowEta.load_beside(d / "eta_v.npz", models["eta_v"],
                                                     base_eta, inputs)
        if base is not None and manifest.get("info", {}).get(WHERE_COVERED):
            models = _with_ratio_maps(models, base, inputs, mf)
        return cls(models=models, tables=tables,
                   phase_centre={k: float(v) for k, v in manifest["phase_centre"].items()},
                   info=manifest.get("info", {}), inputs=inputs,
                   validity=ValidityRegion.from_dict(validity) if validity else None,
                   regimes=[cls._load(d / "regimes" / str(r), models)
                            for r in manifest.get("regimes") or []])


def _with_ratio_maps(models: dict[str, Any], base: Mapping[str, Any], inputs: tuple[str, ...],
                     manifest: Path) -> dict[str, Any]:
    """A covered regime's loaded maps with its pulsations as ratios to the base maps."""
    from fdi_ros.plants.diesel.pulsation import HARMONICS, PulsationRatio, RatioContext

    names = [k for pair in HARMONICS.values() for k in pair]
    if not hasattr(models.get("eta_v"), "flow") or any(k not in models for k in names):
        raise ValueError(f"{manifest}: a pulsation-ratio regime needs an EGR flow model and "
                         f"ratio maps of {names}")
    ctx = RatioContext(models["eta_v"], base, {k: models[k] for k in names}, inputs)
    return {**models, **{k: PulsationRatio(ctx, k) for k in names}}


@dataclass(frozen=True)
class IdentificationResult:
    """Outcome of :func:`identify_reference_models`.

    nrmse_test : held-out NRMSE per output (LOLIMOT); nrmse_test_lut : the same for the tables.
    lut_error : table-vs-model RMSE on the test points per output.
    """

    models: ReferenceModelSet
    results: dict[str, LolimotResult]
    nrmse_train: dict[str, float]
    nrmse_test: dict[str, float]
    nrmse_test_lut: dict[str, float]
    lut_error: dict[str, dict]
    n_train: int
    n_val: int
    n_test: int
    train_s: float
    success: bool
    message: str


def storage_regressor(t, n, p2, lag: int = 2) -> np.ndarray:
    """``x = (dp2/dt) / (n p2)`` [1/(rpm s)], dp2/dt a backward difference over ``lag``
    segments (NaN for the first ``lag``), the same estimate the residual models use online.

    The air stored in the boost volume while p2 changes, ``V_b/(R T2) dp2/dt``, passes the MAF
    sensor but not the cylinders; relative to ``m_th = n/120 V_D p2/(R T2)`` it adds
    ``(120 V_b / V_D) x`` to the eta_V computed from the MAF.
    """
    t, n, p2 = (np.asarray(a, dtype=float) for a in (t, n, p2))
    x = np.full(t.shape, np.nan)
    if t.size > lag:
        dt = t[lag:] - t[:-lag]
        with np.errstate(divide="ignore", invalid="ignore"):
            x[lag:] = np.where(dt > 0, (p2[lag:] - p2[:-lag]) / dt, np.nan) / (n[lag:] * p2[lag:])
    return x


def actuator_breakpoints(x: np.ndarray, most: int) -> np.ndarray:
    """Table breakpoints of an actuator command: its distinct settings when there are at most
    ``most`` (e.g. flaps open / closed), else ``most`` equidistant ones over its range."""
    u = np.unique(np.round(np.asarray(x, dtype=float), 3))
    return u if 2 <= u.size <= most else np.linspace(u[0], u[-1], max(most, 2))


def _target(k: str, y: np.ndarray, centre: float | None) -> np.ndarray:
    return wrap_phase(y, centre) if k in PHASES else y


def identify_reference_models(data: Mapping[str, np.ndarray], *,
                              config: IdentificationConfig | None = None,
                              progress: bool = False) -> IdentificationResult:
    """Identify the five models from feature arrays (see :func:`feature_table`).

    The segments are split into contiguous train / validation / test blocks; the validation
    blocks choose the number of local models, the test blocks give the reported NRMSE.
    """
    cfg = config or IdentificationConfig()
    extra = tuple(cfg.extra_inputs)
    missing = [k for k in INPUTS + OUTPUTS + extra if k not in data]
    if missing:
        raise ValueError(f"identification data lacks {missing}")
    finite = np.ones(np.asarray(data["n"]).shape[0], dtype=bool)
    for k in INPUTS + OUTPUTS + extra + tuple(a for a in ACTUATORS if a in data):
        finite &= np.isfinite(np.asarray(data[k], dtype=float))
    # Actuator commands the data span are model inputs; held ones bound the validity only.
    spanned = tuple(a for a in ACTUATORS if cfg.actuator_inputs and a in data and
                    np.ptp(np.asarray(data[a], dtype=float)[finite]) > ACTUATOR_TOL[a])
    inputs = INPUTS + spanned + tuple(k for k in extra if k not in spanned)
    X = np.column_stack([np.asarray(data[k], dtype=float) for k in inputs])[finite]
    if X.shape[0] < 10 * cfg.min_samples_per_model:
        raise ValueError(f"only {X.shape[0]} usable segments: too few to identify the models")
    bounded = INPUTS + ACTUATORS + tuple(k for k in extra if k not in ACTUATORS)
    validity = ValidityRegion.learn({k: np.asarray(data[k], dtype=float)[finite]
                                     for k in bounded if k in data},
                                    bounded, tolerance=ACTUATOR_TOL,
                                    rel_tolerance=0.0, units=UNITS)
    tr, va, te = split_blocks(X.shape[0], block=cfg.block, seed=cfg.seed)
    n_bp = np.asarray(cfg.lut_n, dtype=float)
    r_bp = np.asarray(cfg.lut_rho2, dtype=float)
    if n_bp.size == 0:
        n_bp = np.linspace(X[:, 0].min(), X[:, 0].max(), 17)
    if r_bp.size == 0:
        r_bp = np.linspace(X[:, 1].min(), X[:, 1].max(), 13)
    bps = (n_bp, r_bp) + tuple(actuator_breakpoints(X[:, 2 + j], cfg.lut_actuator)
                               for j in range(len(spanned))) if cfg.tables else None
    models, tables, results, centres, min_amp = {}, {}, {}, {}, {}
    nr_tr, nr_te, nr_lut, lut_err = {}, {}, {}, {}
    t0 = time.perf_counter()
    outputs = OUTPUTS
    if progress:
        from tqdm import tqdm
        outputs = tqdm(OUTPUTS, desc="reference models", unit="model")
    storage = 0.0
    xs = None
    if cfg.storage_correction and all(k in data for k in ("t", "p2")):
        xs = (np.asarray(data["storage_x"], dtype=float) if "storage_x" in data else
              storage_regressor(data["t"], data["n"], data["p2"], cfg.rate_lag))[finite]
    for k in outputs:
        y = np.asarray(data[k], dtype=float)[finite]
        if k == "eta_v" and xs is not None:
            # eta_V = f(n, rho2) + c x: c by partialling out (Frisch-Waugh / Robinson's
            # double residual): the parts of x and of eta_V that the static map of
            # (n, rho2) explains are removed first (LOLIMOT fits of each), then c is the
            # least-squares slope between the remainders. Alternating fits of f and c
            # converge slowly because the cycle's boost ramps correlate with (n, rho2).
            ok = np.isfinite(xs)
            x0 = np.nan_to_num(xs)
            sel = tr[ok[tr]]
            mx, my = cfg.lolimot(), cfg.lolimot()
            mx.fit(X[sel], x0[sel])
            my.fit(X[sel], y[sel])
            rx = x0[sel] - mx.predict(X[sel])
            ry = y[sel] - my.predict(X[sel])
            c0 = float(rx @ ry / (rx @ rx)) if float(rx @ rx) > 0 else 0.0
            # The remainders still share some structure, so refine c on the validation
            # blocks: the c whose static map predicts held-out eta_V best.
            from scipy.optimize import minimize_scalar

            sv = va[ok[va]]

            def val_rmse(c):
                m = cfg.lolimot()
                m.fit(X[sel], y[sel] - c * x0[sel])
                return float(np.sqrt(np.mean((y[sv] - c * x0[sv] - m.predict(X[sv])) ** 2)))

            hi = 3.0 * abs(c0) + 1e-12
            opt = minimize_scalar(val_rmse, bounds=(-hi, hi), method="bounded",
                                  options={"xatol": 0.01 * hi, "maxiter": 20})
            storage = float(opt.x) if opt.fun < val_rmse(c0) else c0
            y = y - storage * x0
        ktr, kva, kte = tr, va, te
        if k in PHASES:
            # The phase of a harmonic that is hardly there is noise: phases are identified
            # (and later compared) only where the amplitude is a fair part of its range.
            amp = np.asarray(data[AMPLITUDE_OF[k]], dtype=float)[finite]
            min_amp[k] = cfg.phase_min_amp_frac * float(np.percentile(amp[tr], 95))
            ktr, kva, kte = (i[amp[i] >= min_amp[k]] for i in (tr, va, te))
        if k in PHASES:
            # The phase wraps (period 180 deg CA) and drifts through most of a period across
            # the air path's resonance: identify the unit phasor (cos, sin) instead, two
            # smooth maps, and take the angle of their prediction.
            centres[k] = branch_centre(y[ktr])
            ang = 2.0 * np.pi * y / PERIOD_DEG
            pred = {}
            for comp, vals in (("cos", np.cos(ang)), ("sin", np.sin(ang))):
                name = f"{k}_{comp}"
                m = cfg.lolimot()
                res = m.fit(X[ktr], vals[ktr], X_val=X[kva], y_val=vals[kva],
                            progress=progress, input_names=inputs, output_name=name)
                m.set_region(X[np.concatenate([ktr, kva, kte])])
                models[name], results[name] = m, res
                tab = _table(m, bps, inputs, name)
                if tab is not None:
                    tables[name] = tab
                pred[comp] = (m.predict, tab or m.predict)
            yw = wrap_phase(y, centres[k])

            def phase_of(Xs, use_table, pred=pred):
                u = pred["cos"][1](Xs) if use_table else pred["cos"][0](Xs)
                v = pred["sin"][1](Xs) if use_table else pred["sin"][0](Xs)
                return np.degrees(np.arctan2(v, u)) * PERIOD_DEG / 360.0

            def circ_nrmse(idx, use_table, yw=yw):
                e = wrap_phase(y[idx] - phase_of(X[idx], use_table), 0.0)
                return float(np.sqrt(np.mean(e ** 2)) / np.std(yw[idx]))

            nr_tr[k] = circ_nrmse(ktr, False)
            nr_te[k] = circ_nrmse(kte, False)
            nr_lut[k] = circ_nrmse(kte, True)
            lut_err[k] = {"rmse": float(np.sqrt(np.mean(wrap_phase(
                phase_of(X[kte], True) - phase_of(X[kte], False), 0.0) ** 2))),
                "n_points": int(kte.size)}
            continue
        m = cfg.lolimot()
        res = m.fit(X[ktr], y[ktr], X_val=X[kva], y_val=y[kva], progress=progress,
                    input_names=inputs, output_name=k)
        # the identified region: every segment of the cycle (trained on or scored on), so the
        # region reaches the cycle's ends (its top speed fell in held-out blocks)
        m.set_region(X)
        models[k], results[k] = m, res
        tab = _table(m, bps, inputs, k)
        if tab is not None:
            tables[k] = tab
        nr_tr[k] = nrmse(y[ktr], m.predict(X[ktr]))
        nr_te[k] = nrmse(y[kte], m.predict(X[kte]))
        nr_lut[k] = nrmse(y[kte], (tab or m.predict)(X[kte]))
        lut_err[k] = table_error(m.predict, tab, X[kte]) if tab is not None else \
            {"rmse": 0.0, "n_points": int(kte.size)}
    train_s = time.perf_counter() - t0
    info = {"nrmse_test": nr_te, "storage_coeff": storage, "phase_min_amp": min_amp,
            "n_models": {k: r.n_models for k, r in results.items()},
            "n_train": int(tr.size), "config": {k: (list(v) if isinstance(v, tuple) else v)
                                                for k, v in asdict(cfg).items()}}
    mset = ReferenceModelSet(models=models, tables=tables, phase_centre=centres, info=info,
                             inputs=inputs, validity=validity)
    return IdentificationResult(models=mset, results=results, nrmse_train=nr_tr,
                                nrmse_test=nr_te, nrmse_test_lut=nr_lut, lut_error=lut_err,
                                n_train=int(tr.size), n_val=int(va.size), n_test=int(te.size),
                                train_s=train_s, success=all(r.success for r in results.values()),
                                message="identified five reference models")


# Operating regimes of the diesel's reference models, in the order they are tried: the
# paper's (EGR valve closed, swirl flaps open: the ECU maps and tables of the paper), then the
# part-load regimes where the ECU recirculates exhaust gas, with the flaps open or closed.
# Each: (name, EGR valve open?, filling ports closed?).
REGIMES = (("egr_closed_flaps_open", False, False), ("egr_open_flaps_open", True, False),
           ("egr_open_flaps_closed", True, True))
# Inputs besides (n, rho2, egr_cmd) of the maps where the EGR valve is open: the recirculated
# gas follows the exhaust back pressure, set by the VGT and the exhaust flow (fuel), and heats
# the charge (T2).
OPEN_EGR_INPUTS = ("fuel", "vgt", "T2")
# The boost temperature's rate [K/s] beyond which the static maps do not hold (a valve that
# opened or closed moments ago, a load step heating the intercooler): such segments are left
# out of the identification, and on line they are "transient" (a regime of their own).
TEMPERATURE_SETTLED = 3.0
# The column marking the segments quasi-stationary for the exhaust side (egrflow.settled).
SETTLED = "egr_settled"
# Info flag of a regime tried only where its maps cover a segment (the EGR-open regime with
# its pulsations relative to the base maps, module pulsation: where they do not cover it, the
# next regime judges eta_V alone)
WHERE_COVERED = "where_covered"
# The name of such a regime: its parent's and this suffix (its transients are the parent's)
PULSATION_SUFFIX = "+pulsation"


def transient_regime(regime: str) -> str:
    """The regime of a transient segment of ``regime``: ``<regime>/transient``, a covered
    regime's its parent's (a transient is judged as the parent judges it)."""
    from fdi_ros.core.symptoms import TRANSIENT_SUFFIX

    return regime.removesuffix(PULSATION_SUFFIX) + TRANSIENT_SUFFIX


# The column marking segments for the further regimes only (1: not in the base regime's maps)
REGIMES_ONLY = "regimes_only"
# Fewest quasi-stationary segments an EGR-open regime needs for its flow model.
MIN_FLOW_SEGMENTS = 500
# Fewest segments a regime needs in the identification data to get models of its own, and
# the stride of the segments its maps are fitted on.
MIN_REGIME_SEGMENTS = 2000
REGIME_STRIDE = 2
# Time constants [s] of the T2 sensor's lag tried by identify_t2_tau (its search bounds).
T2_TAU_BOUNDS = (0.0, 3.0)
# ... the rate [K/s] up to which a segment's temperature counts as settled for it, and the one
# from which it counts as moving: where the lag's error (tau dT2/dt) stands out of the map's
# and the stored air's. On the identification data the search over every unsettled segment
# (> 1 K/s) took 0.71 s for the plant's 0.8 s sensor; over those moving faster than 10 K/s
# (511 segments, after a load step or the EGR valve closing) 0.80 s.
T2_TAU_SETTLED = 1.0
T2_TAU_MOVING = 10.0


def regime_labels(data: Mapping[str, np.ndarray]) -> np.ndarray:
    """The regime of each segment by its actuator commands ("" where none of
    :data:`REGIMES`: e.g. flaps moving, or closed with the EGR valve closed)."""
    n = np.asarray(data["n"]).shape[0]
    egr = np.asarray(data["egr_cmd"], dtype=float) if "egr_cmd" in data else np.zeros(n)
    swirl = np.asarray(data["swirl_cmd"], dtype=float) if "swirl_cmd" in data else np.zeros(n)
    tol_e, tol_s = ACTUATOR_TOL["egr_cmd"], ACTUATOR_TOL["swirl_cmd"]
    out = np.full(n, "", dtype=object)
    for name, egr_open, closed in REGIMES:
        e_ok = egr > tol_e if egr_open else np.abs(egr) <= tol_e
        s_ok = np.abs(swirl - 1.0) <= tol_s if closed else np.abs(swirl) <= tol_s
        out[(out == "") & e_ok & s_ok] = name
    return out


def compensate_t2(data: Mapping[str, np.ndarray], tau: float) -> dict[str, np.ndarray]:
    """``data`` with the T2 sensor's lag undone (as :meth:`ReferenceModelSet.compensate`)."""
    probe = ReferenceModelSet(models={}, tables={}, info={"t2_tau": float(tau)})
    return probe.compensate(data)


def identify_t2_tau(data: Mapping[str, np.ndarray], config: IdentificationConfig) -> float:
    """The T2 sensor's time constant [s]: a slow sensor makes rho2 and eta_V wrong in every
    temperature transient, by ``tau dT2/dt / T2``.

    The static eta_V map of (n, rho2) is fitted on the training segments whose temperature
    has settled (|dT2/dt| <= T2_TAU_SETTLED, where tau hardly matters), then tau is the one
    whose compensation lets that map predict the segments whose temperature moves
    (|dT2/dt| > T2_TAU_MOVING; the fastest 500 if fewer than 50 do) best, the
    stored air's share and an offset fitted with it by least squares (the two regressors
    move together in a load step); twice, the map refitted with the first tau. The map stays
    fixed in the search: a map refitted per tau split its cells differently for neighbouring
    taus, and the bumpy objective stopped the search 0.2 s short of the sensor's 0.8 s.
    """
    from scipy.optimize import minimize_scalar

    n_rows = np.asarray(data["n"]).shape[0]
    tr, _, _ = split_blocks(n_rows, block=config.block, seed=config.seed)
    x = np.nan_to_num(np.asarray(data.get("storage_x", np.zeros(n_rows)), dtype=float))
    rate = np.abs(np.asarray(data["T2_rate"], dtype=float))
    step = max(1, n_rows // 20000)   # every step-th settled segment for the map

    def columns(tau: float, rows: Mapping[str, np.ndarray] = data
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        d = compensate_t2(rows, tau)
        X = np.column_stack([d[k] for k in INPUTS])
        y = d["eta_v"]
        return X, y, np.all(np.isfinite(X), axis=1) & np.isfinite(y)

    _, _, ok = columns(0.0)
    moving = np.flatnonzero(ok & (rate > T2_TAU_MOVING))
    if moving.size < 50:
        cand = np.flatnonzero(ok & (rate > T2_TAU_SETTLED))
        moving = np.sort(cand[np.argsort(-rate[cand])][:500])
    if moving.size < 50:
        return 0.0
    A = np.column_stack([x[moving], np.ones(moving.size)])
    at_moving = {k: np.asarray(v)[moving] for k, v in data.items()}   # the search's rows
    tau = 0.0
    for _ in range(2):
        X, y, ok = columns(tau)
        fit = tr[ok[tr] & (rate[tr] <= T2_TAU_SETTLED)][::step]
        m = config.lolimot()
        m.fit(X[fit], y[fit])

        def rmse(t: float, m=m) -> float:
            Xt, yt, _ = columns(t, at_moving)
            e = yt - m.predict(Xt)
            coef, *_ = np.linalg.lstsq(A, e, rcond=None)
            return float(np.sqrt(np.mean((e - A @ coef) ** 2)))

        opt = minimize_scalar(rmse, bounds=T2_TAU_BOUNDS, method="bounded",
                              options={"xatol": 0.01, "maxiter": 30})
        tau = float(opt.x) if opt.fun < rmse(0.0) else 0.0
    return tau


def identify_regime_models(data: Mapping[str, np.ndarray], *,
                           config: IdentificationConfig | None = None,
                           progress: bool = False, further_regimes: bool = True,
                           log: Callable[[str], None] = lambda s: None) -> IdentificationResult:
    """The reference models of every operating regime the data hold enough of.

    1. The T2 sensor's time constant, from the base regime's data (:func:`identify_t2_tau`),
       when the data have the ``T2_rate`` feature; every regime's data compensated with it.
    2. The base regime (:data:`REGIMES`, first): the paper's five maps of (n, rho2), as
       :func:`identify_reference_models` (ECU tables, storage correction).
    3. With ``further_regimes``, each further regime with at least
       :data:`MIN_REGIME_SEGMENTS` segments: maps of
       (n, rho2, egr_cmd, fuel, vgt, T2) evaluated directly (no table holds six inputs), its
       eta_V corrected for the stored air with the base regime's coefficient (the boost
       volume's physics does not change with the valve).
    Returns the base regime's result; its model set holds the others in ``regimes``.
    """
    from fdi_ros.plants.diesel import egrflow

    cfg = config or IdentificationConfig()
    data = dict(data)
    if all(k in data for k in ("n", "fuel", "vgt", "egr_cmd")):
        # quasi-stationary for the exhaust side (over the whole stream, before it is split)
        data[SETTLED] = egrflow.settled(data).astype(float)
    labels = regime_labels(data)
    sel = {name: labels == name for name, _, _ in REGIMES}
    if REGIMES_ONLY in data:
        sel[REGIMES[0][0]] &= np.asarray(data[REGIMES_ONLY]) == 0
    base_name = REGIMES[0][0]
    if sel[base_name].sum() < 10 * cfg.min_samples_per_model:
        raise ValueError(f"only {int(sel[base_name].sum())} segments with the EGR valve "
                         "closed and the flaps open: too few to identify the base regime")
    rows = {k: {c: np.asarray(v)[m] for c, v in data.items()} for k, m in sel.items()}
    tau = 0.0
    every = rows   # every segment of each regime (the VGT's lag shows in T2 transients too)
    if "T2_rate" in data:
        # the sensor's lag shows in the temperature transients (the EGR valve opening and
        # closing in the ECU's passes among them): identified on all of the base regime's
        # segments, the maps then on those whose temperature has settled (as on line)
        tau = identify_t2_tau(rows[base_name], cfg)
        log(f"[identify] T2 sensor time constant {tau:.2f} s")
        every = {k: compensate_t2(v, tau) for k, v in rows.items()}
        rows = {k: {c: v[np.abs(d["T2_rate"]) <= TEMPERATURE_SETTLED] for c, v in d.items()}
                for k, d in every.items()}
    res = identify_reference_models(rows[base_name], config=cfg, progress=progress)
    base = res.models
    base.info.update(regime=base_name, t2_tau=tau,
                     regime_nrmse_test={base_name: res.nrmse_test},
                     regime_segments={base_name: int(sel[base_name].sum())})
    coeff = float(base.info.get("storage_coeff", 0.0))

    def stored_air_removed(d: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The regime's eta_V less the air stored in the boost volume (the base regime's
        coefficient: the boost volume's physics does not change with the valve)."""
        if "storage_x" in d:
            d = {**d, "eta_v": d["eta_v"] - coeff * np.nan_to_num(d["storage_x"])}
        return d

    flows: list[tuple[dict[str, np.ndarray], Any, tuple[str, ...]]] = []
    for name, _, closed in REGIMES[1:] if further_regimes else ():
        d = rows[name]
        if d["n"].size < MIN_REGIME_SEGMENTS or not all(k in d for k in OPEN_EGR_INPUTS):
            continue
        # every other segment: neighbours 15 ms apart repeat each other, and six-input maps
        # cost several times the paper's two-input ones
        d = stored_air_removed({k: v[::REGIME_STRIDE] for k, v in d.items()})
        # the joint coverage over the operating point (n, rho2): a six-input grid is empty
        rcfg = dataclasses.replace(cfg, extra_inputs=OPEN_EGR_INPUTS, tables=False,
                                   storage_correction=False, coverage_inputs=2)
        r = identify_reference_models(d, config=rcfg, progress=progress)
        r.models.info.update(regime=name, t2_tau=tau)
        # eta_V from the exhaust side's physics over the base map (module egrflow): a map of
        # six inputs learns the exhaust side along the identification's passes only, and a
        # drive lies between them. Identified on the regime's own quasi-stationary segments
        # (with the flaps closed also the ports' loss); without enough of them the data map
        # stays (tried: the flaps-open exhaust side with only the ports' loss fitted on the
        # unsettled flaps-closed segments; it read eta_V 0.04 low on a drive, a false alarm).
        if SETTLED in d and d[SETTLED].sum() >= MIN_FLOW_SEGMENTS:
            flow = _egr_flow_map(d, base, r.models, closed, cfg)
            r.models.models["eta_v"] = flow[0]
            r.nrmse_test["eta_v"] = flow[1]
            r.models.info["egr_flow"] = flow[0].flow.to_dict() | {"fit": flow[2]}
            # the crank pulsations' maps of six inputs do not carry over between drives
            # (held-out NRMSE 0.2-0.6 on a drive they were not identified on, README):
            # this regime is judged on eta_V alone
            r.models.info["judged_outputs"] = ["eta_v"]
            flows.append((stored_air_removed(every[name]), flow[0], r.models.inputs))
            if not closed:
                # ... and where the base maps cover it, on the pulsations too: relative to
                # the base maps (module pulsation; the ports' loss with the flaps closed
                # changes the pulsation's source, which the base maps do not describe)
                covered = _pulsation_regime(d, base, r.models, cfg)
                if covered is not None:
                    base.regimes.append(covered[0])
                    base.info["regime_nrmse_test"][covered[0].regime] = covered[1]
                    log(f"[identify] regime {covered[0].regime}: {covered[2]} segments within "
                        "the base maps, held-out NRMSE " + ", ".join(
                            f"{k} {v:.3f}" for k, v in covered[1].items()))
        base.regimes.append(r.models)
        base.info["regime_nrmse_test"][name] = r.nrmse_test
        base.info["regime_segments"][name] = int(d["n"].size)
        log(f"[identify] regime {name}: {d['n'].size} segments, held-out NRMSE "
            + ", ".join(f"{k} {v:.3f}" for k, v in r.nrmse_test.items()))
    if flows and all("vgt_rate" in d for d, _, _ in flows):
        base.info["vgt_tau"] = identify_vgt_tau(flows)
        log(f"[identify] VGT vanes' time constant {base.info['vgt_tau']:.3f} s")
    return res


def vgt_position(cmd: np.ndarray, rate: np.ndarray, tau: float) -> np.ndarray:
    """The VGT vanes' position estimated from their command and its rate: a first-order lag
    of time constant ``tau`` undone, ``cmd - tau d(cmd)/dt``, within 0..1."""
    return np.clip(cmd - tau * rate, 0.0, 1.0)


# Search bounds [s] of the VGT vanes' lag behind their command, and the command's rate [1/s]
# from which a segment's vanes count as moving (where the lag shows in the EGR flow).
VGT_TAU_BOUNDS = (0.0, 1.0)
VGT_MOVING = 0.2


def identify_vgt_tau(parts: Sequence[tuple[Mapping[str, np.ndarray], Any, tuple[str, ...]]]
                     ) -> float:
    """The time constant [s] of the VGT vanes behind their command: the EGR flow model sees
    the command, the exhaust side the vanes, and while the boost controller moves them
    (a tip-in with the valve open) p3 and the recirculated gas follow the vanes. ``parts``:
    each EGR-open regime's data (T2 compensated), its identified eta_V flow model and its
    inputs; tau is the one whose position estimate (``cmd - tau d(cmd)/dt``) lets the flow
    models predict eta_V best on the segments whose vanes move (|d(cmd)/dt| > VGT_MOVING),
    the models fixed (identified on quasi-stationary segments, where tau does not matter).
    0 if fewer than 50 such segments or no lag predicts better than none."""
    from scipy.optimize import minimize_scalar

    sets = []
    for d, model, inputs in parts:
        rate = np.asarray(d["vgt_rate"], dtype=float)
        X = np.column_stack([np.asarray(d[k], dtype=float) for k in inputs])
        ok = np.isfinite(rate) & (np.abs(rate) > VGT_MOVING) & np.all(np.isfinite(X), axis=1) \
            & np.isfinite(np.asarray(d["eta_v"], dtype=float))
        rows = np.flatnonzero(ok)
        if rows.size:
            sets.append((X[rows], rate[rows], np.asarray(d["eta_v"], float)[rows], model,
                         inputs.index("vgt")))
    if sum(s[0].shape[0] for s in sets) < 50:
        return 0.0

    def rmse(tau: float) -> float:
        err = []
        for X, rate, y, model, j in sets:
            Xt = X.copy()
            Xt[:, j] = vgt_position(X[:, j], rate, tau)
            e = y - model.predict(Xt)
            err.append(e[np.isfinite(e) & model.in_region(Xt)])
        return float(np.sqrt(np.mean(np.concatenate(err) ** 2)))

    opt = minimize_scalar(rmse, bounds=VGT_TAU_BOUNDS, method="bounded",
                          options={"xatol": 0.005, "maxiter": 30})
    return float(opt.x) if opt.fun < rmse(0.0) else 0.0


def _egr_flow_map(d: Mapping[str, np.ndarray], base: ReferenceModelSet,
                  regime: ReferenceModelSet, flaps_closed: bool,
                  cfg: IdentificationConfig) -> tuple[Any, float, dict]:
    """An EGR-open regime's eta_V map (:class:`.egrflow.EgrFlowEta`) identified on its
    quasi-stationary segments of the training and validation blocks; its held-out NRMSE on
    the test blocks' (all of them, as the data map's)."""
    from fdi_ros.plants.diesel import egrflow
    from fdi_ros.plants.diesel.plant import DieselParams

    size = d["n"].size
    tr, va, te = split_blocks(size, block=cfg.block, seed=cfg.seed)
    fit_rows = np.sort(np.r_[tr, va])
    fit_rows = fit_rows[d[SETTLED][fit_rows] > 0]
    base_eta = base.models["eta_v"]
    eta_tot = base_eta.predict(np.column_stack([d["n"], d["rho2"]]))
    sub = {k: d[k][fit_rows] for k in egrflow.INPUTS}
    engine = DieselParams()
    f = egrflow.fit(sub, eta_tot[fit_rows], d["eta_v"][fit_rows],
                    displacement_l=engine.V_D * 1e3, n_cyl=engine.n_cyl,
                    port=flaps_closed, seed=cfg.seed)
    m = egrflow.EgrFlowEta(f.model, base_eta, regime.models["eta_v"], regime.inputs)
    X = np.column_stack([d[k] for k in regime.inputs])
    ok = np.isfinite(d["eta_v"][te]) & np.all(np.isfinite(X[te]), axis=1)
    score = nrmse(d["eta_v"][te][ok], m.predict(X[te][ok]))
    return m, score, {"segments": f.n_segments, "rmse": round(f.rmse, 5), "nfev": f.nfev,
                      "success": f.success}


def _pulsation_regime(d: Mapping[str, np.ndarray], base: ReferenceModelSet,
                      regime: ReferenceModelSet, cfg: IdentificationConfig
                      ) -> tuple[ReferenceModelSet, dict[str, float], int] | None:
    """The EGR-open regime ``regime`` (its eta_V an EGR flow model) judged on the pulsations
    too, where the base maps cover a segment: the harmonics relative to the base maps' by
    ratio maps of :data:`.pulsation.RATIO_INPUTS` (:mod:`.pulsation`), identified on its
    segments of ``d`` within the base maps' coverage. Returns the set, the held-out NRMSE per
    output (the harmonics themselves) and the segments it was identified on; None with fewer
    than :data:`MIN_REGIME_SEGMENTS` of them."""
    from fdi_ros.plants.diesel import pulsation as pu

    flow = regime.models["eta_v"]
    X = np.column_stack([d[k] for k in regime.inputs])
    n, rho2 = d["n"], d["rho2"]
    inside = base.models["eta_v"].in_region(np.column_stack([n, rho2])) \
        & np.all(np.isfinite(X), axis=1)
    rows = np.flatnonzero(inside)
    if rows.size < MIN_REGIME_SEGMENTS:
        return None
    sub = {k: np.asarray(v)[rows] for k, v in d.items()}
    ref = pu.base_harmonics(base.models, sub["n"], sub["rho2"])
    R = pu.ratio_inputs(flow, X[rows], regime.inputs)
    targets = pu.ratio_targets(sub, ref)
    min_amp = base.info.get("phase_min_amp", {})
    strong = {ph: ref[amp] >= float(min_amp.get(ph, -np.inf))
              for amp, ph in pu.HARMONICS.values()}
    tr, va, te = split_blocks(rows.size, block=cfg.block, seed=cfg.seed)
    maps = pu.fit_ratio_maps(R, targets, np.sort(np.r_[tr, va]), strong, np.arange(rows.size))
    ctx = pu.RatioContext(flow, base.models, maps, regime.inputs)
    models: dict[str, Any] = {"eta_v": flow, **{k: pu.PulsationRatio(ctx, k) for k in maps}}
    name = regime.regime + PULSATION_SUFFIX
    info = {k: v for k, v in regime.info.items() if k not in ("nrmse_test", "judged_outputs")}
    info.update(regime=name, phase_min_amp=dict(min_amp), ratio_inputs=list(pu.RATIO_INPUTS),
                judged_outputs=list(pu.JUDGED), **{WHERE_COVERED: True})
    out = ReferenceModelSet(models=models, tables={}, phase_centre={}, info=info,
                            inputs=regime.inputs, validity=regime.validity)
    pred = ctx.evaluate(X[rows][te])
    score = {}
    for amp, ph in pu.HARMONICS.values():
        ok = pred["valid"] & np.isfinite(sub[amp][te])
        score[amp] = nrmse(sub[amp][te][ok], pred[amp][ok])
        e = wrap_phase(sub[ph][te] - pred[ph], 0.0)[ok & strong[ph][te]]
        score[ph] = float(np.sqrt(np.mean(e ** 2)) / np.std(sub[ph][te][ok & strong[ph][te]]))
    info["nrmse_test"] = score
    return out, score, int(rows.size)


def _table(m: Lolimot, bps, inputs: tuple[str, ...], name: str) -> LookupTable | None:
    """The ECU look-up table of one identified map (None: tables are not wanted)."""
    if bps is None:
        return None
    return LookupTable.from_model(m.predict, bps, region=m.in_region, input_names=inputs,
                                  output_name=name)


def table_grid_errors(models: ReferenceModelSet, X: np.ndarray,
                      grids: tuple[tuple[int, int], ...] = ((5, 4), (9, 7), (17, 13), (33, 25))
                      ) -> dict[str, dict[str, float]]:
    """Table-versus-model RMSE of every LOLIMOT map for several ECU grid sizes (equidistant
    breakpoints over the identified range), evaluated at the points X (rows of the models'
    inputs; valid ones only)."""
    out = {}
    for nn, nr in grids:
        row = {}
        for name, m in models.models.items():
            lo, hi = m.input_range
            # the actuator inputs keep their breakpoints (the settings of the command)
            bp = (np.linspace(lo[0], hi[0], nn), np.linspace(lo[1], hi[1], nr),
                  *models.tables[name].breakpoints[2:])
            lut = LookupTable.from_model(m.predict, bp, region=m.in_region)
            row[name] = table_error(m.predict, lut, X)["rmse"]
        out[f"{nn}x{nr}"] = row
    return out
