"""LOLIMOT oracles: one model == least squares, a known break is found, smooth blending,
the contract (shape, determinism, bad input, save/load) and the identified region."""

from __future__ import annotations

import numpy as np
import pytest

from fdi_ros.core.lolimot import Lolimot


def _piecewise(X):
    # Break at x1 = 0.5 with slopes +2 and -2 along x1, plus 0.3 x0 everywhere.
    x0, x1 = X[:, 0], X[:, 1]
    return np.where(x1 < 0.5, 1.0 + 2.0 * x1, 2.0 - 2.0 * (x1 - 0.5)) + 0.3 * x0


@pytest.fixture()
def grid_data():
    rng = np.random.default_rng(1)
    return rng.uniform(0.0, 1.0, size=(3000, 2))


def test_one_model_equals_global_least_squares():
    rng = np.random.default_rng(0)
    X = rng.uniform([800.0, 1.0], [4500.0, 3.0], size=(500, 2))
    y = 0.2 + 1e-4 * X[:, 0] - 0.05 * X[:, 1] + 0.01 * rng.standard_normal(500)
    model = Lolimot(max_models=1, ridge=0.0)
    res = model.fit(X, y)
    assert res.n_models == 1 and res.success
    A = np.column_stack([np.ones(500), X])
    coef = np.linalg.lstsq(A, y, rcond=None)[0]
    np.testing.assert_allclose(model.predict(X), A @ coef, rtol=0, atol=1e-9)
    offset, slopes = model.local_parameters()
    np.testing.assert_allclose(slopes[0], coef[1:], rtol=1e-6)
    np.testing.assert_allclose(offset[0], coef[0] + model.centres[0] @ coef[1:], rtol=1e-9)


def test_piecewise_linear_break_and_slopes_recovered(grid_data):
    X = grid_data
    # Narrow validity functions: nearly crisp cells, so the local slopes are the true ones.
    model = Lolimot(max_models=2, k_sigma=0.08, ridge=0.0)
    res = model.fit(X, _piecewise(X))
    assert res.splits == ((0, 1),)  # the only split is along x1, the input with the break
    lo, hi = model.cell_bounds
    # The split sits at the break (the bounding box is within 1e-3 of [0, 1]).
    assert abs(sorted(hi[:, 1])[0] - 0.5) < 2e-3
    _, slopes = model.local_parameters()
    order = np.argsort(model.centres[:, 1])
    np.testing.assert_allclose(slopes[order, 1], [2.0, -2.0], rtol=0.02)
    np.testing.assert_allclose(slopes[:, 0], [0.3, 0.3], rtol=0.02)
    rng = np.random.default_rng(5)
    Xt = rng.uniform(0, 1, (500, 2))
    far = np.abs(Xt[:, 1] - 0.5) > 0.1
    np.testing.assert_allclose(model.predict(Xt[far]), _piecewise(Xt[far]), atol=5e-3)


def test_more_models_reduce_error_and_validation_selects(grid_data):
    rng = np.random.default_rng(2)
    f = lambda X: np.sin(3 * X[:, 0]) * np.exp(X[:, 1])  # noqa: E731
    X = grid_data
    y = f(X) + 0.02 * rng.standard_normal(X.shape[0])
    Xv = rng.uniform(0, 1, (800, 2))
    res = Lolimot(max_models=25).fit(X, y, X_val=Xv, y_val=f(Xv) + 0.02 * rng.standard_normal(800))
    assert res.loss[0] > 5 * res.loss[-1]
    assert res.n_models == int(np.argmin(res.criterion)) + 1
    assert res.val_rmse < 0.03
    res_aic = Lolimot(max_models=25).fit(X, y)
    assert res_aic.criterion_name == "aicc" and res_aic.n_models > 5


def test_smooth_across_cell_borders(grid_data):
    X = grid_data
    model = Lolimot(max_models=6)
    model.fit(X, _piecewise(X) ** 2)
    lo, hi = model.cell_bounds
    # Walk across every interior border along x1 and x0: no jumps, bounded derivative.
    for d in (0, 1):
        for b in np.unique(np.concatenate([lo[:, d], hi[:, d]])):
            if b <= 0.01 or b >= 0.99:
                continue
            t = np.linspace(b - 1e-3, b + 1e-3, 41)
            P = np.full((41, 2), 0.37)
            P[:, d] = t
            yy = model.predict(P)
            steps = np.abs(np.diff(yy))
            assert steps.max() < 5 * np.median(steps) + 1e-9
    phi = model.validity(X)
    np.testing.assert_allclose(phi.sum(axis=1), 1.0)


