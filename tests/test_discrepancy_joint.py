"""Joint hypotheses over several residuals, residual sets, change points: oracle tests.

A synthetic plant with two relations that share a sensor: ``y1 = a u v`` and ``y2 = b u / w``
(both measured; ``u``, ``v``, ``w`` read by the models). A gain of ``u`` moves both residuals,
a gain of ``y1`` only the first, a gain of ``v`` only the first: scored on both residuals at
once, the hidden one is named, with its size.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from fdi_ros.core.discrepancy import DiscrepancyConfig, discover
from fdi_ros.core.discrepancy.context import build_contexts
from fdi_ros.core.discrepancy.effects import ratio_change_point
from fdi_ros.core.discrepancy.joint import hypotheses
from fdi_ros.core.measured import Measured, segments_from_gaps
from fdi_ros.core.residualset import PressureMapModel, ResidualSet, ThrottleFlowModel


@dataclass(frozen=True)
class TwoRelations:
    """``y1 = 2 u v``, ``y2 = 3 u / w``: the model knows both exactly."""

    inputs = ("u", "v", "w")
    channels = ("y1", "y2")
    uses = {"y1": ("u", "v"), "y2": ("u", "w")}

    def predict(self, data: Measured) -> dict[str, np.ndarray]:
        return {"y1": 2.0 * data["u"] * data["v"], "y2": 3.0 * data["u"] / data["w"]}

    def region(self, data: Measured) -> dict[str, np.ndarray]:
        return {"u": data["u"], "v": data["v"]}


def _record(seed: int, *, hide: str | None = None, gain: float = 1.0) -> Measured:
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 120.0, 0.05)

    def smooth(lo: float, hi: float) -> np.ndarray:
        x = sum(rng.uniform(0.5, 1) * np.sin(2 * np.pi * t / rng.uniform(4, 40)
                                               + rng.uniform(0, 6.3)) for _ in range(4))
        x = (x - x.min()) / (x.max() - x.min())
        return lo + (hi - lo) * x

    sig = {"u": smooth(1.0, 3.0), "v": smooth(2.0, 5.0), "w": smooth(1.0, 2.0),
           "z": smooth(0.0, 1.0)}
    sig["y1"] = 2.0 * sig["u"] * sig["v"] + rng.normal(0, 0.05, t.size)
    sig["y2"] = 3.0 * sig["u"] / sig["w"] + rng.normal(0, 0.05, t.size)
    if hide:
        sig[hide] = sig[hide] * gain
    return Measured(t=t, signals=sig, units=dict.fromkeys(sig, "1"),
                    segment=segments_from_gaps(t, 0.2), source=f"two relations {seed}",
                    mapped=tuple(sig))


def test_a_sensor_read_by_two_relations_is_one_hypothesis():
    ctxs = build_contexts(_record(1), TwoRelations(), sensors=True)
    hs = hypotheses(ctxs, effects=("gain_error", "offset"), onset=False)
    u_gain = [h for h in hs if h.carrier == "u" and h.effect == "gain_error"]
    assert len(u_gain) == 1 and set(u_gain[0].views) == {"y1", "y2"}
    v_gain = next(h for h in hs if h.carrier == "v" and h.effect == "gain_error")
    assert v_gain.views == ("y1",)
    y1_gain = next(h for h in hs if h.carrier == "y1" and h.effect == "gain_error")
    assert y1_gain.views == ("y1",)


@pytest.mark.parametrize("gain", [1.08, 0.94])
def test_a_sensor_both_relations_read_is_named_alone(gain):
    """A gain of ``u`` looks on the first residual exactly like a gain of ``v`` or of ``y1``
    (the product is all it sees), on the second like a gain of ``w`` or ``y2``: only both
    residuals at once tell that ``u`` is wrong, and nothing else explains both."""
    res, _ = discover(_record(7, hide="u", gain=gain), TwoRelations(),
                      config=DiscrepancyConfig(effects=("gain_error", "offset", "drift"),
                                               onset=False))
    top = res.findings[0]
    assert (top.effect, top.channel) == ("gain_error", "u"), [
        (f.label, f.channel) for f in res.findings]
    assert top.params["gain"] == pytest.approx(gain, abs=0.003)
    assert set(top.residuals) == {"y1", "y2"}
    assert len(res.findings) == 1 and not top.alternatives


@pytest.mark.parametrize("hide,other,gain,other_gain", [("v", "y1", 0.93, 1 / 0.93),
                                                        ("y1", "v", 1.06, 1 / 1.06),
                                                        ("w", "y2", 1.07, 1.07)])
def test_a_sensor_one_relation_reads_is_an_honest_tie(hide, other, gain, other_gain):
    """A gain of ``v`` and the reciprocal gain of ``y1`` move the first residual alike and
    the second not at all (``w`` divides: its gain is ``y2``'s own): reported as a tie, each
    with its size and what would separate them."""
    res, _ = discover(_record(7, hide=hide, gain=gain), TwoRelations(),
                      config=DiscrepancyConfig(effects=("gain_error", "offset", "drift"),
                                               onset=False))
    top = res.findings[0]
    named = {top.channel: top.params} | {a["channel"]: a["params"] for a in top.alternatives
                                         if a["effect"] == "gain_error"}
    assert top.effect == "gain_error" and {hide, other} <= set(named), named
    assert named[hide]["gain"] == pytest.approx(gain, abs=0.003)
    assert named[other]["gain"] == pytest.approx(other_gain, abs=0.003)
    tie = next(a for a in top.alternatives if a["channel"] in (hide, other))
    assert tie["why"] and tie["separate_by"]


def test_null_two_relations_consistent():
    res, _ = discover(_record(11), TwoRelations())
    assert res.verdict == "consistent", [(f.label, f.channel) for f in res.findings]


def test_ratio_change_point_sees_a_gain_at_low_load():
    """A 10 % gain from t = 40 s while the regressor is 20 times smaller than later: the ratio
    steps at 40 s; a squared-error fit of the absolute residual would wait for the load."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 100.0, 0.05)
    g = np.where(t < 55.0, 1.0, 20.0) + rng.uniform(0, 0.1, t.size)
    r = np.where(t >= 40.0, 0.1, 0.0) * g + rng.normal(0, 0.02, t.size)
    on = ratio_change_point(r, g, t, np.ones(t.size, bool))
    assert on == pytest.approx(40.0, abs=0.5)


def test_throttle_and_pressure_map_recover_known_coefficients():
    """Oracle: data made by the models themselves (known coefficients) are fitted back."""
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 200.0, 0.05)
    theta = 2.0 + 18.0 * (0.5 + 0.5 * np.sin(2 * np.pi * t / 37.0)) ** 2
    p_ic = 101325.0 + 20000.0 * (0.5 + 0.5 * np.sin(2 * np.pi * t / 23.0 + 1.0))
    p_im = 25000.0 + 40000.0 * (0.5 + 0.5 * np.sin(2 * np.pi * t / 31.0 + 2.0))
    T = 300.0 + 10.0 * np.sin(2 * np.pi * t / 90.0)
    sig = {"throttle": theta, "p_ic": p_ic, "p_im": p_im, "T_im": T,
           "n": 1500.0 + 1000.0 * (0.5 + 0.5 * np.sin(2 * np.pi * t / 17.0)),
           "p_amb": np.full(t.size, 101325.0), "wastegate": rng.uniform(0, 1, t.size)}
    data = Measured(t=t, signals=dict(sig, maf=np.zeros(t.size)),
                    units=dict.fromkeys(sig, "1"), segment=np.zeros(t.size, int))
    truth = ThrottleFlowModel(coef=(1e-5, 4e-5, 1e-4, -3e-5), volume_l=12.0,
                              position_range=(float(theta.min()), float(theta.max())))
    sig["maf"] = truth.predict(data)["maf_throttle"]
    data = Measured(t=t, signals=sig, units=dict.fromkeys(sig, "1"),
                    segment=np.zeros(t.size, int))
    fit = ThrottleFlowModel().fit(data)
    np.testing.assert_allclose(fit.coef, truth.coef, rtol=1e-6, atol=1e-12)
    assert fit.volume_l == pytest.approx(12.0, rel=1e-6)
    pmap = PressureMapModel(regressors=("n", "wastegate"), degree=2, max_lag_s=3.0,
                            coef=(0.01, 0.12, -0.03, 0.02, 0.01, -0.01),
                            ranges=((float(sig["n"].min()), float(sig["n"].max())), (0.0, 1.0)),
                            lag_s=0.8)
    sig["p_ic"] = pmap.predict(data)["p_ic"]
    data = Measured(t=t, signals=sig, units=dict.fromkeys(sig, "1"),
                    segment=np.zeros(t.size, int))
    got = PressureMapModel(regressors=("n", "wastegate"), degree=2, max_lag_s=3.0).fit(data)
    assert got.lag_s == pytest.approx(0.8, rel=0.1)  # on the identification grid
    p = got.predict(data)["p_ic"]
    assert np.sqrt(np.mean((p - sig["p_ic"]) ** 2)) < 0.002 * 101325.0
    both = ResidualSet(models=(fit, got), checks=("p_ic",))
    back = ResidualSet.from_dict(both.to_dict())
    assert back == both
    assert both.measures == {"maf_throttle": "maf", "p_ic": "p_ic"}


