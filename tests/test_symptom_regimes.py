"""Operating regimes in the symptom stage (pure core): each regime's residuals are judged by
that regime's fault-free statistics; the step-wise and the array path agree; a regime without
thresholds is "not valid here"; one regime behaves exactly as before regimes existed."""

from __future__ import annotations

import numpy as np
import pytest

from fdi_ros.core.symptoms import (
    SymptomConfig,
    SymptomGenerator,
    calibrate_thresholds,
    load_thresholds,
)
from fdi_ros.core.types import ResidualVector

NAMES = ("r_a", "r_b", "r_c")


def _rv(i, values, regime="", valid=True):
    return ResidualVector(model_id="nominal", index=i, t=0.01 * i, valid=valid,
                          status="" if valid else "outside", names=NAMES, units=("1",) * 3,
                          values=np.asarray(values, float), norm=0.0, regime=regime)


def _levels_by_definition(V, c, thr, intense, L, on, off):
    """The symptom rule written from its definition, one regime: moving average of the last
    L centred residuals, level by threshold, debounced on/off (intensity changes at once)."""
    out, level, cand, cnt, buf = [], [0] * V.shape[1], [0] * V.shape[1], [0] * V.shape[1], []
    for v in V:
        buf = (buf + [v - c])[-L:]
        f = np.mean(buf, axis=0)
        for i, fi in enumerate(f):
            r = -1 if fi < -thr[i] else 2 if fi > intense * thr[i] else 1 if fi > thr[i] else 0
            cnt[i] = cnt[i] + 1 if r == cand[i] else 1
            cand[i] = r
            grow = level[i] != 0 and r != 0 and (r > 0) == (level[i] > 0)
            if grow or (r != level[i] and cnt[i] >= (off if r == 0 else on)):
                level[i] = r
        out.append(tuple(level))
    return out


def _config(seed):
    rng = np.random.default_rng(seed)
    c = rng.normal(0, 1, 3)
    thr = rng.uniform(0.5, 2.0, 3)
    other = {"centre": tuple(rng.normal(0, 3, 3)), "threshold": tuple(rng.uniform(2, 6, 3)),
             "scale": (1.0, 1.0, 1.0)}
    return SymptomConfig(centre=tuple(c), threshold=tuple(thr), scale=(1.0,) * 3, names=NAMES,
                         filter_len=int(rng.integers(1, 6)), debounce_on=int(rng.integers(1, 4)),
                         debounce_off=int(rng.integers(1, 5)), regimes={"open": other},
                         base_regime="closed")


@pytest.mark.parametrize("seed", range(6))
def test_one_regime_keeps_the_threshold_rule(seed):
    cfg = _config(seed)
    rng = np.random.default_rng(100 + seed)
    V = np.cumsum(rng.normal(0, 0.6, (300, 3)), axis=0) * 0.3 + np.asarray(cfg.centre)
    got = [s.levels for s in SymptomGenerator(cfg).run([_rv(i, v) for i, v in enumerate(V)])]
    want = _levels_by_definition(V, np.asarray(cfg.centre), np.asarray(cfg.threshold),
                                 cfg.intense_factor, cfg.filter_len, cfg.debounce_on,
                                 cfg.debounce_off)
    assert got == want
    assert any(any(lv) for lv in got) and not all(any(lv) for lv in got)


@pytest.mark.parametrize("seed", range(8))
def test_regimes_judged_by_their_own_statistics_stepwise_equals_array_path(seed):
    cfg = _config(seed)
    rng = np.random.default_rng(seed)
    n = 400
    regime = np.where(np.cumsum(rng.random(n) < 0.03) % 2 == 0, "closed", "open")
    regime[rng.random(n) < 0.05] = ""            # no regime named: the base one
    valid = rng.random(n) > 0.05
    c_open, t_open = cfg.statistics("open")
    Z = np.cumsum(rng.normal(0, 0.5, (n, 3)), axis=0) * 0.2        # in threshold units
    V = np.where((regime == "open")[:, None], c_open + Z * t_open,
                 np.asarray(cfg.centre) + Z * np.asarray(cfg.threshold))
    rvs = [_rv(i, V[i], regime[i], valid[i]) for i in range(n)]
    gen = SymptomGenerator(cfg)
    step = [gen.update(rv) for rv in rvs]
    arr = SymptomGenerator(cfg).run(rvs)
    assert [s.levels for s in step] == [s.levels for s in arr]
    assert [s.valid for s in step] == [s.valid for s in arr] == list(valid)
    assert [s.regime for s in step] == list(regime)
    np.testing.assert_allclose([s.threshold_high for s in arr], [s.threshold_high for s in step])
    for s, r in zip(arr, regime):
        c, thr = cfg.statistics(r)
        assert s.threshold_high == pytest.approx(tuple(c + thr))
    # the same normalised walk gives the same levels whatever regime it is expressed in
    base = SymptomGenerator(cfg).run([_rv(i, np.asarray(cfg.centre) + Z[i] * np.asarray(
        cfg.threshold), "", valid[i]) for i in range(n)])
    assert [s.levels for s in base] == [s.levels for s in arr]


