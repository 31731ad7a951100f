"""What an effect sees of one channel: measured values, baseline prediction, explanations.

A :class:`ChannelContext` is built from a :class:`~fdi_ros.core.measured.Measured` record and a
baseline model. It holds everything a catalogue effect may regress on: time, segments, crank
angle, the candidate explanation columns (measured signals the model does not use, and smoothed
time derivatives of all measured signals), the operating-region coordinates of the model
(axes of the error map), and the leak regressor (compressible orifice flow per unit area).
"""

from __future__ import annotations

from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fdi_ros.core.constants import R_AIR
from fdi_ros.core.measured import Measured

KAPPA_AIR = 1.4
MAX_RESPONSES = 96  # exact sensor-error predictions kept per context (memory bound)


@dataclass(frozen=True)
class LeakSpec:
    """Where a leak between the measured flow channel and the surroundings would sit.

    The flow channel is metered upstream of the leak, the model predicts the flow the engine
    takes in; a leak then changes the metered flow by the flow through the orifice:
    ``y = yhat - CdA * q(p_amb -> p_in)``, q > 0 into the system (a throttled gasoline manifold
    sucks air in; a boosted diesel charge-air path blows air out, q < 0).

    Attributes
    ----------
    channel : the flow channel (e.g. "maf").
    p_in, T_in : signal names of the pressure [Pa] and temperature [K] inside, at the leak.
    p_amb, T_amb : signal name or constant of the surroundings [Pa], [K].
    flow_scale : channel units per kg/s (3600 for kg/h).
    cd : discharge coefficient used to turn the effective area Cd*A into a geometric area.
    """

    channel: str
    p_in: str
    T_in: str
    p_amb: str | float = 101325.0
    T_amb: str | float = 293.15
    flow_scale: float = 1.0
    cd: float = 0.7

    def to_dict(self) -> dict[str, Any]:
        return dict(channel=self.channel, p_in=self.p_in, T_in=self.T_in, p_amb=self.p_amb,
                    T_amb=self.T_amb, flow_scale=self.flow_scale, cd=self.cd)


def orifice_flux(p_up: np.ndarray, T_up: np.ndarray, p_down: np.ndarray,
                 kappa: float = KAPPA_AIR) -> np.ndarray:
    """Isentropic mass flux through a unit-area orifice [kg/(s m^2)], p_up >= p_down.

    ``q = p_up / sqrt(R T_up) * Psi(p_down / p_up)`` with
    ``Psi(pr) = sqrt(2 kappa / (kappa - 1) * (pr^(2/kappa) - pr^((kappa+1)/kappa)))``,
    held at its critical value below the choking ratio ``(2/(kappa+1))^(kappa/(kappa-1))``.
    """
    pr_crit = (2.0 / (kappa + 1.0)) ** (kappa / (kappa - 1.0))
    with np.errstate(invalid="ignore", divide="ignore"):  # NaN where T or p is not physical
        pr = np.clip(p_down / p_up, pr_crit, 1.0)
        psi = np.sqrt(np.maximum(2.0 * kappa / (kappa - 1.0)
                                 * (pr ** (2.0 / kappa) - pr ** ((kappa + 1.0) / kappa)), 0.0))
        return np.asarray(p_up / np.sqrt(R_AIR * T_up) * psi, float)


def leak_regressor(data: Measured, spec: LeakSpec) -> np.ndarray:
    """Signed orifice flux from the surroundings into the system [kg/(s m^2)] per sample."""

    def sig(v: str | float) -> np.ndarray:
        if isinstance(v, str):
            return np.asarray(data[v], dtype=float)
        return np.full(data.n_samples, float(v))

    p_in, T_in, p_a, T_a = sig(spec.p_in), sig(spec.T_in), sig(spec.p_amb), sig(spec.T_amb)
    inflow = p_a >= p_in
    q = np.where(inflow, orifice_flux(p_a, T_a, p_in), -orifice_flux(p_in, T_in, p_a))
    return q


