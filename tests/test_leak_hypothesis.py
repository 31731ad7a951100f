"""A leaky EGR valve's hypothesis: its eta_V effect with the valve closed is the exhaust side's
leak flow across the valve (p3 - p2 sets its size and sign), times one coefficient fitted on
the identification's faulty segments: a known coefficient is recovered from segments drawn at
random, an effect that does not follow the flow is refused (the map stays), and the bank's
hypothesis evaluates it alike segment by segment and over a stream."""

from __future__ import annotations

import random

import numpy as np
import pytest

from fdi_ros.core.types import FeatureVector, ResidualVector


def _segments(models, rng: np.random.Generator, n: int) -> list[FeatureVector]:
    from fdi_ros.plants.diesel.symptoms import model_features

    names = tuple(dict.fromkeys((*model_features(models), "n", "rho2", "T2", "fuel",
                                 "egr_cmd", "vgt", "T2_rate", "vgt_rate", "eta_v")))
    draw = {"n": (1200.0, 3500.0), "rho2": (1.2, 2.3), "T2": (310.0, 345.0),
            "fuel": (8.0, 42.0), "vgt": (0.2, 0.9), "eta_v": (0.85, 0.95)}
    out = []
    for i in range(n):
        v = {k: float(rng.uniform(*draw[k])) if k in draw else 0.0 for k in names}
        out.append(FeatureVector(plant="diesel", index=i, t_start=0.02 * i,
                                 t_end=0.02 * (i + 1), alpha_start=0.0, valid=True, status="",
                                 names=names, units=("",) * len(names),
                                 values=np.array([v[k] for k in names])))
    return out


def test_leak_coefficient_drawn_at_random_is_recovered(diesel_reference_dir):
    from fdi_ros.plants.diesel.reference import ReferenceModelSet
    from fdi_ros.plants.diesel.symptoms import (
        _exhaust_keys,
        exhaust_side,
        fit_leak_effect,
        load_symptom_config,
    )

    seed = random.randrange(2**32)
    rng = np.random.default_rng(seed)
    models = ReferenceModelSet.load(diesel_reference_dir)
    cfg = load_symptom_config(diesel_reference_dir)
    flow = exhaust_side(models)
    assert flow is not None
    feats = _segments(models, rng, 600)
    d = models.compensate({k: np.array([fv.get(k) for fv in feats])
                           for k in _exhaust_keys(models)})
    q = flow.closed_valve_leak(d, models.models["eta_v"].predict(
        np.column_stack([d["n"], d["rho2"]])))
    assert (q > 0).any() and (q < 0).any(), seed   # both ways across the valve
    c_true = float(rng.uniform(2e-6, 2e-5)) * float(rng.choice([-1.0, 1.0]))
    size = float(rng.uniform(1.0, 8.0))
    centre, thr = cfg.statistics(models.regime)
    j = cfg.names.index("r_eta")

    def rvs(z_eta: np.ndarray) -> list[ResidualVector]:
        Z = rng.normal(0.0, 0.1, (len(feats), len(cfg.names)))
        Z[:, j] = z_eta
        return [ResidualVector("nominal", fv.index, fv.t_end, True, "", cfg.names,
                               ("",) * len(cfg.names), centre + thr * z, 0.0, models.regime)
                for fv, z in zip(feats, Z)]

    effect = c_true * q * size
    noise = rng.normal(0.0, 0.05 * np.std(effect), len(feats))
    c = fit_leak_effect(models, cfg, feats, rvs(effect + noise), size=size)
    assert c == pytest.approx(c_true, rel=0.03), seed
    # an effect of the same size that does not follow the flow: refused
    assert fit_leak_effect(models, cfg, feats, rvs(rng.permutation(effect)), size=size) \
        is None, seed
    # too few segments: refused
    assert fit_leak_effect(models, cfg, feats[:50], rvs(effect)[:50], size=size) is None


def test_bank_leaky_valve_hypothesis_uses_the_exhaust_side(diesel_bank):
    """The bank's leaky-valve hypothesis carries the coefficient (its identification's effect
    follows the leak flow), and its base-regime eta_V effect is that flow times it."""
    from fdi_ros.core.graphconfig import load_graph_config
    from fdi_ros.core.residual_models import load_residual_model

    cfg = load_graph_config(diesel_bank)
    hyp = load_residual_model(cfg.resolve_spec(cfg.entry("egr_leaky").model),
                              model_id="egr_leaky")
    assert hyp.eta_leak is not None and np.isfinite(hyp.eta_leak)
    rng = np.random.default_rng(random.randrange(2**32))
    feats = _segments(hyp.models, rng, 50)
    G = hyp.effects(feats, hyp.models.regime)
    d, eta = hyp._closed_side(feats)
    j = hyp.config.names.index("r_eta")
    np.testing.assert_allclose(G[:, j], hyp.eta_leak * hyp._flow.closed_valve_leak(d, eta))
    # the maps give the other residuals, and the EGR-open regimes' effects stay the maps'
    others = [k for k in range(len(hyp.config.names)) if k != j]
    np.testing.assert_allclose(G[:, others], hyp.direction(
        [[fv.get(k) for k in hyp.inputs] for fv in feats])[:, others])
    # a recording without a feature the exhaust side reads (older bags lack vgt_rate): the
    # map's effect, not an error
    strip = [FeatureVector(**{**fv.__dict__,
                              "names": tuple(k for k in fv.names if k != "vgt_rate"),
                              "units": tuple(u for k, u in zip(fv.names, fv.units)
                                             if k != "vgt_rate"),
                              "values": np.array([v for k, v in zip(fv.names, fv.values)
                                                  if k != "vgt_rate"])}) for fv in feats]
    assert hyp.leak_effect(strip, hyp.models.regime) is None
    np.testing.assert_allclose(hyp.effects(strip, hyp.models.regime), hyp.direction(
        [[fv.get(k) for k in hyp.inputs] for fv in strip]))
