"""Symptoms: thresholds from fault-free statistics, debouncing, isolation by the table."""

from __future__ import annotations

import numpy as np
import pytest

from fdi_ros.core.residual_models import load_residual_model, registered_types
from fdi_ros.core.symptoms import moving_average
from fdi_ros.core.types import ResidualVector
from fdi_ros.plants import ROOT
from fdi_ros.plants.diesel.symptoms import (
    PAPER_TABLE,
    RESIDUALS,
    SYMPTOMS,
    SymptomConfig,
    SymptomGenerator,
    calibrate_thresholds,
    isolate,
    load_fault_symptom_tables,
)


def _rv(i, values, valid=True):
    return ResidualVector(model_id="nominal", index=i, t=0.015 * i, valid=valid,
                          status="" if valid else "outside", names=RESIDUALS,
                          units=("1",) * 5, values=np.asarray(values, float), norm=0.0)


def test_moving_average_is_causal_mean():
    R = np.arange(10.0)[:, None]
    F = moving_average(R, 3)
    np.testing.assert_allclose(F[:, 0], [0, 0.5, 1, 2, 3, 4, 5, 6, 7, 8])


def test_thresholds_cover_fault_free_data_and_detect_a_step():
    rng = np.random.default_rng(0)
    sd = np.array([0.01, 2.0, 1.5, 80.0, 2.0])
    R = rng.standard_normal((5000, 5)) * sd + np.array([0.002, 0, 0, 0, 0])
    cfg = calibrate_thresholds(R, k_sigma=5.0, filter_len=4)
    np.testing.assert_allclose(cfg.centre, [0.002, 0, 0, 0, 0], atol=0.1 * sd.max())
    # The filtered std of white noise is sd / 2 for a 4-segment mean.
    np.testing.assert_allclose(cfg.scale, sd / 2, rtol=0.1)
    gen = SymptomGenerator(config=cfg)
    fresh = rng.standard_normal((3000, 5)) * sd + cfg.centre
    levels = np.array([gen.update(_rv(i, r)).levels for i, r in enumerate(fresh)])
    assert not levels.any()  # no false symptom on fault-free data
    # A step of -8 filtered sigmas in r_eta: "-" within filter + debounce segments.
    step = np.zeros(5)
    step[0] = -8 * cfg.scale[0]
    states = [gen.update(_rv(3000 + i, cfg.centre + step)) for i in range(8)]
    first = next(i for i, s in enumerate(states) if s.levels[0] != 0)
    assert states[first].levels[0] == -1 and first + 1 <= cfg.filter_len + cfg.debounce_on
    assert states[-1].in_order(SYMPTOMS) == (-1, 0, 0, 0, 0)
    assert states[-1].signature == "-,o,o,o,o"


def test_debounce_rejects_a_single_spike_and_intense_level():
    cfg = SymptomConfig(centre=(0.0,) * 5, threshold=(1.0,) * 5, scale=(0.2,) * 5, names=RESIDUALS,
                        filter_len=1, debounce_on=3, debounce_off=2)
    gen = SymptomGenerator(config=cfg)
    seq = [0, 5, 0, 0, 2, 2, 2, 2, 5, 5, 0, 0, 0]
    lv = [gen.update(_rv(i, [v, 0, 0, 0, 0])).levels[0] for i, v in enumerate(seq)]
    assert lv == [0, 0, 0, 0, 0, 0, 1, 1, 2, 2, 2, 0, 0]


def test_invalid_residuals_give_no_symptom_and_restart():
    cfg = SymptomConfig(centre=(0.0,) * 5, threshold=(1.0,) * 5, scale=(0.2,) * 5, names=RESIDUALS,
                        filter_len=1, debounce_on=1, debounce_off=1)
    gen = SymptomGenerator(config=cfg)
    assert gen.update(_rv(0, [3, 0, 0, 0, 0])).levels[0] == 1
    s = gen.update(_rv(1, [3, 0, 0, 0, 0], valid=False))
    assert not s.valid and s.levels == (0,) * 5 and s.status == "outside"
    nan = gen.update(_rv(2, [np.nan, 0, 0, 0, 0]))
    assert not nan.valid and nan.levels == (0,) * 5


