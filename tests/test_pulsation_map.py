"""Crank-angle pulsation maps: the hat basis, a known map recovered, the diesel's sensor
gains told apart by the pulsation they scale (or not)."""

from __future__ import annotations

import secrets

import numpy as np
import pytest

from fdi_ros.core.discrepancy import discover
from fdi_ros.core.discrepancy.model import baseline_from_dict
from fdi_ros.core.meanvalue import harmonic_basis
from fdi_ros.core.measured import Measured, segments_from_gaps
from fdi_ros.core.residualset import PulsationMapModel, ResidualSet


def test_hats_interpolate_linearly_between_knots():
    """The hats are a partition of unity, and a function linear between the knots is
    reproduced exactly by its knot values (the end values hold beyond the range)."""
    rng = np.random.default_rng(secrets.randbelow(2**31))
    knots = int(rng.integers(2, 20))
    nz = rng.uniform(-0.2, 1.2, 500)
    B = harmonic_basis(nz, np.zeros_like(nz), 0, knots)
    np.testing.assert_allclose(B.sum(axis=1), 1.0, atol=1e-12)
    values = rng.normal(size=knots)
    grid = np.linspace(0.0, 1.0, knots)
    np.testing.assert_allclose(B @ values, np.interp(np.clip(nz, 0, 1), grid, values),
                               atol=1e-12)


def _record(seed: int, coef_fn, duration_s: float = 30.0, dalpha: float = 20.0) -> Measured:
    """Crank-resolved record: speed and load wander, p = mean + a known pulsation."""
    rng = np.random.default_rng(seed)
    alpha = np.arange(0.0, duration_s * 6 * 2000.0, dalpha)
    t = alpha / (6 * 2000.0)  # 2000 rpm nominal time base
    n = 2000.0 + 600.0 * np.sin(2 * np.pi * t / rng.uniform(7, 13) + rng.uniform(0, 6))
    load = 150.0 + 60.0 * np.sin(2 * np.pi * t / rng.uniform(4, 9) + rng.uniform(0, 6))
    a, b = coef_fn(n, load)
    p = 1.5e5 + 3e3 * np.sin(2 * np.pi * t / 5.0) + a * np.cos(2 * np.pi * alpha / 180) \
        + b * np.sin(2 * np.pi * alpha / 180)
    return Measured(t=t, signals={"n": n, "maf": load, "p2": p},
                    units={"n": "rpm", "maf": "kg/h", "p2": "Pa"}, alpha=alpha,
                    segment=segments_from_gaps(t, 0.1))


def test_a_known_pulsation_map_is_recovered_and_saved():
    """Coefficient maps linear in the load and smooth in the speed: the fitted map predicts
    a fresh record's pulsation to a small fraction of its amplitude, through a save/load."""
    def coef(n, load):
        return (2000.0 + 8.0 * load) * np.cos(n / 400.0), (1000.0 + 5.0 * load) * np.sin(
            n / 500.0)

    m = PulsationMapModel(channel="p2", n="n", load="maf", orders=(1.0,), harmonic_degree=1,
                          harmonic_knots=24).fit([_record(1, coef), _record(2, coef)])
    fresh = _record(3, coef)
    again = baseline_from_dict(ResidualSet(models=(m,)).to_dict()).models[0]
    for model in (m, again):
        pred = model.predict(fresh)["p2 pulsation"]
        ok = np.isfinite(pred)
        assert ok.mean() > 0.9
        seg = np.floor(fresh.alpha / 180.0).astype(int)
        err = fresh["p2"] - pred
        err = err - (np.bincount(seg[ok], err[ok]) / np.bincount(seg[ok]))[seg]
        a, b = coef(fresh["n"], fresh["maf"])
        assert np.sqrt(np.mean(err[ok] ** 2)) < 0.03 * np.sqrt(np.mean(a ** 2 + b ** 2))


def test_a_pulsation_is_not_mapped_over_itself():
    with pytest.raises(ValueError, match="over itself"):
        PulsationMapModel(channel="p2", load="p2")


def test_without_pulsation_leaves_out_the_pulsation_checks():
    from fdi_ros.plants.diesel import discrepancy_scenarios as sc

    rs = sc.diesel_model_template()
    assert rs.checks == ("p2 pulsation",) and rs.orders == (1.0, 2.0)
    mean = rs.without_pulsation()
    assert mean.channels == ("maf",) and mean.checks == () and mean.orders == ()