def test_contract_determinism_save_load_bad_input(tmp_path, grid_data):
    X = grid_data
    y = _piecewise(X)
    a = Lolimot(max_models=5)
    b = Lolimot(max_models=5)
    a.fit(X, y, input_names=("n", "rho2"), output_name="eta_v")
    b.fit(X, y, input_names=("n", "rho2"), output_name="eta_v")
    Xt = np.random.default_rng(3).uniform(-0.2, 1.2, (100, 2))
    assert a.predict(Xt).shape == (100,)
    np.testing.assert_array_equal(a.predict(Xt), b.predict(Xt))
    path = a.save(tmp_path / "m.npz")
    c = Lolimot.load(path)
    np.testing.assert_array_equal(a.predict(Xt), c.predict(Xt))
    np.testing.assert_array_equal(a.in_region(Xt), c.in_region(Xt))
    assert c.input_names == ("n", "rho2") and c.output_name == "eta_v"
    assert np.isnan(a.predict(np.array([[np.nan, 0.5]])))[0]
    with pytest.raises(ValueError):
        a.predict(np.zeros((3, 3)))
    with pytest.raises(ValueError):
        Lolimot().fit(X, np.where(np.arange(X.shape[0]) == 3, np.nan, y))
    with pytest.raises(ValueError):
        Lolimot(k_sigma=5.0)
    with pytest.raises(RuntimeError):
        Lolimot().predict(X)
    with pytest.raises(FileNotFoundError):
        Lolimot.load(tmp_path / "missing.npz")
    (tmp_path / "bad.npz").write_bytes(b"junk")
    with pytest.raises(ValueError):
        Lolimot.load(tmp_path / "bad.npz")


def test_in_region_marks_the_empty_corner():
    rng = np.random.default_rng(4)
    X = rng.uniform(0, 1, (4000, 2))
    X = X[~((X[:, 0] < 0.4) & (X[:, 1] > 0.6))]  # "low speed with high boost" left empty
    model = Lolimot(max_models=3)
    model.fit(X, X[:, 0] + X[:, 1])
    inside = model.in_region(np.array([[0.7, 0.7], [0.2, 0.2], [0.1, 0.9], [1.5, 0.5]]))
    assert inside.tolist() == [True, True, False, False]


def test_pooled_fit_matches_the_plain_fit_on_repetitive_data():
    # Quasi-stationary data: many repeats of a few hundred operating points.
    rng = np.random.default_rng(6)
    ops = rng.uniform(0, 1, (300, 2))
    X = ops[rng.integers(0, 300, 6000)] + rng.normal(0, 1e-3, (6000, 2))
    f = lambda X: np.sin(3 * X[:, 0]) * np.exp(X[:, 1])  # noqa: E731
    y = f(X) + 0.01 * rng.standard_normal(6000)
    plain = Lolimot(max_models=8)
    pooled = Lolimot(max_models=8, compress_bins=64)
    r1, r2 = plain.fit(X, y), pooled.fit(X, y)
    assert r1.n_models == r2.n_models
    Xt = rng.uniform(0, 1, (500, 2))
    np.testing.assert_allclose(pooled.predict(Xt), plain.predict(Xt), atol=0.02)
    assert abs(r1.train_rmse - r2.train_rmse) < 0.1 * r1.train_rmse + 1e-3


def test_coverage_closing_fills_holes_but_keeps_the_outline():
    from fdi_ros.core.lolimot import _closing

    g = np.ones((6, 6), bool)
    g[:3, 3:] = False        # the empty corner (3 x 3 bins)
    g[4, 2] = False          # a one-bin hole between sweeps
    c = _closing(g)
    assert c[4, 2] and not c[:2, 4:].any() and c[:3, 3:].sum() <= 1