def test_isolation_by_the_paper_table():
    assert isolate((-1, 0, 0, 0, 0), PAPER_TABLE) == ["leak_ic_engine"]
    assert isolate((0, -1, -1, 0, 0), PAPER_TABLE) == ["swirl_flap_closed"]
    assert isolate((2, -1, -1, 0, 0), PAPER_TABLE) == ["egr_stuck_open"]
    assert isolate((1, -1, -1, 0, 0), PAPER_TABLE) == ["egr_stuck_open"]  # sign match
    # The table cannot tell the open crank-case vent from the leaky EGR valve.
    assert sorted(isolate((1, 0, 0, 0, 0), PAPER_TABLE)) == ["crankcase_vent_open", "egr_leaky"]
    assert isolate((0, 0, 0, 0, 0), PAPER_TABLE) == []
    assert isolate({"s_eta": -1}, PAPER_TABLE) == ["leak_ic_engine"]
    with pytest.raises(ValueError):
        isolate((1, 0), PAPER_TABLE)


def test_fault_symptom_table_file(tmp_path):
    p = tmp_path / "fst.yaml"
    p.write_text("symptoms: [s_eta, s_Am, s_Ap, s_phim, s_php]\n"
                 "tables:\n  paper:\n    leak_ic_engine: '-,o,o,o,o'\n"
                 "    egr_stuck_open: [++, '-', '-', o, o]\n")
    t = load_fault_symptom_tables(p)
    assert t["paper"]["egr_stuck_open"] == (2, -1, -1, 0, 0)
    p.write_text("tables:\n  x:\n    f: '+,?,o,o,o'\n")
    with pytest.raises(ValueError):
        load_fault_symptom_tables(p)
    # columns in another order than the diesel's symptoms: refused, not silently misread
    p.write_text("symptoms: [s_Am, s_eta, s_Ap, s_phim, s_php]\n"
                 "tables:\n  x:\n    leak_ic_engine: 'o,-,o,o,o'\n")
    with pytest.raises(ValueError, match="columns"):
        load_fault_symptom_tables(p)
    # The shipped file's paper table and the one in the code are the paper's Fig. 14, checked
    # against the figure's rows as printed (not against each other).
    shipped = load_fault_symptom_tables(ROOT / "config" / "diesel_fst.yaml")
    assert dict(shipped["paper"]) == FIG_14 and dict(PAPER_TABLE) == FIG_14
    assert shipped["paper"].columns == SYMPTOMS == PAPER_TABLE.columns


# Schwarte & Isermann (2002), Fig. 14, typed from the paper: columns s_eta, s_Am, s_Ap, s_phim,
# s_php; "++" intense positive, "+" positive, "-" negative, "o" no response.
FIG_14_PRINTED = {
    "crankcase_vent_open": "+  o  o  o  o",     # crank case vent: pipe is open at junction
    "leak_ic_engine": "-  o  o  o  o",          # leakage between intercooler and engine
    "restriction_ic_engine": "o  -  -  +  +",   # restriction between intercooler and engine
    "swirl_flap_closed": "o  -  -  o  o",       # swirl flaps actuator, filling port is closed
    "egr_stuck_open": "++ -  -  o  o",          # EGR valve stuck at open
    "egr_leaky": "+  o  o  o  o",               # leaky EGR valve
}
FIG_14 = {f: tuple({"++": 2, "+": 1, "o": 0, "-": -1}[c] for c in row.split())
          for f, row in FIG_14_PRINTED.items()}


