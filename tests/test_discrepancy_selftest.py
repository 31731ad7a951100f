"""The randomised self-test: random hidden effects found, nulls left alone.

The seed is drawn when the test runs and printed (``-s`` shows it; a failure message repeats
it), so no fixed set of cases can be tuned to; replay with
``fdi-ros discrepancy selftest --n 5 --nulls 1 --seed S --json OUT``.
"""

from __future__ import annotations

import secrets

import pytest

from fdi_ros.cli import main
from fdi_ros.plants.diesel import discrepancy_scenarios as sc
from fdi_ros.plants.diesel.discrepancy_selftest import (
    DETECTABLE,
    EFFECTS,
    LOCAL_SHARE,
    draw_case,
    run_selftest,
    summarise,
)


@pytest.fixture(scope="module")
def baseline(discrepancy_baseline):
    return discrepancy_baseline


def test_random_cases_found_and_nulls_clean(baseline):
    seed = secrets.randbelow(2**31)
    print(f"selftest seed {seed}")
    # five hidden effects and one null case (the relevance floor keeps the baseline's own
    # small wanders, real but below 1 % of reading, from being named)
    out = run_selftest(5, seed, n_null=1, baseline=baseline)
    why = f"seed {seed}: misses {out['misses']}"
    # at most one miss in five (the acceptance run of 60 + 10 is reported in the docs); a
    # reported tie that contains the truth (e.g. a lag or a dead time of an input sensor,
    # which nothing the model predicts separates) is not a miss
    assert out["n_cases"] == 5 and out["n_nulls"] == 1
    assert out["top1_or_tie"] >= 0.8, why
    assert out["false_discoveries"] == 0, f"seed {seed}: {out['cases']}"
    pe = out["parameter_rel_error"]
    assert pe["within_tolerance"] >= pe["of"] - 1, why
    rows = out["confusion"]["rows"]
    assert sum(sum(r.values()) for r in rows.values()) == 6


def test_draw_is_log_uniform_within_the_stated_ranges():
    import numpy as np

    rng = np.random.default_rng(secrets.randbelow(2**31))
    for eff in EFFECTS:
        for _ in range(20):
            p = draw_case(rng, eff)
            key = "gain" if eff == "gain_error" else None
            v = abs(p[key or DETECTABLE[eff][0]])
            _, lo, hi = DETECTABLE[eff]
            if eff == "gain_error":
                v = max(v, 1.0 / v)
            assert lo * (1 - 1e-12) <= v <= hi * (1 + 1e-12), (eff, p)
            if eff == "local_region":
                assert LOCAL_SHARE[0] <= p["share"] <= LOCAL_SHARE[1], p


def test_local_band_placed_where_the_window_spends_its_drawn_share():
    """A hidden local offset's speed band covers the drawn share of the window's samples
    (within what 10 rpm steps allow), on speed records drawn at random."""
    import numpy as np

    from fdi_ros.plants.diesel.discrepancy_selftest import place_band

    seed = secrets.randbelow(2**31)
    rng = np.random.default_rng(seed)
    for _ in range(20):
        t = np.linspace(0.0, 60.0, 3000)
        n = 2000 + np.cumsum(rng.normal(0, 15, t.size)) + 400 * np.sin(t / rng.uniform(3, 20))
        share, width = rng.uniform(*LOCAL_SHARE), rng.uniform(400, 700)
        lo, hi = place_band(n, width, share)
        assert hi - lo >= width - 1e-9
        got = np.mean((n >= lo) & (n < hi))
        assert got == pytest.approx(share, abs=0.05), (seed, got, share)


def test_summary_counts_confusions_and_false_discoveries():
    from fdi_ros.plants.diesel.discrepancy_selftest import CaseResult

    cases = [CaseResult(0, "offset", "maf", {"offset": 4.0}, "offset", "maf", {"offset": 4.4}),
             CaseResult(1, "drift", "maf", {"rate_per_s": 0.1}, "gain_error", "maf", {},
                        tie=["drift"]),
             CaseResult(2, None, "maf", {}, "offset", "maf", {"offset": 1.0})]
    s = summarise(cases)
    assert s["top1_effect_and_channel"] == 0.5
    assert s["false_discoveries"] == 1
    assert s["ties_containing_truth"] == 1
    assert s["confusion"]["rows"]["drift"]["gain_error"] == 1
    assert s["parameter_rel_error"]["max"] == pytest.approx(0.1)


def test_cli_needs_its_arguments(capsys, tmp_path):
    assert main(["discrepancy", "--plant", "diesel"]) == 2
    assert "--measured" in capsys.readouterr().err
    assert main(["discrepancy", "selftest", "--n", "-1", "--seed", "1", "--json",
                 str(tmp_path / "o.json")]) == 2
    assert not (tmp_path / "o.json").exists()


def test_warm_up_dependence_beats_a_change_over_time(baseline):
    """A channel depending on a smooth warm-up temperature looks like a drift or a gain that
    changes in time; the measured column explains it with fewer parameters and is named."""
    import numpy as np

    from fdi_ros.core.discrepancy import DiscrepancyConfig, discover
    from fdi_ros.core.measured import Measured

    seed = secrets.randbelow(10**6)
    print(f"warm-up seed {seed}")
    rng = np.random.default_rng(seed)
    rec = sc.plant_record(seed % 5000 + 3000, duration_s=60.0)
    tau = rng.uniform(15.0, 40.0)
    warm = 290.0 + rng.uniform(30.0, 70.0) * (1.0 - np.exp(-(rec.t - rec.t[0]) / tau))
    coef = rng.choice([-1.0, 1.0]) * rng.uniform(4.0, 8.0)
    sig = dict(rec.signals, T_coolant=warm)
    sig["maf"] = sig["maf"] + coef * (warm - warm.mean()) / warm.std()
    data = Measured(t=rec.t, signals=sig, units=dict(rec.units, T_coolant="K"),
                    alpha=rec.alpha, segment=rec.segment, source="warm-up", mapped=rec.mapped)
    # the first step's choice (later steps only search what is left)
    res, _ = discover(data, baseline, config=DiscrepancyConfig(max_findings=1))
    top = res.findings[0]
    assert (top.effect, top.params.get("input")) == ("input_dependence", "T_coolant"), (
        seed, [(f.label, round(f.gain_pct, 1)) for f in res.findings])
