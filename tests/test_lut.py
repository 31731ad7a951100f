"""Look-up tables: exact on bilinear functions, clamped, validity flags, error vs grid size."""

from __future__ import annotations

import numpy as np
import pytest

from fdi_ros.core.lolimot import Lolimot
from fdi_ros.core.lut import LookupTable, table_error


def _bilinear(X):
    return 1.0 + 2.0 * X[:, 0] - 3.0 * X[:, 1] + 0.5 * X[:, 0] * X[:, 1]


def test_bilinear_function_is_reproduced_exactly_and_clamped():
    bp = (np.array([0.0, 0.3, 1.0, 2.0]), np.array([-1.0, 0.5, 1.0]))
    lut = LookupTable.from_model(_bilinear, bp)
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(0, 2, 200), rng.uniform(-1, 1, 200)])
    np.testing.assert_allclose(lut(X), _bilinear(X), atol=1e-12)
    # Clamping: beyond the outermost breakpoints the edge value is held, flagged invalid.
    vals, valid = lut.evaluate(np.array([[5.0, 0.0], [-1.0, 3.0], [1.0, 0.0]]))
    np.testing.assert_allclose(vals[:2], _bilinear(np.array([[2.0, 0.0], [0.0, 1.0]])))
    assert valid.tolist() == [False, False, True]
    assert np.isnan(lut(np.array([[np.nan, 0.0]])))[0]


def test_ecu_bilinear_by_hand():
    lut = LookupTable(breakpoints=(np.array([0.0, 1.0]), np.array([0.0, 1.0])),
                      values=np.array([[0.0, 1.0], [2.0, 4.0]]),
                      identified=np.ones((2, 2), bool))
    # f(0.5, 0.5) = mean of the four corners; f(0.25, 1) = 0.75*1 + 0.25*4.
    np.testing.assert_allclose(lut(np.array([[0.5, 0.5], [0.25, 1.0]])), [1.75, 1.75])


def test_validity_from_model_region_and_error_shrinks_with_grid(tmp_path):
    rng = np.random.default_rng(1)
    X = rng.uniform([800.0, 1.0], [4500.0, 3.0], (4000, 2))
    X = X[~((X[:, 0] < 1800) & (X[:, 1] > 2.2))]   # empty corner: low speed, high boost
    f = lambda X: 0.8 + 0.05 * np.sin(X[:, 0] / 700.0) - 0.02 * (X[:, 1] - 2) ** 2  # noqa: E731
    model = Lolimot(max_models=15)
    model.fit(X, f(X))
    errs = []
    for nx, ny in ((5, 4), (9, 7), (17, 13)):
        bp = (np.linspace(800, 4500, nx), np.linspace(1, 3, ny))
        lut = LookupTable.from_model(model.predict, bp, region=model.in_region,
                                     input_names=("n", "rho2"), output_name="eta_v")
        errs.append(table_error(model.predict, lut, X)["rmse"])
    assert errs[0] > errs[1] > errs[2]
    _, valid = lut.evaluate(np.array([[1000.0, 2.9], [3000.0, 2.0]]))
    assert valid.tolist() == [False, True]
    path = lut.save(tmp_path / "eta.json")
    back = LookupTable.load(path)
    np.testing.assert_array_equal(back(X[:50]), lut(X[:50]))
    np.testing.assert_array_equal(back.identified, lut.identified)


def test_bad_tables_rejected(tmp_path):
    with pytest.raises(ValueError):
        LookupTable(breakpoints=(np.array([0.0, 0.0]),), values=np.zeros(2),
                    identified=np.ones(2, bool))
    with pytest.raises(ValueError):
        LookupTable(breakpoints=(np.array([0.0, 1.0]),), values=np.zeros(3),
                    identified=np.ones(3, bool))
    lut = LookupTable.from_model(_bilinear, (np.arange(3.0), np.arange(3.0)))
    with pytest.raises(ValueError):
        lut(np.zeros((2, 3)))
    (tmp_path / "x.json").write_text("{")
    with pytest.raises(ValueError):
        LookupTable.load(tmp_path / "x.json")