def test_registry_rejects_bad_specs(tmp_path):
    assert "diesel_reference" in registered_types()
    with pytest.raises(ValueError):
        load_residual_model({"type": "no_such_kind"}, model_id="x")
    with pytest.raises(ValueError):
        load_residual_model({"path": "."}, model_id="x")
    with pytest.raises(FileNotFoundError):
        load_residual_model(tmp_path / "missing", model_id="x")
    with pytest.raises(FileNotFoundError):
        load_residual_model({"type": "diesel_reference", "path": str(tmp_path)}, model_id="n")


def test_isolation_with_one_mismatch_allowed():
    # Our plant's open vent also lowers the MAF amplitude: one symptom off the paper's row.
    assert isolate((2, -1, 0, 0, 0), PAPER_TABLE) == []
    assert sorted(isolate((2, -1, 0, 0, 0), PAPER_TABLE, max_mismatch=1)) == [
        "crankcase_vent_open", "egr_leaky", "egr_stuck_open"]   # each differs in one symptom
    assert isolate((-1, 0, 0, 0, 0), PAPER_TABLE, max_mismatch=1) == ["leak_ic_engine"]


def _fv(i, t, n, p2, fuel, valid=True):
    from fdi_ros.core.types import FeatureVector

    names = ("n", "p2", "fuel")
    return FeatureVector(plant="diesel", index=i, t_start=t - 0.015, t_end=t, alpha_start=0.0,
                         valid=valid, status="", names=names, units=("",) * 3,
                         values=np.array([n, p2, fuel], float))


def test_quasi_stationarity_gate_and_storage_correction():
    from fdi_ros.plants.diesel.symptoms import QuasiStationarity

    cfg = SymptomConfig(centre=(0.0,) * 5, threshold=(1.0,) * 5, scale=(1.0,) * 5, names=RESIDUALS,
                        storage_coeff=500.0, settle_s=0.5, max_speed_change=50.0,
                        max_fuel_change=1.0, rate_lag=2)
    qs = QuasiStationarity(cfg)
    r0 = np.zeros(5)
    out = []
    for i in range(200):
        t = 0.015 * (i + 1)
        n = 2000.0 if t < 1.5 else 2200.0          # a speed step at 1.5 s
        p2 = 150000.0 + 3000.0 * t                 # boost rising at 3 kPa/s
        out.append(qs.apply(_fv(i, t, n, p2, 20.0), r0, True, ""))
    valid = np.array([o[1] for o in out])
    t = 0.015 * (np.arange(200) + 1)
    assert not valid[t < 0.4].any()                # history shorter than settle_s
    assert valid[(t > 0.6) & (t < 1.49)].all()
    assert not valid[(t > 1.5) & (t < 1.99)].any()  # speed moved 200 rpm within 0.5 s
    assert valid[t > 2.05].all() and "transient" in out[110][2]
    # r_eta correction: storage_coeff * (dp2/dt) / (n p2), dp2/dt = 3000 Pa/s exactly.
    k = 80
    p2 = 150000.0 + 3000.0 * t[k]
    assert out[k][0][0] == pytest.approx(500.0 * 3000.0 / (2000.0 * p2), rel=1e-6)
    # A segment flagged invalid by the front end restarts the history.
    assert not qs.apply(_fv(300, 5.0, 2200.0, 1.6e5, 20.0, valid=False), r0, False, "x")[1]
    assert not qs.apply(_fv(301, 5.015, 2200.0, 1.6e5, 20.0), r0, True, "")[1]


def test_isolation_distance_weighs_opposite_signs_double():
    table = {"vent": (2, -1, 0, 0, 0), "leak": (-1, 0, 0, 0, 0)}
    # (-,-): vent has s_eta of opposite sign (2), leak misses s_Am (1) -> leak.
    assert isolate((-1, -1, 0, 0, 0), table, max_mismatch=1) == ["leak"]
    assert isolate((-1, -1, 0, 0, 0), table, max_mismatch=0) == []
