"""Dead time between two signals from the signals themselves: cross-correlation, then the
phase of their cross spectrum for the fraction of a sample.

:func:`estimate_delay` answers "by how much does ``y`` trail ``x``" (``y(t) ~ x(t - d)``), e.g.
a measurement against the model's prediction of it. Both are put on a uniform time grid
(the median sample step; crank-angle sampled data have a step that varies with speed), every
contiguous segment separately. The whole-sample part is the peak of the cross-correlation of
the demeaned signals over the lags allowed; the rest is the slope of the cross-spectrum
phase, ``phi(f) = -2 pi f delta``, fitted by weighted least squares over the frequencies
where the two signals are coherent (weights: the cross-spectrum magnitude). Unlike a parabola
through three correlation values, the phase slope has no bias towards whole samples, so a
dead time comes out to a small fraction of a sample period.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DelayEstimate:
    """Result of :func:`estimate_delay` (``delay_s`` > 0: ``y`` trails ``x``)."""

    delay_s: float
    step_s: float  # the uniform grid's sample period
    peak_corr: float  # normalised cross-correlation at the whole-sample peak
    success: bool
    message: str = ""


def _uniform(t: np.ndarray, x: np.ndarray, segment: np.ndarray, step: float
             ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per segment, ``x`` linearly interpolated onto a grid of period ``step``."""
    out = []
    for s in np.unique(segment):
        idx = np.flatnonzero((segment == s) & np.isfinite(x))
        if idx.size < 8:
            continue
        tg = np.arange(t[idx[0]], t[idx[-1]], step)
        out.append((tg, np.interp(tg, t[idx], x[idx])))
    return out


def estimate_delay(y: np.ndarray, x: np.ndarray, t: np.ndarray, *,
                   segment: np.ndarray | None = None, max_delay_s: float,
                   step_s: float | None = None) -> DelayEstimate:
    """How much ``y`` trails ``x`` (see the module docstring), at most ``max_delay_s`` either
    way. Samples where either is NaN are left out (interpolated over within a segment)."""
    seg = np.zeros(t.shape, int) if segment is None else np.asarray(segment)
    ok = np.isfinite(y) & np.isfinite(x)
    if ok.sum() < 16:
        return DelayEstimate(0.0, 0.0, 0.0, False, "fewer than 16 valid samples")
    step = float(step_s or np.median(np.diff(t[ok])))
    ys = _uniform(t[ok], y[ok], seg[ok], step)
    xs = _uniform(t[ok], x[ok], seg[ok], step)
    max_lag = max(1, int(np.ceil(max_delay_s / step)))
    pairs = [(a[1], b[1]) for a, b in zip(ys, xs) if a[1].size > 2 * max_lag + 8]
    if not pairs:
        return DelayEstimate(0.0, step, 0.0, False, "no segment longer than the lags searched")
    # whole samples: the cross-correlation summed over segments (FFT, zero padded)
    lags = np.arange(-max_lag, max_lag + 1)
    cc = np.zeros(lags.size)
    power = [0.0, 0.0]
    for a, b in pairs:
        a = a - a.mean()
        b = b - b.mean()
        nfft = 1 << int(np.ceil(np.log2(a.size + b.size)))
        full = np.fft.irfft(np.fft.rfft(a, nfft) * np.conj(np.fft.rfft(b, nfft)), nfft)
        cc += full[lags % nfft]  # full[k] = sum_n a[n + k] b[n]: y at n + k against x at n
        power[0] += float(a @ a)
        power[1] += float(b @ b)
    norm = float(np.sqrt(power[0] * power[1])) or 1.0
    k = int(lags[int(np.argmax(cc))])
    # the fraction: phase slope of the cross spectrum of y advanced by k samples against x
    num = den = 0.0
    for a, b in pairs:
        n = a.size - abs(k)
        aa = a[k:k + n] if k >= 0 else a[:n]
        bb = b[:n] if k >= 0 else b[-k:-k + n]
        aa = (aa - aa.mean()) * np.hanning(n)
        bb = (bb - bb.mean()) * np.hanning(n)
        s = np.fft.rfft(aa) * np.conj(np.fft.rfft(bb))
        f = np.fft.rfftfreq(n, step)
        w = np.abs(s)
        band = (f > 0) & (w > 0.05 * w.max())  # coherent frequencies, not the noise floor
        phi = np.angle(s[band])
        ok_ph = np.abs(phi) < 0.5 * np.pi  # within a quarter period: no wrap
        fb, wb, pb = f[band][ok_ph], w[band][ok_ph], phi[ok_ph]
        num += float(np.sum(wb * fb * pb))
        den += float(np.sum(wb * fb * fb))
    frac = -num / (2.0 * np.pi * den) if den > 0 else 0.0
    frac = float(np.clip(frac, -step, step))
    return DelayEstimate(delay_s=k * step + frac, step_s=step,
                         peak_corr=float(cc.max() / norm), success=True)
