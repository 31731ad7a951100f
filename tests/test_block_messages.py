"""The batched messages of the live graph (FeatureBlock, ResidualBlock): the vectors of one
sensor block survive the round trip exactly, in either message flavour, for random blocks;
malformed blocks are refused with the reason."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from fdi_ros import msgs
from fdi_ros.core.types import FeatureVector, ResidualVector


def _same(a, b) -> bool:
    da, db = a.__dict__, b.__dict__
    for k, va in da.items():
        vb = db[k]
        if isinstance(va, np.ndarray):
            if not np.array_equal(va, vb, equal_nan=True):
                return False
        elif isinstance(va, float) and math.isnan(va):
            if not (isinstance(vb, float) and math.isnan(vb)):
                return False
        elif va != vb:
            return False
    return True


def _random_vectors(rng):
    k = int(rng.integers(1, 6))
    names = tuple(f"f{j}" for j in range(int(rng.integers(1, 20))))
    units = tuple(rng.choice(["rpm", "1", "kg/h", "deg CA"]) for _ in names)
    t0 = float(rng.uniform(0, 1e4))
    feats, res = [], []
    for i in range(k):
        v = rng.normal(size=len(names)) * 10.0 ** rng.integers(-6, 6)
        v[rng.random(v.size) < 0.1] = np.nan
        valid = bool(rng.random() < 0.8)
        feats.append(FeatureVector(
            plant="diesel", index=int(rng.integers(0, 2**40)) + i, t_start=t0 + i * 0.005,
            t_end=t0 + (i + 1) * 0.005, alpha_start=float(rng.choice([np.nan, 180.0 * i])),
            valid=valid, status="" if valid else "NaN sample", names=names, units=units,
            values=v))
        res.append(ResidualVector(
            model_id="leak_ic_engine_small", index=feats[-1].index, t=feats[-1].t_end,
            valid=valid, status="" if valid else "not valid here: settling",
            names=names[:3], units=units[:3], values=v[:3].copy(),
            norm=float(rng.exponential()) if valid else float("nan"),
            regime=str(rng.choice(["", "egr_open"]))))
    return feats, res


@pytest.mark.parametrize("flavour", ["rosbags", "rclpy"])
def test_blocks_round_trip_random(flavour):
    fac = msgs.MessageFactory(flavour)
    seed = int(np.random.SeedSequence().entropy % 2**32)
    rng = np.random.default_rng(seed)
    for _ in range(40):
        feats, res = _random_vectors(rng)
        fm = fac.feature_blocks(feats, block_index=17)
        rm = fac.residual_blocks(res)
        assert len(fm) == 1 and len(rm) == 1, seed
        back_f = msgs.to_feature_list(fm[0])
        back_r = msgs.to_residual_list(rm[0])
        assert all(_same(a, b) for a, b in zip(feats, back_f)) and len(back_f) == len(feats), seed
        assert all(_same(a, b) for a, b in zip(res, back_r)) and len(back_r) == len(res), seed
        assert fm[0].block_index == 17


def test_blocks_split_where_names_change():
    """Vectors with other names (another plant wing's stream) go into a message of their own,
    in order."""
    fac = msgs.MessageFactory("rosbags")
    feats, _ = _random_vectors(np.random.default_rng(3))
    other = replace(feats[0], names=("x",), units=("1",), values=np.array([1.0]))
    out = fac.feature_blocks([*feats, other, *feats], block_index=2)
    assert [len(m.index) for m in out] == [len(feats), 1, len(feats)]
    assert [fv.index for m in out for fv in msgs.to_feature_list(m)] == \
        [f.index for f in [*feats, other, *feats]]
    assert fac.feature_blocks([], block_index=0) == []


def test_malformed_blocks_refused_with_the_reason():
    fac = msgs.MessageFactory("rosbags")
    feats, res = _random_vectors(np.random.default_rng(5))
    feats = feats + feats  # at least two vectors
    res = res + res
    m = fac.feature_blocks(feats, block_index=9)[0]
    m.values = m.values[:-1]
    with pytest.raises(ValueError, match="values for"):
        msgs.to_feature_list(m)
    m = fac.feature_blocks(feats, block_index=9)[0]
    m.status = m.status[:-1]
    with pytest.raises(ValueError, match="status"):
        msgs.to_feature_list(m)
    m = fac.residual_blocks(res)[0]
    m.norm = m.norm[:1]
    with pytest.raises(ValueError, match="norm"):
        msgs.to_residual_list(m)
    m = fac.residual_blocks(res)[0]
    m.units = m.units[:-1]
    with pytest.raises(ValueError, match="units"):
        msgs.to_residual_list(m)
