"""Takagi-Sugeno systems and their Levenberg-Marquardt fit: oracles and contracts."""

from __future__ import annotations

import numpy as np
import pytest

from fdi_ros.core.tsfuzzy import StackedTS, TakagiSugeno, fit_ts

OFFSET = np.array([10700.0, 14150.0, 0.2])
SCALE = np.array([300.0, 400.0, 0.02])


def _inputs(rng, n=1000):
    return OFFSET + SCALE * rng.uniform(-1.5, 1.5, (n, 3))


def _true_model() -> TakagiSugeno:
    return TakagiSugeno(centers=np.array([-1.0, 0.0, 1.0]), sigmas=np.array([0.5, 0.6, 0.5]),
                        coef=np.array([[10.0, -40.0, 5.0, 80.0],
                                       [0.0, -60.0, 10.0, 100.0],
                                       [-15.0, -90.0, 20.0, 120.0]]),
                        offset=OFFSET, scale=SCALE, premise=0)


def test_analytic_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    x = _inputs(rng, 200)
    model = _true_model().with_theta(_true_model().theta() + rng.normal(0, 0.1, 18))
    jac = model.jacobian(x)
    theta = model.theta()
    fd = np.empty_like(jac)
    for j in range(theta.size):
        h = 1e-6 * max(1.0, abs(theta[j]))
        tp, tm = theta.copy(), theta.copy()
        tp[j] += h
        tm[j] -= h
        fd[:, j] = (model.with_theta(tp)(x) - model.with_theta(tm)(x)) / (2 * h)
    np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


def test_one_rule_equals_affine_least_squares():
    rng = np.random.default_rng(5)
    x = _inputs(rng, 500)
    z = (x - OFFSET) / SCALE
    y = 3.0 + z @ np.array([-50.0, 12.0, 90.0]) + 5.0 * np.sin(z[:, 0] * 2) \
        + rng.normal(0, 1.0, 500)
    res = fit_ts(x, y, n_rules=1, offset=OFFSET, scale=SCALE)
    phi = np.column_stack([np.ones(500), z])
    ls, *_ = np.linalg.lstsq(phi, y, rcond=None)
    np.testing.assert_allclose(res.model.coef[0], ls, rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(res.model(x), phi @ ls, atol=1e-7)


def test_known_consequents_recovered_from_seeded_data():
    rng = np.random.default_rng(11)
    truth = _true_model()
    x = _inputs(rng, 1000)
    y = truth(x) + rng.normal(0.0, 0.5, 1000)
    # start from the true premise and wrong consequents: LM must find the consequents
    init = TakagiSugeno(centers=truth.centers + 0.1, sigmas=truth.sigmas * 1.2,
                        coef=np.zeros_like(truth.coef), offset=OFFSET, scale=SCALE)
    res = fit_ts(x, y, n_rules=3, offset=OFFSET, scale=SCALE, init=init, max_nfev=400)
    assert res.rmse == pytest.approx(0.5, rel=0.1)
    np.testing.assert_allclose(res.model.coef, truth.coef, rtol=0.05, atol=2.5)
    # the premise is only weakly identifiable from the data; the function itself is recovered
    x_new = _inputs(np.random.default_rng(12), 500)
    assert np.max(np.abs(res.model(x_new) - truth(x_new))) < 0.6
    assert res.cost_history[-1] < res.cost_history[0]
    assert res.nfev == len(res.cost_history) and res.time_s > 0


def test_fit_is_deterministic_and_rejects_bad_input():
    rng = np.random.default_rng(2)
    x = _inputs(rng, 300)
    y = _true_model()(x)
    a = fit_ts(x, y, offset=OFFSET, scale=SCALE, max_nfev=30)
    b = fit_ts(x, y, offset=OFFSET, scale=SCALE, max_nfev=30)
    np.testing.assert_array_equal(a.x, b.x)
    bad = x.copy()
    bad[4, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        fit_ts(bad, y)
    with pytest.raises(ValueError, match="shape|must be"):
        fit_ts(x, y[:-1])
    with pytest.raises(ValueError, match="samples"):
        fit_ts(x[:5], y[:5])
    with pytest.raises(ValueError, match="positive"):
        TakagiSugeno(centers=np.zeros(2), sigmas=np.array([1.0, -1.0]), coef=np.zeros((2, 4)),
                     offset=OFFSET, scale=SCALE)


def test_stacked_models_equal_single_models():
    rng = np.random.default_rng(9)
    base = _true_model()
    models = [base.with_theta(base.theta() + rng.normal(0, 0.2, 18)) for _ in range(4)]
    stacked = StackedTS.stack(models)
    x = _inputs(rng, 7)
    out = stacked(x[:, None, :])  # (7, 4)
    for j, m in enumerate(models):
        np.testing.assert_allclose(out[:, j], m(x), rtol=1e-12)
    np.testing.assert_allclose(stacked.take([2])(x[:, None, :])[:, 0], models[2](x))