@pytest.fixture(scope="module")
def baseline(discrepancy_baseline):
    return discrepancy_baseline


@pytest.mark.parametrize("hidden", ["p2", "T2", "maf"])
def test_sensor_gains_named_on_their_own_sensor(baseline, hidden):
    """A gain of p2 and a reciprocal gain of T2 move the boost density, and so the air-flow
    residual, alike; a MAF gain does nearly the same to it. The pulsations tell the sensors
    apart: a p2 gain scales the boost pressure's pulsation, a MAF gain the air flow's, a T2
    gain neither. The gain is drawn at test time (printed) within the stated detectable range.
    Named on its own sensor; a gain of p2 is named as such with no T2 error beside it. (A T2
    gain and a T2 offset are an honest tie over the few percent T2 moves in a minute, and a
    MAF gain near the detection limit may keep a T2 gain as a tie, a p2 gain within 5 % of 1
    a T2 error. Near the detection limit
    a p2 gain may also be named as the reciprocal MAF gain with the p2 gain tied: both
    pulsations grow with the air flow, so the two gains differ only through eta_V's
    curvature in the boost density; seed 861244395, p2 gain 1.043.)"""
    from fdi_ros.plants.diesel import discrepancy_scenarios as sc

    seed = secrets.randbelow(2**31)
    rng = np.random.default_rng(seed)
    g = float(np.exp(rng.uniform(np.log(1.04), np.log(1.12))))
    g = g if rng.uniform() < 0.5 else 1.0 / g
    print(f"seed {seed}: gain {g:.4f} on {hidden}")
    data = sc.hide(sc.plant_record(int(rng.integers(2000, 10**6)),
                                   profile_seed=int(rng.integers(10**6))),
                   "gain_error", {"gain": g}, channel=hidden)
    res, _ = discover(data, baseline)
    top = res.findings[0]
    tied = {(a["effect"], a.get("channel")) for a in top.alternatives}
    why = (seed, g, top.label, top.channel, sorted(tied))
    if hidden == "p2" and top.channel == "maf":
        assert top.effect == "gain_error" and ("gain_error", "p2") in tied, why
        return
    assert top.channel == hidden, why
    assert top.effect == "gain_error" or ("gain_error", hidden) in tied, why
    if top.effect == "gain_error":
        assert top.params["gain"] == pytest.approx(g, rel=0.3 * abs(g - 1.0)), why
    if hidden == "p2":
        # near the detection limit the p2 pulsation, the one relation that tells a p2 gain
        # from a T2 error, gains little: the T2 error may stay as a tie there (seed
        # 968141719, p2 gain 1.044: held-out gain 89.1 % against 90.5 %, reported as a tie
        # with that measurement to separate them)
        assert top.effect == "gain_error", why
        assert abs(np.log(g)) < np.log(1.05) or not any(c == "T2" for _, c in tied), why


def test_mean_value_data_analysed_with_a_pulsating_baseline(baseline):
    """Data without a crank angle (e.g. 20 Hz logger means) against the diesel baseline,
    whose relations predict pulsations: the mean-value relation is compared (the analysis
    used to refuse such data), and a MAF gain drawn at test time is found: named, or tied
    with the top finding at its size (without the pulsations a MAF gain and a T2 error move
    the mean-value relation alike: an honest tie, as the self-test counts it)."""
    from fdi_ros.core.measured import segment_means
    from fdi_ros.plants.diesel import discrepancy_scenarios as sc

    seed = secrets.randbelow(2**31)
    rng = np.random.default_rng(seed)
    g = float(np.exp(rng.uniform(np.log(1.04), np.log(1.12))))
    g = g if rng.uniform() < 0.5 else 1.0 / g
    data = segment_means(sc.hide(sc.plant_record(int(rng.integers(2000, 10**6)),
                                                 profile_seed=int(rng.integers(10**6))),
                                 "gain_error", {"gain": g}, channel="maf"))
    assert data.alpha is None
    res, ext = discover(data, baseline)
    top = res.findings[0]
    gains = [f["params"]["gain"] for f in [top.__dict__] + top.alternatives
             if f["effect"] == "gain_error" and f["channel"] == "maf"]
    why = (seed, g, top.label, [a["label"] for a in top.alternatives])
    assert gains, why
    assert gains[0] == pytest.approx(g, rel=0.3 * abs(g - 1.0)), why
    assert ext.baseline is baseline  # the extended model keeps the pulsations for crank data
