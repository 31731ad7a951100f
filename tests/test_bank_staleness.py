"""When the bank builder rebuilds: a reference model set it made is stale once one of its
identification or calibration scenarios changes (one identified by hand on other data is
kept), and the hypotheses fitted on a reference rebuilt now are rebuilt in the same run."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

from fdi_ros.plants.diesel import identify, wing
from fdi_ros.plants.diesel.identify import FEATURES_VERSION
from fdi_ros.plants.diesel.reference import ACTUATOR_TOL


def _reference(d: Path, sources: str | None) -> None:
    d.mkdir(parents=True, exist_ok=True)
    info = {"regime": "egr_closed_flaps_open", "further_regimes": True,
            "features": FEATURES_VERSION}
    if sources is not None:
        info["sources"] = sources
    ranges = [{"name": k, "lo": 0.0, "hi": 1.0, "tol": v} for k, v in ACTUATOR_TOL.items()]
    (d / wing.REFERENCE_FILES[0]).write_text(json.dumps({"validity": {"ranges": ranges},
                                                         "info": info}))
    (d / wing.REFERENCE_FILES[1]).write_text("{}")


def test_a_changed_scenario_makes_the_builders_reference_stale(tmp_path, monkeypatch):
    scenarios = [tmp_path / f"s{i}.yaml" for i in range(3)]
    for i, f in enumerate(scenarios):
        f.write_text(f"name: s{i}\n")
    monkeypatch.setattr(identify, "reference_sources", lambda resolve=Path: [str(f) for f in
                                                                            scenarios])
    digest = identify.digest_of(scenarios)
    _reference(tmp_path / "built", digest)
    _reference(tmp_path / "by_hand", None)
    assert wing._reference_current(tmp_path / "built")
    assert wing._reference_current(tmp_path / "by_hand")
    scenarios[1].write_text("name: s1\nseed: 2\n")   # an identification scenario edited
    assert not wing._reference_current(tmp_path / "built")
    assert wing._reference_current(tmp_path / "by_hand")   # not the builder's: kept
    assert identify.digest_of(scenarios) != digest


def test_hypotheses_on_a_rebuilt_reference_are_rebuilt_with_it(tmp_path, monkeypatch):
    ref = tmp_path / "ref"
    entries = [SimpleNamespace(id="nominal", faults=frozenset(), model={
                   "type": "diesel_reference", "path": str(ref)}),
               SimpleNamespace(id="leak_ic_engine", faults=frozenset({"leak_ic_engine"}),
                               model={"type": "diesel_fault_hypothesis", "path": str(ref),
                                      "hypothesis": str(tmp_path / "h")})]
    cfg = SimpleNamespace(bank=entries, resolve_spec=lambda m: dict(m), resolve=Path)
    monkeypatch.setattr(wing, "_hypothesis_current", lambda spec, fault: True)
    for current, want in ((True, []), (False, ["nominal", "leak_ic_engine"])):
        monkeypatch.setattr(wing, "_reference_current", lambda d, r=Path, c=current: c)
        assert [mid for mid, _ in wing._missing(cfg)] == want