_DERIVATIVES: OrderedDict[tuple[int, int, int, float], tuple[Any, ...]] = OrderedDict()


def smooth_derivative(x: np.ndarray, t: np.ndarray, segment: np.ndarray,
                      window_s: float) -> np.ndarray:
    """d x / d t per segment after a centred moving average of about ``window_s``.

    NaN samples stay NaN (and make their neighbourhood NaN): a derivative across a missing
    sample would be a guess. Near the segment ends the window is shortened. The last few
    results are remembered for the very same arrays (a model re-run with one input changed
    differentiates the others again).
    """
    key = (id(x), id(t), id(segment), float(window_s))
    hit = _DERIVATIVES.get(key)
    if hit is not None and hit[0] is x and hit[1] is t and hit[2] is segment:
        _DERIVATIVES.move_to_end(key)
        kept: np.ndarray = hit[3]
        return kept
    out = _smooth_derivative(x, t, segment, window_s)
    _DERIVATIVES[key] = (x, t, segment, out)
    while len(_DERIVATIVES) > 32:
        _DERIVATIVES.popitem(last=False)
    return out


def _smooth_derivative(x: np.ndarray, t: np.ndarray, segment: np.ndarray,
                       window_s: float) -> np.ndarray:
    out = np.full_like(x, np.nan, dtype=float)
    for s in np.unique(segment):
        idx = np.flatnonzero(segment == s)
        if idx.size < 3:
            continue
        ts, xs = t[idx], x[idx]
        dt = float(np.median(np.diff(ts)))
        w = max(1, int(round(window_s / dt)))
        if w > 1 and idx.size > w:
            k = np.ones(w)
            # at the ends the window is cut short: average over the samples it holds (an
            # on-line residual needs the derivative at the newest sample)
            xs = np.convolve(xs, k, mode="same") / np.convolve(np.ones(idx.size), k, mode="same")
        out[idx] = np.gradient(xs, ts)
    return out