@pytest.mark.parametrize("p, compress, with_val", [(2, 0, True), (3, 16, False), (1, 0, False)])
def test_fast_splits_equal_the_reference(p, compress, with_val, monkeypatch):
    """Candidate splits that reuse the untouched cells' validities and the data's regressor
    products grow exactly the tree of the reference, which recomputes everything."""
    rng_seed = int(np.random.SeedSequence().entropy % 10_000)
    rng = np.random.default_rng(rng_seed)
    X = rng.uniform(-1.0, 2.0, size=(1500, p))
    y = np.sin(2.5 * X[:, 0]) + (X[:, -1] > 0.7) * X[:, -1] + 0.05 * rng.standard_normal(1500)
    kw = dict(max_models=int(rng.integers(4, 14)), k_sigma=float(rng.uniform(0.3, 0.5)),
              compress_bins=compress, patience=3)
    Xv, yv = (X[:300], y[:300]) if with_val else (None, None)
    fits = {}
    for fast in (True, False):
        monkeypatch.setattr(Lolimot, "_fast_splits", fast)
        m = Lolimot(**kw)
        fits[fast] = (m, m.fit(X[300:], y[300:], X_val=Xv, y_val=yv))
    (a, ra), (b, rb) = fits[True], fits[False]
    assert ra.splits == rb.splits and ra.n_models == rb.n_models, f"seed {rng_seed}"
    np.testing.assert_array_equal(ra.loss, rb.loss)
    for u, v in zip(a.to_arrays().values(), b.to_arrays().values()):
        np.testing.assert_array_equal(u, v)
    np.testing.assert_array_equal(a.predict(X[:50]), b.predict(X[:50]))


def test_stack_equals_each_map_predicting_alone():
    """LolimotStack (several maps of the same inputs in one pass) gives every map's own
    prediction, for maps of different sizes, scalings and widths, at random points inside,
    far outside and with NaN."""
    from fdi_ros.core.lolimot import LolimotStack

    seed = int(np.random.SeedSequence().entropy % 2**32)
    rng = np.random.default_rng(seed)
    p = int(rng.integers(1, 4))
    models = []
    for _ in range(int(rng.integers(1, 6))):
        X = rng.uniform(-1, 1, size=(400, p)) * rng.uniform(0.1, 100, size=p) + rng.normal(
            size=p) * 50
        y = np.sin(X @ rng.normal(size=p) / np.abs(X).max()) + 0.01 * rng.normal(size=400)
        m = Lolimot(max_models=int(rng.integers(1, 12)), k_sigma=float(rng.uniform(0.2, 0.6)))
        m.fit(X, y)
        models.append(m)
    stack = LolimotStack(models)
    Xq = rng.normal(size=(50, p)) * 200
    Xq[3, 0] = np.nan
    Xq[5] = 1e6
    got = stack.predict(Xq)
    want = np.column_stack([m.predict(Xq) for m in models])
    assert got.shape == want.shape
    assert np.array_equal(np.isnan(got), np.isnan(want)), seed
    ok = np.isfinite(want)
    assert np.allclose(got[ok], want[ok], rtol=1e-9, atol=1e-12), (seed, np.abs(got - want).max())
    assert np.isnan(got[3]).all()
    with pytest.raises(ValueError):
        LolimotStack([])


def test_region_from_all_identification_data(tmp_path):
    """set_region: the identified region reaches rows the model was scored on beyond the
    training box (and only where there were rows); it survives save/load, and a model file
    without it keeps the training box."""
    rng = np.random.default_rng(int(np.random.SeedSequence().entropy % 2**32))
    X = np.column_stack([rng.uniform(0, 10, 3000), rng.uniform(0, 1, 3000)])
    y = X[:, 0] * X[:, 1]
    train = X[:, 0] < 9.0
    m = Lolimot(max_models=6)
    m.fit(X[train], y[train])
    probe = np.array([[9.5, 0.5], [5.0, 0.5], [11.0, 0.5]])
    assert m.in_region(probe).tolist() == [False, True, False]
    before = m.predict(probe)
    m.set_region(X)
    assert m.in_region(probe).tolist() == [True, True, False]
    assert np.array_equal(m.predict(probe), before)  # the model itself is unchanged
    path = m.save(tmp_path / "m.npz")
    back = Lolimot.load(path)
    assert back.in_region(probe).tolist() == [True, True, False]
    old = {k: v for k, v in m.to_arrays().items() if not k.startswith("region_")}
    old["coverage"] = np.ones((16, 16), dtype=bool)  # a file written before set_region
    assert Lolimot.from_arrays(old).in_region(probe).tolist() == [False, True, False]
    with pytest.raises(ValueError):
        m.set_region(np.full((3, 2), np.nan))
