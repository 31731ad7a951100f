"""`fdi-ros diagnose` on the committed sample bag, and clear errors for bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "bags" / "diesel_leak_5mm_features"


def _diagnose(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fdi_ros.cli", "diagnose", *args], cwd=ROOT,
                          capture_output=True, text=True)


def test_sample_bag_diagnosed(diesel_bank):
    r = _diagnose(str(SAMPLE))
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["fault_truth"][0]["fault"] == "leak_ic_engine"
    assert out["isolated_faults"] == ["leak_ic_engine"]
    assert 0 < out["detection_delay_s"] <= 5 * 0.015 + 1e-9  # within 5 segments
    assert out["isolation_delay_s"] < 2.0
    assert out["cleared_detections_s"] == []
    assert out["realtime_factor"] > 1.0
    assert 0 < out["valid_segments"] <= out["segments"]
    assert out["coverage"] == round(out["valid_segments"] / out["segments"], 4)
    assert sum(out["not_valid_reasons"].values()) <= out["segments"] - out["valid_segments"]
    assert all("#" in k or not any(c.isdigit() for c in k) for k in out["not_valid_reasons"])


def test_bad_bags_clear_errors(tmp_path: Path):
    r = _diagnose(str(tmp_path / "missing"))
    assert r.returncode == 2 and "does not exist" in r.stderr
    (tmp_path / "empty").mkdir()
    r = _diagnose(str(tmp_path / "empty"))
    assert r.returncode == 2 and "not a rosbag2 directory" in r.stderr
    assert "Traceback" not in r.stderr
