"""The scalar per-segment look-up path equals the vectorised one (values and validity),
inside, at the edges, outside (clamped, not valid), and for NaN inputs."""

from __future__ import annotations

import numpy as np

from fdi_ros.core.lut import LookupTable


def test_point_path_equals_vectorised_path():
    rng = np.random.default_rng(3)
    b0 = np.array([800.0, 1200, 2000, 2600, 3400, 4000])
    b1 = np.array([1.0, 1.4, 1.9, 2.5, 3.1])
    vals = rng.normal(size=(6, 5))
    ident = rng.random((6, 5)) > 0.3
    lut = LookupTable(breakpoints=(b0, b1), values=vals, identified=ident)
    pts = np.column_stack([rng.uniform(500, 4500, 400), rng.uniform(0.7, 3.5, 400)])
    pts = np.vstack([pts, [[800.0, 1.0], [4000.0, 3.1], [2000.0, 1.9], [np.nan, 2.0]]])
    vec_v, vec_ok = lut._interp(lut.values, *lut._corners(pts)[:2]), None
    idx, frac, inside, finite = lut._corners(pts)
    vec_ok = inside & (lut._interp(lut.identified.astype(float), idx, frac) >= 0.5)
    vec_v[~finite] = np.nan
    for k, (x0, x1) in enumerate(pts):
        v, ok = lut.evaluate_point(x0, x1)
        assert ok == bool(vec_ok[k]), (x0, x1)
        if np.isnan(vec_v[k]):
            assert np.isnan(v)
        else:
            assert abs(v - vec_v[k]) <= 1e-12 * max(1.0, abs(vec_v[k]))
    # evaluate() of one point takes the scalar path and agrees too
    v1, ok1 = lut.evaluate(pts[5])
    assert v1.shape == (1,) and abs(v1[0] - vec_v[5]) < 1e-12 and ok1[0] == vec_ok[5]