def test_unknown_regime_is_not_valid_and_says_why():
    cfg = _config(1)
    gen = SymptomGenerator(cfg)
    big = np.asarray(cfg.centre) + 50.0 * np.asarray(cfg.threshold)
    for i in range(5):
        s = gen.update(_rv(i, big, "flaps_closed"))
        assert not s.valid and "flaps_closed" in s.status and not any(s.levels)
    s = SymptomGenerator(cfg).run([_rv(0, big, "flaps_closed")])[0]
    assert not s.valid and "no thresholds for regime 'flaps_closed'" in s.status


def test_calibration_per_regime_equals_calibrating_each_regime_alone(tmp_path):
    rng = np.random.default_rng(7)
    n = 3000
    labels = np.where(rng.random(n) < 0.6, "closed", np.where(rng.random(n) < 0.99, "open",
                                                              "rare"))
    R = rng.normal(0, 1, (n, 3)) * np.where((labels == "open")[:, None], 4.0, 1.0) \
        + np.where((labels == "open")[:, None], 2.0, 0.0)
    valid = rng.random(n) > 0.1
    cfg = calibrate_thresholds(R, valid, names=NAMES, regimes=labels, base_regime="closed")
    alone = calibrate_thresholds(R[valid & (labels == "open")], names=NAMES)
    base = calibrate_thresholds(R[valid & (labels == "closed")], names=NAMES)
    assert cfg.regimes["open"]["threshold"] == alone.threshold
    assert cfg.regimes["open"]["centre"] == alone.centre
    assert cfg.threshold == base.threshold and cfg.centre == base.centre
    assert "rare" not in cfg.regimes        # too few rows: no thresholds, "not valid"
    assert min(cfg.regimes["open"]["threshold"]) > 2.5 * max(cfg.threshold)
    path = tmp_path / "thresholds.json"
    path.write_text(__import__("json").dumps(cfg.to_dict()))
    assert load_thresholds(path) == cfg
    with pytest.raises(ValueError, match="regime 'x'"):
        SymptomConfig.from_dict({**cfg.to_dict(), "regimes": {"x": {"centre": [0, 0, 0]}}})


def test_a_residual_not_judged_in_a_regime_never_gives_a_symptom_there(tmp_path):
    """A regime judged on some residuals only (e.g. crank pulsations with the EGR valve open,
    whose maps do not carry over): the others never give a symptom in it, however far they
    go, while the judged ones and every residual of the other regimes keep the rule; the flag
    survives the threshold file, and a malformed one is refused."""
    import json
    import random

    seed = random.randrange(2**32)
    rng = np.random.default_rng(seed)
    base = _config(seed % 1000)
    judged = (True, False, bool(rng.integers(2)))
    st = {**base.regimes["open"], "judged": judged}
    cfg = SymptomConfig(**{**base.__dict__, "regimes": {"open": st}})
    back = SymptomConfig.from_dict(json.loads(json.dumps(cfg.to_dict())))
    assert back == cfg and back.regimes["open"]["judged"] == judged
    assert cfg.judges_all("") and cfg.judges_all("closed") and not cfg.judges_all("open")
    c, thr = cfg.statistics("open")
    assert np.all(np.isinf(thr) == ~np.array(judged)), seed
    n = 80
    far = np.asarray(base.regimes["open"]["centre"]) + 50.0 * np.asarray(
        base.regimes["open"]["threshold"]) * rng.choice([-1, 1], 3)
    rvs = [_rv(i, far + rng.normal(0, 0.1, 3), regime="open" if i < n else "")
           for i in range(2 * n)]
    step = SymptomGenerator(cfg)
    states = [step.update(rv) for rv in rvs]
    assert [s.levels for s in states] == [s.levels for s in SymptomGenerator(cfg).run(rvs)]
    for s in states[n // 2:n]:
        assert all((lv != 0) == j for lv, j in zip(s.levels, judged)), (seed, s.levels)
        assert all(np.isnan(r) != j for r, j in zip(s.residuals, judged)), (seed, s.residuals)
    # the base regime judges every residual: the same values are symptoms there
    assert all(lv != 0 for lv in states[-1].levels), (seed, states[-1].levels)
    for bad in ((True, False), (1, 0, 1)):
        with pytest.raises(ValueError, match="judged"):
            SymptomConfig(**{**base.__dict__, "regimes": {"open": {**st, "judged": bad}}})