@dataclass
class ChannelContext:
    """Inputs of the effect fits for one channel (see the module docstring)."""

    channel: str
    unit: str
    t: np.ndarray
    y: np.ndarray
    yhat: np.ndarray
    segment: np.ndarray
    columns: dict[str, np.ndarray] = field(default_factory=dict)
    region: dict[str, np.ndarray] = field(default_factory=dict)
    alpha: np.ndarray | None = None
    leak_q: np.ndarray | None = None
    leak: LeakSpec | None = None
    t_ref: float = 0.0
    cache: dict[Any, Any] = field(default_factory=dict, repr=False)
    # left-out index intervals of the folds (i0, i1, fold)
    folds: tuple[np.ndarray, np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    fold_ids: dict[int, int] = field(default_factory=dict, repr=False)    # id(train mask) -> fold
    sensors: tuple[str, ...] = ()  # input sensors whose errors are candidate explanations
    source: Any = field(default=None, repr=False)  # (data, model) behind ``sensor_response``
    responses: dict[Any, np.ndarray] = field(default_factory=dict, repr=False)
    # the measured signal this residual compares with its model ("" = ``channel`` itself) and
    # the signals the model reads: an error of one of them moves this residual
    measured: str = ""
    uses: tuple[str, ...] = ()
    # errors judged with the mean of every 180 deg CA segment removed (the pulsation view of
    # crank-resolved data); ``pulse`` holds the segment index of every sample
    pulse: np.ndarray | None = field(default=None, repr=False)
    quantum: float = 0.0  # relative step of the lag and dead-time values the model is re-run at
    _errors: deque[Any] = field(default_factory=deque, repr=False)  # kept exact responses

    @property
    def signal(self) -> str:
        """The measured signal of this residual."""
        return self.measured or self.channel

    def pulsation(self, x: np.ndarray) -> np.ndarray:
        """``x`` minus its mean over each 180 deg CA segment (``x`` itself without
        ``pulse``); NaN samples do not count and stay NaN."""
        if self.pulse is None:
            return x
        ok = np.isfinite(x)
        s = np.bincount(self.pulse[ok], weights=x[ok], minlength=int(self.pulse.max()) + 1)
        c = np.bincount(self.pulse[ok], minlength=s.size)
        return np.asarray(x - (s / np.maximum(c, 1))[self.pulse], float)

    def sensor_lag_response(self, sensor: str, tau_s: float) -> np.ndarray:
        """``yhat(x + tau dx/dt) - yhat(x)``: the prediction from the reading of ``sensor``
        with a first-order lag tau undone (the truth of a lagged reading is the reading plus
        tau times its slope), minus the prediction. The slope is taken over a window of tau
        (at least 0.05 s): undoing a lag amplifies what is faster than it. Cached per tau."""
        return self._corrected(sensor, "lag", tau_s)

    def sensor_shift_response(self, sensor: str, delay_s: float) -> np.ndarray:
        """``yhat(x(t + d)) - yhat(x(t))``: the prediction from the reading of ``sensor``
        advanced by ``delay_s`` (per segment, linear interpolation), minus the prediction: a
        reading that trails the truth by a dead time d is undone by the advance, computed
        exactly (no derivative of a noisy reading). Cached per delay."""
        return self._corrected(sensor, "shift", delay_s)

    def _corrected(self, sensor: str, how: str, v: float) -> np.ndarray:
        if self.quantum > 0 and v > 0:
            # a view that only checks: values within a fraction ``quantum`` of each other
            # (the folds' fits) share one re-run of the model
            v = float(np.exp(np.round(np.log(v) / self.quantum) * self.quantum))
        key = (sensor, how, round(float(v), 9))
        if key not in self.responses:
            if self.source is None:
                raise ValueError(f"no model behind channel {self.channel}")
            data, model = self.source
            if how == "lag":
                x = self.sensor_reading(sensor)
                fixed = x + v * smooth_derivative(x, data.t, data.segment, max(float(v), 0.05))
            else:
                fixed = self.sensor_reading(sensor, v)
            pred = model.predict(_replaced(data, sensor, fixed))[self.channel]
            self.responses[key] = np.asarray(pred, float) - self.sensor_base()
        return self.responses[key]

    def sensor_reading(self, sensor: str, advance_s: float = 0.0) -> np.ndarray:
        """The reading of an input sensor, advanced by ``advance_s`` (per segment, linear
        interpolation; 0: as measured)."""
        if self.source is None:
            raise ValueError(f"no data behind channel {self.channel}")
        data = self.source[0]
        x = np.asarray(data[sensor], float)
        if advance_s == 0.0:
            return x
        adv = np.empty_like(x)
        seg = np.asarray(data.segment)
        cuts = np.flatnonzero(np.diff(seg)) + 1
        for a, b in zip(np.r_[0, cuts], np.r_[cuts, x.size]):
            ts, xs = data.t[a:b], x[a:b]
            okx = np.isfinite(xs)
            adv[a:b] = (np.interp(ts + advance_s, ts[okx], xs[okx]) if okx.sum() > 1
                        else np.nan)
        return adv

    def sensor_base(self) -> np.ndarray:
        """The model's own prediction of this channel (before any extension)."""
        if "base" not in self.responses:
            data, model = self.source
            self.responses["base"] = np.asarray(model.predict(data)[self.channel], float)
        return self.responses["base"]

    def sensor_error_response(self, sensor: str, kind: str, value: float,
                              onset_s: float | None = None, column: str = "", *,
                              keep: bool = True) -> np.ndarray:
        """``yhat(x_true) - yhat(x)``: the prediction from the reading ``x`` of ``sensor`` with
        an error of ``kind`` and size ``value`` removed (from ``onset_s`` on), the model re-run
        exactly, minus the prediction. Kinds: ``offset`` (x - value), ``gain_error``
        (x / value), ``drift`` (x - value (t - t_ref)), ``input_dependence`` (x - value z, z
        the measured ``column`` standardised). Cached per value (``keep``), at most
        ``MAX_RESPONSES`` of them; views with a ``quantum`` round the value (gains: their
        departure from 1) to that relative step and the onset to 0.1 s."""
        if self.source is None:
            raise ValueError(f"no model behind channel {self.channel}")
        v, on = float(value), onset_s
        if self.quantum > 0:
            d = v - 1.0 if kind == "gain_error" else v
            if d != 0.0:
                d = float(np.sign(d) * np.exp(np.round(np.log(abs(d)) / self.quantum)
                                               * self.quantum))
            v = d + 1.0 if kind == "gain_error" else d
            on = None if on is None else round(float(on), 1)
        key = ("error", sensor, kind, round(v, 12), None if on is None else round(on, 6),
               column)
        if key in self.responses:
            kept: np.ndarray = self.responses[key]
            return kept
        data, model = self.source
        x = self.sensor_reading(sensor)
        if kind == "offset":
            xt = x - v
        elif kind == "gain_error":
            xt = x / v
        elif kind == "drift":
            xt = x - v * (data.t - self.t_ref)
        elif kind == "input_dependence":
            z = np.asarray(data[column], float)
            xt = x - v * np.where(np.isfinite(z), (z - np.nanmean(z)) / (np.nanstd(z) or 1.0),
                                  0.0)
        else:
            raise ValueError(f"no exact sensor error of kind {kind!r}")
        if on is not None:
            xt = np.where(data.t >= on, xt, x)
        out: np.ndarray = (np.asarray(model.predict(_replaced(data, sensor, xt))[self.channel],
                                      float) - self.sensor_base())
        if keep:
            self._errors.append(key)
            while len(self._errors) > MAX_RESPONSES:
                self.responses.pop(self._errors.popleft(), None)
            self.responses[key] = out
        return out

    def sensor_response(self, sensor: str, direction: str) -> np.ndarray:
        """How this channel's prediction moves per unit error of an input sensor.

        ``D(d) = (yhat(x + h d) - yhat(x - h d)) / (2 h)`` with the model re-run on the
        perturbed input ``x`` of ``sensor`` (central difference, step small against the
        signal): the directional derivative of the prediction along the sensor error shape
        ``d``. Directions: ``one`` (an offset), ``x`` (a gain: the reading itself),
        ``t`` (a drift: time since ``t_ref``), ``dxdt`` (the reading's slope) and
        ``col:NAME`` (an error that follows the measured column NAME, standardised). Cached
        per context.
        """
        key = (sensor, direction)
        if key in self.responses:
            return self.responses[key]
        if self.source is None:
            raise ValueError(f"no model behind channel {self.channel}: sensor errors of "
                             f"{sensor} cannot be evaluated")
        data, model = self.source
        x = np.asarray(data[sensor], float)
        if direction == "one":
            d = np.ones_like(x)
        elif direction == "x":
            d = x
        elif direction == "t":
            d = data.t - self.t_ref
        elif direction == "dxdt":
            d = smooth_derivative(x, data.t, data.segment, 0.25)
        elif direction.startswith("col:"):
            z = np.asarray(data[direction[4:]], float)
            d = (z - np.nanmean(z)) / (np.nanstd(z) or 1.0)
        else:
            raise ValueError(f"unknown sensor error direction {direction!r}")
        d = np.where(np.isfinite(d), d, 0.0)
        h = 1e-4 * float(np.nanmedian(np.abs(x)) or 1.0) / float(np.sqrt(np.mean(d ** 2)) or 1.0)
        up = model.predict(_replaced(data, sensor, x + h * d))[self.channel]
        dn = model.predict(_replaced(data, sensor, x - h * d))[self.channel]
        out: np.ndarray = (np.asarray(up, float) - np.asarray(dn, float)) / (2.0 * h)
        self.responses[key] = out
        return out

    @property
    def n(self) -> int:
        return int(self.t.shape[0])

    @property
    def ok(self) -> np.ndarray:
        """Samples where both measurement and prediction exist."""
        return np.asarray(np.isfinite(self.y) & np.isfinite(self.yhat))

    @property
    def dt(self) -> float:
        return float(np.median(np.diff(self.t)))


def _model_of(model: Any, channel: str) -> Any:
    """What predicts ``channel``: the member of a set of relations (``model.model_of``), or
    the model itself."""
    pick = getattr(model, "model_of", None)
    return pick(channel) if callable(pick) else model


def _replaced(data: Measured, name: str, x: np.ndarray) -> Measured:
    sig = dict(data.signals)
    sig[name] = x
    return Measured(t=data.t, signals=sig, units=dict(data.units), alpha=data.alpha,
                    segment=data.segment, source=data.source, mapped=data.mapped)


def build_contexts(data: Measured, model: Any, *, derivative_window_s: float = 0.25,
                   t_ref: float | None = None, sensors: bool = False
                   ) -> dict[str, ChannelContext]:
    """One context per channel the model predicts and the data measures.

    ``model`` follows :class:`fdi_ros.core.discrepancy.model.BaselineModel`. Candidate columns
    are the measured signals the model does not use (minus the channel itself) and ``d/dt`` of
    every measured signal (lags and filling dynamics show there). ``sensors``: the model's
    input sensors (and the other predicted channels) become candidate carriers of a sensor
    error, judged by how the error would move this channel's prediction
    (:meth:`ChannelContext.sensor_response`).
    """
    pred = model.predict(data)
    region = model.region(data)
    # a model with several residuals may say which signal each one measures (default: the
    # channel of that name) and which signals each one's model reads (default: all inputs)
    measures = dict(getattr(model, "measures", None) or {})
    uses = dict(getattr(model, "uses", None) or {})
    derivs = {f"d/dt {k}": smooth_derivative(v, data.t, data.segment, derivative_window_s)
              for k, v in data.signals.items() if np.isfinite(v).mean() > 0.5
              and np.nanstd(v) > 0}
    out = {}
    for ch in model.channels:
        sig_name = measures.get(ch, ch)
        if sig_name not in data.signals:
            continue
        reads = tuple(uses.get(ch, model.inputs))
        cols = {k: v for k, v in data.signals.items()
                if k not in reads and k != sig_name and np.isfinite(v).mean() > 0.5
                and np.nanstd(v) > 0}
        cols.update({k: v for k, v in derivs.items() if k != f"d/dt {sig_name}"})
        spec = next((s for s in getattr(model, "leaks", ()) if s.channel == ch), None)
        q = None
        if spec is not None:
            try:
                q = leak_regressor(data, spec) * spec.flow_scale
            except KeyError:
                spec, q = None, None
        readable = tuple(s for s in dict.fromkeys(reads)
                         if s in data.signals and s != sig_name
                         and np.isfinite(data[s]).mean() > 0.5 and np.nanstd(data[s]) > 0)
        out[ch] = ChannelContext(channel=ch, unit=data.units.get(sig_name, ""), t=data.t,
                                 y=np.asarray(data[sig_name], float),
                                 yhat=np.asarray(pred[ch], float),
                                 segment=data.segment, columns=cols, region=region,
                                 alpha=data.alpha, leak_q=q, leak=spec,
                                 t_ref=float(data.t[0] if t_ref is None else t_ref),
                                 sensors=readable if sensors else (),
                                 source=(data, _model_of(model, ch)),
                                 measured=sig_name if sig_name != ch else "", uses=readable)
    if not out:
        raise ValueError(f"the measured data has none of the model's channels {model.channels} "
                         f"(signals: {sorted(data.signals)})")
    return out
