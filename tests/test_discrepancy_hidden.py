"""Hide a catalogue effect in measured data from our diesel plant and require finding it.

Every test: a plant run (seeded operating cycle, sensor noise), one effect applied with
parameters drawn at random within the ranges of :data:`scenarios.RANGES` (the analysis never
sees them), the full analysis (held-out blocks, significance), then: the top finding is that
effect on ``maf``, its fitted parameter is within the stated tolerance, its held-out gain is
above the stated amount. The baseline is identified once on three fault-free runs with other
operating profiles and seeds.
"""

from __future__ import annotations

import numpy as np
import pytest

from fdi_ros.core.discrepancy import DiscrepancyConfig, discover
from fdi_ros.core.types import FaultEvent
from fdi_ros.plants.diesel import discrepancy_scenarios as sc


@pytest.fixture(scope="module")
def baseline(discrepancy_baseline):
    return discrepancy_baseline


def _run(baseline, effect: str, seed: int):
    params = sc.draw(effect, seed)
    if effect == "leak":
        data = sc.plant_record(seed, faults=[FaultEvent(t=0.0, fault="leak_ic_engine",
                                                        size=params["diameter_mm"],
                                                        size_unit="mm")])
    else:
        data = sc.hide(sc.plant_record(seed), effect, params)
    res, ext = discover(data, baseline)
    return params, res, ext, data


def _top(res, effect):
    assert res.verdict == "discrepant", res.message
    top = res.findings[0]
    assert top.effect == effect, [(f.label, round(f.gain_pct, 1)) for f in res.findings]
    assert top.channel == "maf"
    assert top.significant and top.p_adjusted < 0.05
    return top


# (effect, seed, minimum held-out gain [%], check of the fitted parameters). Every effect of
# the catalogue, with a channel, size and record drawn at random, is the randomised self-test's
# (test_discrepancy_selftest.py); this case also checks the extended model it returns.
CASES = [
    ("gain_error", 102, 50.0, lambda h, f: abs(f["gain"] - h["gain"]) < 0.005),
]


@pytest.mark.parametrize("effect,seed,min_gain,check", CASES, ids=[c[0] for c in CASES])
def test_hidden_effect_found(baseline, effect, seed, min_gain, check):
    hidden, res, ext, data = _run(baseline, effect, seed)
    top = _top(res, effect)
    assert check(hidden, top.params), (hidden, top.params)
    assert top.gain_pct > min_gain, top.gain_pct
    assert top.rmse_after < top.rmse_before
    if effect == "gain_error":
        # the extended model is real: saved, loaded, and it predicts the measured channel
        # better than the baseline on a fresh record with the same effect
        fresh = sc.hide(sc.plant_record(seed + 500), effect, hidden)
        before = fresh["maf"] - baseline.predict(fresh)["maf"]
        after = fresh["maf"] - ext.predict(fresh)["maf"]
        assert np.sqrt(np.nanmean(after ** 2)) < 0.5 * np.sqrt(np.nanmean(before ** 2))


@pytest.mark.parametrize("seed", [201])
def test_null_no_significant_finding(baseline, seed):
    res, _ = discover(sc.plant_record(seed), baseline)
    assert res.verdict == "consistent", [(f.label, f.gain_pct, f.p_adjusted)
                                         for f in res.findings]
    assert not res.findings


def test_two_hidden_effects_both_found(baseline):
    g = sc.draw("gain_error", 301)
    h = sc.draw("missing_harmonic", 302)
    data = sc.hide(sc.hide(sc.plant_record(301), "gain_error", g), "missing_harmonic", h)
    res, _ = discover(data, baseline)
    found = {f.effect: f.params for f in res.findings}
    assert "gain_error" in found and "missing_harmonic" in found, list(found)
    assert abs(found["gain_error"]["gain"] - g["gain"]) < 0.01
    assert found["missing_harmonic"]["order"] == h["order"]


def test_reference_models_miss_the_boost_volume_filling(diesel_reference_dir):
    """The project's static eta_V reference (paper eq. 3) has no storage term: on a transient
    cycle the MAF residual follows dp2/dt (air stored in the boost volume)."""
    from fdi_ros.plants.diesel.discrepancy import DieselReferenceBaseline

    # the first step's choice is the finding (later steps only search what is left)
    res, _ = discover(sc.plant_record(201),
                      DieselReferenceBaseline(path=str(diesel_reference_dir)),
                      config=DiscrepancyConfig(max_findings=1))
    top = res.findings[0]
    assert (top.effect, top.params["input"]) == ("input_dependence", "d/dt p2")
    assert top.params["coef"][0] > 0 and top.gain_pct > 30.0


def test_cli_on_a_plant_csv_with_a_saved_baseline(baseline, tmp_path):
    import json

    from fdi_ros.cli import main

    hidden = sc.draw("offset", 401)
    data = sc.hide(sc.plant_record(401, duration_s=40.0), "offset", hidden)
    names = ["t", "alpha"] + list(data.signals)
    table = np.column_stack([data.t, data.alpha] + [data[k] for k in data.signals])
    csv = tmp_path / "measured.csv"
    np.savetxt(csv, table, delimiter=",", header=",".join(names), comments="", fmt="%.9g")
    base = tmp_path / "baseline.json"
    base.write_text(json.dumps(baseline.to_dict()))
    out = tmp_path / "out.json"
    assert main(["discrepancy", "--plant", "diesel", "--measured", str(csv), "--baseline",
                 str(base), "--json", str(out), "--quiet"]) == 0
    doc = json.loads(out.read_text())
    top = doc["findings"][0]
    assert (top["effect"], top["channel"]) == ("offset", "maf")
    assert top["params"]["offset"] == pytest.approx(hidden["offset"], abs=0.3)
    assert doc["verdict"] == "discrepant" and top["significant"]
