"""Measured-data loading: CSV with our columns, CSV + mapping, validation, segment means."""

from __future__ import annotations

import numpy as np
import pytest

from fdi_ros.core.measured import Mapping, load_csv, load_measured, segment_means

MAPPING = """
time: {column: time, unit: s}
signals:
  n: {column: engine_speed, unit: rpm, scale: 9.549296585513721}
  maf: {column: air_mass_flow, unit: kg/h, scale: 3600.0}
  p_im: {column: p, unit: Pa, offset: 100.0}
keep_unmapped: true
"""


def _write(path, header, rows):
    path.write_text(",".join(header) + "\n" + "\n".join(",".join(str(c) for c in r)
                                                        for r in rows) + "\n")
    return path


def test_own_columns_and_units(tmp_path):
    p = _write(tmp_path / "m.csv", ["t", "n", "maf", "extra"],
               [[0.0, 1000, 10, 1], [0.05, 1010, 11, 2], [0.1, 1020, 12, 3]])
    m = load_csv(p)
    assert m.units["n"] == "rpm" and m.units["maf"] == "kg/h"
    assert m.unmapped == ("extra",)
    np.testing.assert_allclose(m["maf"], [10, 11, 12])


def test_mapping_renames_converts_keeps_unmapped(tmp_path):
    mp = tmp_path / "map.yaml"
    mp.write_text(MAPPING)
    p = _write(tmp_path / "x.csv", ["time", "engine_speed", "air_mass_flow", "p", "oil"],
               [[0.0, 100.0, 0.01, 5e4, 80], [0.05, 110.0, 0.02, 6e4, 81]])
    m = load_csv(p, mp)
    np.testing.assert_allclose(m["n"], [100 * 60 / (2 * np.pi), 110 * 60 / (2 * np.pi)])
    np.testing.assert_allclose(m["maf"], [36.0, 72.0])
    np.testing.assert_allclose(m["p_im"], [50100.0, 60100.0])
    assert m.units["maf"] == "kg/h"
    assert "oil" in m.unmapped and "engine_speed" not in m.signals


def test_nan_cells_are_masked_not_dropped(tmp_path):
    p = _write(tmp_path / "m.csv", ["t", "maf", "n"],
               [[0.0, 1, 1000], [0.05, "", 1000], [0.1, "nan", 1000], [0.15, 4, 1000]])
    m = load_csv(p)
    assert m.n_samples == 4
    assert list(m.valid(["maf"])) == [True, False, False, True]


@pytest.mark.parametrize("rows,msg", [
    ([[0.0, 1], [0.05, "abc"]], "line 3, column 'maf'"),
    ([[0.0, 1], [0.0, 2]], "not strictly increasing"),
    ([[0.1, 1], [0.05, 2]], "not strictly increasing"),
    ([[0.0, 1], [0.05, 2, 3]], "fields"),
    ([[0.0, 1]], "fewer than 2"),
])
def test_malformed_csv_is_a_clear_error(tmp_path, rows, msg):
    p = _write(tmp_path / "bad.csv", ["t", "maf"], rows)
    with pytest.raises(ValueError, match=msg):
        load_csv(p)


def test_missing_time_and_mapped_column_errors(tmp_path):
    p = _write(tmp_path / "x.csv", ["time", "a"], [[0, 1], [1, 2]])
    with pytest.raises(ValueError, match="no 't' column"):
        load_csv(p)
    with pytest.raises(ValueError, match="wants column 'engine_speed'"):
        load_csv(p, Mapping.from_dict({"time": "time", "signals": {"n": "engine_speed"}}))
    with pytest.raises(ValueError, match="unknown keys"):
        Mapping.from_dict({"time": "time", "signals": {"n": "a"}, "bogus": 1})
    with pytest.raises(FileNotFoundError):
        load_measured(tmp_path / "absent.csv")


def test_gaps_split_segments(tmp_path):
    t = [0.0, 0.05, 0.1, 2.0, 2.05, 2.1]
    p = _write(tmp_path / "g.csv", ["t", "maf"], [[x, 1.0] for x in t])
    m = load_csv(p)
    assert list(m.segment) == [0, 0, 0, 1, 1, 1]


def test_segment_means_remove_the_pulsation():
    from fdi_ros.core.measured import Measured

    alpha = np.arange(0, 3600, 20.0)  # 20 deg CA steps, 20 segments of 180 deg
    t = alpha / (6 * 2000.0)
    maf = 100.0 + 0.01 * t + 5 * np.cos(2 * np.pi * alpha / 180 + 0.3) + 2 * np.cos(
        4 * np.pi * alpha / 180)
    m = Measured(t=t, signals={"maf": maf}, units={"maf": "kg/h"}, alpha=alpha)
    s = segment_means(m)
    assert s.alpha is None and s.n_samples == 18  # first and last segments dropped
    np.testing.assert_allclose(s["maf"], 100.0 + 0.01 * s.t, atol=1e-9)


def test_bag_of_sensor_blocks_loads_as_one_record(tmp_path):
    from fdi_ros import bag
    from fdi_ros.plants.diesel.plant import DieselIntakePlant

    plant = DieselIntakePlant(seed=3, dalpha_deg=30.0)
    plant.set_inputs(n_rpm=1800.0, fuel_mg=20.0)
    blocks = [plant.advance(240) for _ in range(3)]
    with bag.BagWriter(tmp_path / "b") as w:
        for b in blocks:
            w.write_block(b)
    m = load_measured(tmp_path / "b")
    assert m.n_samples == 720 and m.alpha is not None
    np.testing.assert_allclose(m["maf"], np.concatenate([b.channel("maf") for b in blocks]))
    assert m.units["maf"] == "kg/h"


def test_csv_fast_reader_equals_the_row_reader(tmp_path):
    """numpy's C reader (a clean file) and the row-by-row reader give the same columns, to
    the bit, on a random table with NaN cells; a file the C reader refuses (an empty cell)
    still loads through the row reader, the empty cell NaN."""
    import secrets

    from fdi_ros.core.measured import _read_csv_columns, _read_csv_rows

    seed = secrets.randbelow(2**31)
    rng = np.random.default_rng(seed)
    header = ["t"] + [f"c{i}" for i in range(int(rng.integers(1, 6)))]
    vals = rng.normal(0, 10.0 ** rng.uniform(-3, 6), (int(rng.integers(2, 400)), len(header)))
    vals[rng.uniform(size=vals.shape) < 0.05] = np.nan
    path = tmp_path / "x.csv"
    path.write_text(",".join(header) + "\n" + "\n".join(
        ",".join(repr(float(v)) for v in row) for row in vals) + "\n")
    fast, rows = _read_csv_columns(path), _read_csv_rows(path, header)
    for h in header:
        np.testing.assert_array_equal(fast[h], rows[h], err_msg=f"seed {seed}")
    lines = path.read_text().splitlines()
    lines[1] = ",".join([lines[1].split(",")[0], ""] + lines[1].split(",")[2:])
    path.write_text("\n".join(lines) + "\n")
    holed = _read_csv_columns(path)
    assert np.isnan(holed[header[1]][0])
