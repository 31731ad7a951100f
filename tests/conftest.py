"""Test environment: loopback-only DDS and a ROS_DOMAIN_ID of this test session's own.

Set before anything imports rclpy so that every node started by a test, in this process or in
a child process, discovers only peers on 127.0.0.0/8 and in its own domain.
"""

from __future__ import annotations

import os

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
os.environ.setdefault("MPLBACKEND", "Agg")
# The supervisor's fault memory and snapshot bags: a directory of this session's own, so tests
# never leave state in the checkout nor see faults a previous run confirmed.
os.environ.setdefault("FDI_ROS_STATE_DIR", __import__("tempfile").mkdtemp(prefix="fdi_state_"))


from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def diesel_bank() -> Path:
    """The diesel graph's model bank (reference models, thresholds, fault hypotheses), built
    once by the same code as `fdi-ros build-bank` when missing or stale; returns the config."""
    from fdi_ros.plants import ensure_bank

    config = ROOT / "config" / "diesel.yaml"
    ensure_bank(config, progress=False, log=lambda s: None)
    return config


@pytest.fixture(scope="session")
def diesel_reference_dir(diesel_bank: Path) -> Path:
    return ROOT / "build" / "models" / "diesel"
