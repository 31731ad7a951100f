"""Crank-synchronous front end: oracles, a slow reference, streaming, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from fdi_ros.core.crank import (
    FEATURE_NAMES,
    CrankSegmenter,
    crank_harmonics,
    segment_features,
    segment_rates,
    segment_table,
)
from fdi_ros.core.types import SampleBlock

# The core knows no engine: these tests give one (a 2 L four-cylinder four-stroke, air).
ENGINE = {"segment_deg": 180.0, "V_D": 2.0e-3, "R": 287.0}
CH = ("n", "p2", "T2", "maf")
UN = ("rpm", "Pa", "K", "kg/h")


def _block(alpha, t, maf, p2, n=None, T2=None, units=UN):
    N = alpha.size
    n = np.full(N, 2000.0) if n is None else n
    T2 = np.full(N, 320.0) if T2 is None else T2
    return SampleBlock(plant="diesel", index=0, t=np.asarray(t, float), alpha=alpha,
                       channels=CH, units=units, values=np.vstack([n, p2, T2, maf]))


def _sig(alpha, mean, amp, phase_deg, extra=()):
    """mean + amp cos(2 pi a/180 + phi) + sum a_k cos(k 2 pi a/180 + p_k); phases in deg CA."""
    th = 2 * np.pi * alpha / 180.0
    x = mean + amp * np.cos(th + np.radians(2.0 * phase_deg))
    for k, a, p in extra:
        x = x + a * np.cos(k * th + p)
    return x


def _cdiff(x, y):
    return (x - y + 90.0) % 180.0 - 90.0


@pytest.mark.parametrize("phase", [-90.0, -89.5, -31.0, 0.0, 12.25, 45.0, 89.9])
def test_known_amplitude_and_phase_constant_speed(phase):
    # oracle: 1 deg CA sampling at constant speed, 2nd and 3rd orders present
    a = np.arange(0.0, 1800.0 + 1)
    t = a / (6 * 2000.0)
    maf = _sig(a, 165.0, 21.5, phase, extra=[(2, 4.0, 0.3), (3, 1.5, -2.0)])
    p2 = _sig(a, 1.5e5, 4000.0, -phase / 2, extra=[(2, 300.0, 1.0)])
    fv = segment_features(_block(a, t, maf, p2), **ENGINE)
    assert len(fv) == 10
    for f in fv:
        assert f.valid and f.status == "ok" and f.names[:10] == FEATURE_NAMES
        assert abs(f.get("maf") - 165.0) < 1e-9
        assert abs(f.get("maf_amp") - 21.5) < 1e-9
        # circular difference: -90 and +90 deg CA are the same phase
        assert abs(_cdiff(f.get("maf_phase"), phase)) < 1e-9
        assert abs(f.get("p2_amp") - 4000.0) < 1e-9 * 4000
        assert abs(_cdiff(f.get("p2_phase"), -phase / 2)) < 1e-9
        assert -90.0 <= f.get("maf_phase") < 90.0
        assert f.t_end - f.t_start == pytest.approx(180 / 12000.0, rel=1e-12)


def test_segment_boundaries_between_samples_are_exact():
    # samples at 0.5, 1.5, ... deg CA: the segment cells are whole samples (rectangle rule)
    a = np.arange(0.5, 1000.0)
    maf = _sig(a, 100.0, 10.0, 20.0, extra=[(2, 2.0, 0.0)])
    f = segment_features(_block(a, a / 12000, maf, maf * 1000), **ENGINE)
    assert len(f) == 4 and f[0].alpha_start == 180.0
    for x in f:
        assert abs(x.get("maf_amp") - 10.0) < 1e-9 and abs(x.get("maf_phase") - 20.0) < 1e-9


def test_nonuniform_sampling_in_span_is_exact_and_ramp_within_tolerance():
    # samples equidistant in TIME during a speed ramp 1000 -> 6000 rpm: non-uniform in alpha
    tt = np.linspace(0.0, 0.2, 20001)
    a = 6.0 * (1000.0 * tt + 0.5 * 25000.0 * tt ** 2)          # n = 1000 + 25000 t rpm
    n = 1000.0 + 25000.0 * tt
    maf = _sig(a, 165.0, 20.0, 30.0, extra=[(2, 3.0, 0.5)])
    f = segment_features(_block(a, tt, maf, maf * 1e3, n=n), **ENGINE)
    assert len(f) == 23
    # a mean + harmonics <= 3 signal lies in the fitted span: exact for any sampling
    assert max(abs(x.get("maf_amp") - 20.0) for x in f) < 1e-9
    assert max(abs(x.get("maf_phase") - 30.0) for x in f) < 1e-9
    # amplitude that grows with speed during a steep but realistic ramp (5000 rpm/s). Stated
    # tolerance against the amplitude at the segment's mid angle: 0.5 % of A, 0.1 deg CA,
    # speed 0.1 %
    tt = np.linspace(0.0, 0.4, 40001)
    n = 1000.0 + 5000.0 * tt
    a = 6.0 * (1000.0 * tt + 2500.0 * tt ** 2)
    amp = 5.0 + 0.004 * n
    maf2 = 150.0 + amp * np.cos(2 * np.pi * a / 180.0 + np.radians(60.0))
    f2 = segment_features(_block(a, tt, maf2, maf2 * 1e3, n=n), **ENGINE)
    assert len(f2) == 26
    for x in f2:
        n_mid = np.interp(x.alpha_start + 90.0, a, n)
        assert abs(x.get("maf_amp") - (5.0 + 0.004 * n_mid)) < 5e-3 * (5.0 + 0.004 * n_mid)
        assert abs(x.get("maf_phase") - 30.0) < 0.1
        assert abs(x.get("n") - n_mid) < 1e-3 * n_mid


def _slow_reference(alpha, x, D=180.0):
    """Obviously-correct per-segment trapezoid Fourier integrals (uniform grid on boundaries)."""
    out = []
    for j in range(int(alpha[0] // D), int(alpha[-1] // D)):
        m = (alpha >= j * D) & (alpha <= (j + 1) * D)
        a, v = alpha[m], x[m]
        th = 2 * np.pi * a / D
        mean = np.trapezoid(v, a) / D
        c = 2 * np.trapezoid(v * np.cos(th), a) / D
        s = 2 * np.trapezoid(v * np.sin(th), a) / D
        out.append((mean, np.hypot(c, s), np.degrees(np.arctan2(-s, c)) / 2))
    return np.array(out)


def test_fast_path_matches_slow_reference_on_noisy_signal():
    rng = np.random.default_rng(4)
    a = np.arange(0.0, 3600.0 + 1)
    maf = _sig(a, 165.0, 20.0, -40.0) + rng.normal(0, 2.0, a.size) + 0.01 * a
    ref = _slow_reference(a, maf)
    tab = segment_table(_block(a, a / 12000, maf, maf), **ENGINE)
    assert np.allclose(tab.column("maf"), ref[:, 0], atol=1e-9)
    assert np.allclose(tab.column("maf_amp"), ref[:, 1], atol=1e-9)
    assert np.allclose(tab.column("maf_phase"), ref[:, 2], atol=1e-7)


def test_streaming_equals_batch_for_any_block_split():
    rng = np.random.default_rng(1)
    a = np.arange(0.0, 5000.0)
    maf = _sig(a, 165.0, 20.0, 10.0) + rng.normal(0, 1.0, a.size)
    p2 = _sig(a, 1.5e5, 3000.0, 50.0) + rng.normal(0, 50.0, a.size)
    batch = segment_table(_block(a, a / 12000, maf, p2), **ENGINE)
    cuts = np.sort(rng.choice(np.arange(1, a.size - 1), size=25, replace=False))
    seg = CrankSegmenter(**ENGINE)
    got = []
    for lo, hi in zip(np.r_[0, cuts], np.r_[cuts, a.size]):
        got += seg.push(_block(a[lo:hi], a[lo:hi] / 12000, maf[lo:hi], p2[lo:hi]))
    assert len(got) == batch.index.size
    vals = np.array([g.values for g in got])
    assert np.allclose(vals, batch.values, rtol=1e-12, atol=1e-9)
    assert [g.index for g in got] == list(batch.index)


@pytest.mark.parametrize("seed", range(4))
def test_rate_features_are_backward_differences_carried_across_blocks(seed):
    """``<ch>_rate``: the difference of the segment means over ``rate_lag`` consecutive valid
    segments divided by their time apart; any block split gives the same; an invalid segment
    (here a NaN sample) restarts the history: NaN for the next ``rate_lag`` segments."""
    rng = np.random.default_rng(seed)
    lag = int(rng.integers(1, 6))
    a = np.arange(0.0, 180.0 * 40)
    t = a / 12000.0
    T2 = 320.0 + 30.0 * np.sin(2 * np.pi * t / 0.3)          # a slow sensor signal
    maf = _sig(a, 165.0, 20.0, 10.0)
    bad_seg = int(rng.integers(12, 25))
    maf[bad_seg * 180 + 50] = np.nan
    seg_kw = {**ENGINE, "rate_channels": ("T2",), "rate_lag": lag}
    whole = CrankSegmenter(**seg_kw).push_table(_block(a, t, maf, maf * 1e3, T2=T2))
    j = whole.names.index("T2_rate")
    assert whole.units[j] == "K/s"
    means, ends, ok = whole.column("T2"), whole.t_end, whole.valid
    for k in range(whole.index.size):
        window = range(k - lag, k + 1)
        if k >= lag and all(ok[i] for i in window):
            want = (means[k] - means[k - lag]) / (ends[k] - ends[k - lag])
            assert whole.values[k, j] == pytest.approx(want, rel=1e-12)
        else:
            assert np.isnan(whole.values[k, j])
    assert np.isnan(whole.values[bad_seg + 1: bad_seg + 1 + lag, j]).all()
    assert np.isfinite(whole.values[bad_seg + 1 + lag, j])
    seg = CrankSegmenter(**seg_kw)
    cuts = np.sort(rng.choice(np.arange(1, a.size - 1), size=30, replace=False))
    got = []
    for lo, hi in zip(np.r_[0, cuts], np.r_[cuts, a.size]):
        got += seg.push(_block(a[lo:hi], t[lo:hi], maf[lo:hi], maf[lo:hi] * 1e3, T2=T2[lo:hi]))
    np.testing.assert_allclose([g.values[j] for g in got], whole.values[:, j], rtol=1e-10,
                               atol=1e-8)
    with pytest.raises(ValueError, match="rate channels"):
        CrankSegmenter(**{**seg_kw, "rate_channels": ("egt",)}).push_table(
            _block(a, t, maf, maf * 1e3, T2=T2))
    # an optional rate channel the blocks lack: no rate for it, the others as before
    opt = CrankSegmenter(**{**seg_kw, "rate_channels": ("T2", "egt"),
                            "rate_optional": ("egt",)}).push_table(
        _block(a, t, maf, maf * 1e3, T2=T2))
    assert "egt_rate" not in opt.names
    np.testing.assert_array_equal(opt.column("T2_rate"), whole.column("T2_rate"))


@pytest.mark.parametrize("seed", range(4))
def test_quadratic_rate_is_exact_for_a_parabola_and_follows_a_lag_without_delay(seed):
    """``rate_order`` 2: the end-point slope of the least-squares quadratic over the window.
    Oracles: on segment means that are a parabola of the (irregular) end times it is the
    parabola's slope at the end, exactly; on a first-order sensor's step response (time
    constant tau) ``x + tau rate`` gives back the step an order of magnitude better than the
    backward difference, whose slope lags by half the window; any block split gives the same;
    lag < 2 is refused."""
    rng = np.random.default_rng(seed)
    lag = int(rng.integers(2, 10))
    n = 60
    t = np.cumsum(rng.uniform(0.01, 0.03, n))
    c = rng.normal(size=3) * (1.0, 30.0, 200.0)
    x = c[0] + c[1] * t + c[2] * t ** 2
    ok = np.ones(n, dtype=bool)
    got = segment_rates(np.arange(n), t, ok, x, lag, order=2)
    want = c[1] + 2.0 * c[2] * t
    assert np.isnan(got[:lag]).all()
    np.testing.assert_allclose(got[lag:], want[lag:], rtol=1e-7, atol=1e-7 * abs(c[1]))
    # a slow sensor's response to a temperature step at t_s (means sampled at segment ends)
    tau, step, t_s = float(rng.uniform(0.4, 1.2)), float(rng.uniform(20.0, 100.0)), 0.3
    t = np.arange(1, 200) * float(rng.uniform(0.01, 0.02))
    sensor = 320.0 + step * (1.0 - np.exp(-np.maximum(t - t_s, 0.0) / tau))
    after = t > t_s + (lag + 2) * 0.02      # the window is past the step's kink
    errs = {}
    for order in (1, 2):
        r = segment_rates(np.arange(t.size), t, np.ones(t.size, bool), sensor, lag, order)
        errs[order] = np.max(np.abs(sensor + tau * r - (320.0 + step))[after])
    assert errs[2] < 0.1 * errs[1] and errs[2] < 0.01 * step
    with pytest.raises(ValueError, match="rate order"):
        segment_rates(np.arange(n), t[:n], ok, x, 1, order=2)
    # carried across blocks like the backward difference
    a = np.arange(0.0, 180.0 * 30)
    ta = a / 12000.0
    T2 = 320.0 + 30.0 * np.sin(2 * np.pi * ta / 0.3)
    maf = _sig(a, 165.0, 20.0, 10.0)
    seg_kw = {**ENGINE, "rate_channels": ("T2",), "rate_lag": lag, "rate_order": 2}
    whole = CrankSegmenter(**seg_kw).push_table(_block(a, ta, maf, maf * 1e3, T2=T2))
    seg = CrankSegmenter(**seg_kw)
    cuts = np.sort(rng.choice(np.arange(1, a.size - 1), size=20, replace=False))
    parts = []
    for lo, hi in zip(np.r_[0, cuts], np.r_[cuts, a.size]):
        parts += seg.push(_block(a[lo:hi], ta[lo:hi], maf[lo:hi], maf[lo:hi] * 1e3,
                                 T2=T2[lo:hi]))
    j = whole.names.index("T2_rate")
    np.testing.assert_allclose([g.values[j] for g in parts], whole.values[:, j], rtol=1e-9,
                               atol=1e-7)
    with pytest.raises(ValueError, match="rate order"):
        CrankSegmenter(**{**seg_kw, "rate_lag": 1})


def test_eta_v_and_density_formula():
    a = np.arange(0.0, 721.0)
    maf = np.full(a.size, 165.0)
    f = segment_features(_block(a, a / 12000, maf, np.full(a.size, 1.5e5)), **ENGINE)[0]
    rho2 = 1.5e5 / (287.0 * 320.0)
    m_th = 0.5 * 2000.0 / 60.0 * 2.0e-3 * rho2 * 3600.0        # kg/h
    assert f.get("rho2") == pytest.approx(rho2, rel=1e-12)
    assert f.get("eta_v") == pytest.approx(165.0 / m_th, rel=1e-12)
    assert f.get("maf_amp") < 1e-9


def test_nan_and_gap_make_only_their_segments_invalid():
    a = np.arange(0.0, 1081.0)
    maf = _sig(a, 165.0, 20.0, 10.0)
    maf[200] = np.nan                     # segment 1 (180..360)
    keep = (a < 700) | (a > 712)          # 12 deg CA hole inside segment 3 (540..720)
    b = _block(a[keep], a[keep] / 12000, maf[keep], maf[keep] * 1e3)
    f = segment_features(b, **ENGINE)
    st = {x.index: (x.valid, x.status) for x in f}
    assert st[1] == (False, "nan") and st[3] == (False, "gap")
    assert st[0][0] and st[2][0] and st[4][0]
    bad = [x for x in f if not x.valid]
    assert all(np.all(np.isnan(x.values)) for x in bad)


def test_one_missing_sample_is_a_gap_and_smooth_nonuniform_sampling_is_not():
    a = np.arange(0.0, 721.0)
    x = _sig(a, 165.0, 20.0, 10.0)
    keep = a != 400.0                     # one sample lost in segment 2 (360..540)
    f = segment_features(_block(a[keep], a[keep] / 12000, x[keep], x[keep]), **ENGINE)
    assert [(g.index, g.valid, g.status) for g in f] == [(0, True, "ok"), (1, True, "ok"),
                                                         (2, False, "gap"), (3, True, "ok")]
    # the same loss across a block boundary of the streaming segmenter
    seg = CrankSegmenter(**ENGINE)
    out = seg.push(_block(a[:400], a[:400] / 12000, x[:400], x[:400]))
    out += seg.push(_block(a[401:], a[401:] / 12000, x[401:], x[401:]))
    assert [g.status for g in out] == ["ok", "ok", "gap", "ok"]
    # equidistant in time over 1000 -> 6000 rpm: steps grow 6-fold, smoothly: no gap
    tt = np.linspace(0.0, 0.2, 20001)
    aa = 6.0 * (1000.0 * tt + 12500.0 * tt ** 2)
    xx = _sig(aa, 165.0, 20.0, 10.0)
    assert all(g.valid for g in segment_features(_block(aa, tt, xx, xx), **ENGINE))


def test_unsorted_duplicate_and_overlapping_blocks_raise():
    a = np.arange(0.0, 400.0)
    maf = np.full(a.size, 1.0)
    dup = a.copy()
    dup[50] = dup[49]
    with pytest.raises(ValueError, match="duplicate"):
        segment_features(_block(dup, a, maf, maf), **ENGINE)
    uns = a.copy()
    uns[[10, 11]] = uns[[11, 10]]
    with pytest.raises(ValueError, match="decreasing"):
        segment_features(_block(uns, a, maf, maf), **ENGINE)
    seg = CrankSegmenter(**ENGINE)
    assert [x.index for x in seg.push(_block(a[:200], a[:200], maf[:200], maf[:200]))] == [0]
    with pytest.raises(ValueError, match="not after"):
        seg.push(_block(a[150:300], a[150:300], maf[150:300], maf[150:300]))
    # the state is unchanged: the proper continuation still works
    out = seg.push(_block(a[200:], a[200:], maf[200:], maf[200:]))
    assert [x.index for x in out] == [1] and all(x.valid for x in out)


def test_wrong_units_or_missing_channels_raise():
    a = np.arange(0.0, 400.0)
    x = np.ones(a.size)
    with pytest.raises(ValueError, match="kg/h"):
        segment_features(_block(a, a, x, x, units=("rpm", "Pa", "K", "g/s")), **ENGINE)
    with pytest.raises(ValueError, match="Pa"):
        segment_features(_block(a, a, x, x, units=("rpm", "bar", "K", "kg/h")), **ENGINE)
    b = SampleBlock(plant="diesel", index=0, t=a, alpha=a, channels=("n", "maf"),
                    units=("rpm", "kg/h"), values=np.vstack([x, x]))
    with pytest.raises(ValueError, match="missing"):
        segment_features(b, **ENGINE)


def test_too_short_or_empty_input_gives_no_segment():
    a = np.arange(10.0, 150.0)
    assert segment_features(_block(a, a, np.ones(a.size), np.ones(a.size)), **ENGINE) == []
    h, nxt = crank_harmonics(np.array([0.0]), None, np.ones((1, 1)), segment_deg=180.0)
    assert h.index.size == 0 and nxt == 0


def test_the_engine_is_given_not_assumed():
    """No engine constants in the core: a six-cylinder four-stroke (one firing = 120 deg CA,
    3 L) is segmented by the same code, with its own eta_v."""
    with pytest.raises(TypeError):
        CrankSegmenter()
    six = {"segment_deg": 120.0, "V_D": 3.0e-3, "R": 287.0}
    a = np.arange(0.0, 1200.0 + 1)
    th = 2 * np.pi * a / 120.0
    maf = 240.0 + 18.0 * np.cos(th + 0.5)
    f = segment_features(_block(a, a / 12000, maf, np.full(a.size, 1.5e5)), **six)
    assert len(f) == 10 and all(g.valid for g in f)
    g = f[3]
    assert g.get("maf_amp") == pytest.approx(18.0, rel=1e-9)
    # phi = -a_max in deg CA of the 120 deg period: maximum at th = -0.5 rad
    assert g.get("maf_phase") == pytest.approx(np.degrees(0.5) * 120.0 / 360.0, abs=1e-9)
    rho2 = 1.5e5 / (287.0 * 320.0)
    assert g.get("eta_v") == pytest.approx((240.0 / 3600.0) / (2000.0 / 120.0 * 3.0e-3 * rho2))
