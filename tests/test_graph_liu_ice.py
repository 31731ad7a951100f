"""The real engine through the live graph: a benchmark file imported into a bag, replayed
into separate node processes over DDS (five lifecycle residual nodes, the supervisor), gives
the same detection and isolation, to the sample, as the offline diagnosis of the same bag."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fdi_ros.cli import main
from fdi_ros.livegraph import run_live

pytestmark = [pytest.mark.graph]

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config" / "liu_ice.yaml"
DATA = ROOT.parent / "shared" / "data" / "liu_ice"
FILE = DATA / "ftp75city2_f_waf_090.csv"


@pytest.mark.skipif(not FILE.is_file(), reason=f"LiU-ICE data {FILE} absent")
def test_replayed_bag_live_equals_offline(tmp_path):
    assert main(["build-bank", str(CONFIG)]) == 0   # identifies the residual set if missing
    bag = tmp_path / "waf_090"
    assert main(["import", str(FILE), "--mapping", str(ROOT / "config" / "mappings" /
                                                       "liu_ice.yaml"), "--out", str(bag)]) == 0
    out = tmp_path / "offline.json"
    assert main(["diagnose", str(bag), "--config", str(CONFIG), "--json", str(out)]) == 0
    off = json.loads(out.read_text())
    assert off["fault_truth"][0]["fault"] == "f_waf"
    assert off["isolated_faults"] == ["f_waf"] and off["detection_delay_s"] <= 5.0, off
    lines: list[str] = []
    run, _ = run_live(CONFIG, replay=bag, realtime_factor=4.0, timeout_s=150,
                      log=lines.append)
    live = run.as_dict()
    assert live["segments"] == off["segments"], lines
    assert live["isolated_faults"] == off["isolated_faults"], lines
    assert live["isolation_s"] == pytest.approx(off["isolation_time_s"], abs=1e-3), lines
    assert live["detection_s"] == pytest.approx(off["detection_time_s"], abs=1e-3), lines
    assert live["cleared_detections_s"] == off["cleared_detections_s"], lines
    assert live["lifecycle_states_after"]["f_waf"] == "active"
    assert live["lifecycle_states_after"]["f_pim"] == "inactive"
