"""The turbofan as a streaming plant for the live graph (its wing: :mod:`.wing`).

:class:`TurbofanRunner` runs a turbofan scenario sample by sample (RK4 at Ts = 0.02 s) and
emits sensor blocks of ``block_samples`` samples with channels ``XN2, XNH, WF36``; faults come
from the scenario and from run-time injections. :class:`TurbofanPreprocessor` turns each
sample into one :class:`FeatureVector` (names ``XNL, XNH, WF36``), the input of the bank's
``turbofan_ts`` residual models.

Fault events: ``fault`` is ``"<type>_<size word>"`` (``"hub_small"``) or a bare type with
``size`` in units of the small fault (``size_unit = "small"``); ``""`` clears every fault;
``active = False`` removes that fault type; ``profile = "ramp"`` grows the size over ``ramp_s``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fdi_ros.core.plant_api import SampledRunner
from fdi_ros.core.supervisor import fault_type
from fdi_ros.core.types import FaultEvent, FeatureVector, SampleBlock, ramp_fraction
from fdi_ros.plants import ROOT
from fdi_ros.plants.turbofan import plant as tfp

DEFAULT_SCENARIO = ROOT / "config" / "turbofan_hub_small_to_large.yaml"
CHANNELS = ("XN2", "XNH", "WF36")
UNITS = ("rpm", "rpm", "kg/s")


def _event_units(ev: FaultEvent) -> tuple[str, float]:
    """(fault type, size in small-fault units) of an injection event."""
    kind = fault_type(ev.fault)
    if ev.fault != kind:
        return kind, tfp.fault_size(kind, ev.fault[len(kind) + 1:])
    return kind, tfp.fault_size(kind, float(ev.size))


class TurbofanRunner(SampledRunner):
    """Streaming turbofan running a scenario file (see ``config/turbofan_*.yaml``)."""

    plant = "turbofan"
    channels = CHANNELS
    units = UNITS

    def __init__(self, scenario: str | Path | dict | None = None, *, seed: int | None = None,
                 block_samples: int = 5, config: str | Path | None = None) -> None:
        import yaml

        from fdi_ros.plants.turbofan.settings import load_scenario, load_settings

        settings = load_settings(config or ROOT / "config" / "turbofan.yaml")
        if isinstance(scenario, dict):
            import tempfile

            with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as fh:
                yaml.safe_dump(scenario, fh)
            sc = load_scenario(fh.name, settings)
            Path(fh.name).unlink()
        else:
            sc = load_scenario(scenario or DEFAULT_SCENARIO, settings)
        if block_samples < 1:
            raise ValueError("block_samples must be >= 1")
        self.scenario = sc
        self.sim = tfp.Turbofan()
        super().__init__(ts=self.sim.k.Ts)
        self._c = np.asarray(sc.condition, dtype=float)
        self._wf = tfp.paper_input(self.sim.scheduled_fuel(self._c), duration_s=sc.duration_s)
        self._base = tfp.Health(manufacturing=sc.manufacturing,
                                deterioration=sc.deterioration).quality()
        self._rng = np.random.default_rng(sc.seed if seed is None else seed)
        self._faults: list[tuple[float, str, float, float]] = []  # (t, type, units, ramp_s)
        for t, faults in sc.events:
            for kind, size in faults.items():
                self.inject(FaultEvent(t=float(t), fault=f"{kind}_{size}" if isinstance(size, str)
                                       else kind, size=float(tfp.fault_size(kind, size)),
                                       size_unit="small"))
        self._x = self.sim.trim(self._wf[0], self._c, self._quality(0.0))
        self._per_block = int(block_samples)

    # -- faults -----------------------------------------------------------------------------------
    def inject(self, event: FaultEvent) -> None:
        if event.fault == "":
            self._faults.append((event.t, "", 0.0, 0.0))
        else:
            kind, units = _event_units(event)
            if not event.active:
                units = 0.0
            ramp = event.ramp_s if event.profile == "ramp" else 0.0
            self._faults.append((event.t, kind, units, ramp))
        self._faults.sort(key=lambda f: f[0])
        self._truth.add(event)

    def _quality(self, t: float) -> np.ndarray:
        sizes: dict[str, float] = {}
        for te, kind, units, ramp in self._faults:
            if t < te:
                break
            if kind == "":
                sizes = {}
                continue
            before = sizes.get(kind, 0.0)
            sizes[kind] = before + ramp_fraction(t, te, ramp) * (units - before)
        p = self._base.copy()
        for kind, units in sizes.items():
            p = p + units * tfp.fault_vector(kind)
        return p

    # -- streaming --------------------------------------------------------------------------------
    @property
    def done(self) -> bool:
        return self._k >= self._wf.size

    def next_block(self) -> SampleBlock:
        if self.done:
            raise ValueError("the turbofan scenario is over")
        n = min(self._per_block, self._wf.size - self._k)
        ts = self.ts
        t = self._times(n)
        vals = np.empty((3, n))
        for j in range(n):
            k = self._k + j
            u = self._wf[k]
            vals[0, j] = self._x[0] + self._rng.normal(0.0, self.sim.k.noise_xnl)
            vals[1, j] = self._x[1] + self._rng.normal(0.0, self.sim.k.noise_xnh)
            vals[2, j] = u
            self._x, _ = self.sim.step(self._x, u, self._c, self._quality(k * ts))
        return self._emit(t, vals)


class TurbofanPreprocessor:
    """One feature vector per sample: (XNL, XNH, WF36); NaN samples are flagged invalid."""

    def __init__(self, **kwargs) -> None:
        if kwargs:
            raise ValueError(f"the turbofan preprocessor takes no options, got {sorted(kwargs)}")
        self._index = 0
        self._gap = False

    def push(self, block: SampleBlock) -> list[FeatureVector]:
        try:
            cols = np.stack([block.channel("XN2"), block.channel("XNH"),
                             block.channel("WF36")])
        except KeyError as exc:
            raise ValueError(f"turbofan block lacks a channel: {exc}") from None
        out = []
        for j, t in enumerate(block.t):
            v = cols[:, j]
            ok = bool(np.all(np.isfinite(v)))
            status = "missing_sample" if not ok else ("after_gap" if self._gap else "ok")
            out.append(FeatureVector(plant="turbofan", index=self._index, t_start=float(t),
                                     t_end=float(t), alpha_start=0.0, valid=ok, status=status,
                                     names=("XNL", "XNH", "WF36"), units=UNITS,
                                     values=v.copy()))
            self._index += 1
            self._gap = False
        return out

    def mark_gap(self) -> None:
        self._gap = True

    def reset(self) -> None:
        self._index = 0
        self._gap = False