@dataclass(frozen=True)
class OneRelationChecked(TwoRelations):
    """The same plant with the second relation a check: it proposes nothing, it scores the
    leading explanations of the first."""

    checks = ("y2",)


def test_report_evidence_is_the_joint_scoring_the_choice_was_made_on(tmp_path):
    """A gain of ``u`` on the first relation alone is a gain of ``v`` or of ``y1`` too; the
    check relation (which reads ``u`` but not ``v``) decides. The report's evidence figure
    sets the top finding against the runner-up of that joint scoring, not of the first
    relation alone, where the two are equal block by block."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fdi_ros.core.discrepancy.report import _evidence_figure, runner_up

    res, _ = discover(_record(11, hide="u", gain=1.07), OneRelationChecked(),
                      config=DiscrepancyConfig(effects=("gain_error", "offset", "drift"),
                                               onset=False))
    top = res.findings[0]
    assert (top.effect, top.channel) == ("gain_error", "u")
    first, second, joint = runner_up(res)
    assert joint and (first.label, first.channel) == (top.label, top.channel)
    assert (second.effect, second.channel) != ("gain_error", "u")
    # the runner-up is worse where the check relation reads u: over the blocks, clearly
    assert np.nanmean(second.mse_blocks) > 1.5 * np.nanmean(first.mse_blocks)
    # on the first relation alone the best other explanation was as good (a tie there)
    alone = [c for c in res.candidates if (c.effect, c.channel) != ("gain_error", "u")]
    best_alone = min(alone, key=lambda c: float(np.nanmean(c.mse_blocks)))
    assert np.nanmean(best_alone.mse_blocks) < 1.2 * np.nanmean(
        next(c for c in res.candidates if c.label == top.label
             and c.channel == top.channel).mse_blocks)
    name, caption = _evidence_figure(plt, tmp_path, res)
    assert (tmp_path / name).is_file() and "every residual" in caption
