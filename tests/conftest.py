"""Test environment: loopback-only DDS and a ROS_DOMAIN_ID of this test session's own.

Set before anything imports rclpy so that every node started by a test, in this process or in
a child process, discovers only peers on 127.0.0.0/8 and in its own domain.

The model banks (diesel reference and hypotheses, turbofan TS models) are identified by a
background process started once the tests are collected, while the test modules that need no
bank run first; a bank fixture then waits on the bank's lock (``fdi_ros.plants.ensure_bank``)
and finds it built. The tests are the same whatever the order; only the wall time changes.
"""

from __future__ import annotations

import os

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
os.environ.setdefault("MPLBACKEND", "Agg")
# The supervisor's fault memory and snapshot bags: a directory of this session's own, so tests
# never leave state in the checkout nor see faults a previous run confirmed.
os.environ.setdefault("FDI_ROS_STATE_DIR", __import__("tempfile").mkdtemp(prefix="fdi_state_"))


import subprocess  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
# bank fixture -> the configuration whose bank it needs
BANKS = {"diesel_bank": "config/diesel.yaml", "diesel_reference_dir": "config/diesel.yaml",
         "turbofan_bank": "config/turbofan.yaml"}
_BUILD = "import sys; from fdi_ros.plants import ensure_bank\n" \
         "for c in sys.argv[1:]: ensure_bank(c, progress=False)"
_background: list[subprocess.Popen] = []


@pytest.hookimpl(trylast=True)  # after the deselection by -m / -k
def pytest_collection_modifyitems(session, config, items):
    """Modules that need no bank first (kept whole: module fixtures are set up once), and the
    banks the others need identified meanwhile, in one background process, in order of use;
    modules marked ``beside_graphs`` last."""
    needs: dict[str, list[str]] = {}
    for it in items:
        needs.setdefault(it.module.__name__, [])
        needs[it.module.__name__] += [BANKS[f] for f in it.fixturenames if f in BANKS]
    # ... and modules marked beside_graphs last: scripts/test.sh runs them in the graph
    # session, after the graphs, beside the other session's last modules
    items.sort(key=lambda it: (it.get_closest_marker("beside_graphs") is not None,
                               bool(needs[it.module.__name__])))
    order = list(dict.fromkeys(c for it in items for c in needs[it.module.__name__]))
    # `make test` (scripts/test.sh) runs the graph tests and the rest as two sessions at once:
    # the graph session builds the banks, the other one's bank fixtures wait for them
    builder = os.environ.get("FDI_ROS_TEST_BANK_BUILDER", "1") != "0"
    if order and builder and not config.getoption("collectonly"):
        log = (ROOT / "build" / "bank_background.log")
        log.parent.mkdir(parents=True, exist_ok=True)
        with log.open("w") as fh:
            _background.append(subprocess.Popen([sys.executable, "-c", _BUILD, *order],
                                                cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT))


def pytest_sessionfinish(session, exitstatus):
    for proc in _background:
        if proc.poll() is None:  # the session ended early (deselected, interrupted)
            proc.terminate()
            proc.wait(30)
        elif proc.returncode:
            print(f"\nbackground bank identification failed (rc {proc.returncode}); its log: "
                  f"{ROOT / 'build' / 'bank_background.log'}", file=sys.stderr)


def _bank(fixture: str) -> Path:
    """The configuration of ``fixture``'s bank, its models identified by the same code as
    `fdi-ros build-bank` when missing or stale (waiting on the background build's lock)."""
    from fdi_ros.plants import ensure_bank

    config = ROOT / BANKS[fixture]
    ensure_bank(config, progress=False, log=lambda s: None)
    return config


@pytest.fixture(scope="session")
def diesel_bank() -> Path:
    """The diesel graph's model bank (reference models, thresholds, fault hypotheses)."""
    return _bank("diesel_bank")


@pytest.fixture(scope="session")
def turbofan_bank() -> Path:
    """The turbofan graph's TS node models."""
    return _bank("turbofan_bank")


@pytest.fixture(scope="session")
def diesel_reference_dir(diesel_bank: Path) -> Path:
    return ROOT / "build" / "models" / "diesel"


@pytest.fixture(scope="session")
def discrepancy_baseline():
    """The diesel discrepancy baseline identified on three fault-free plant runs (one fit for
    every module that analyses hidden effects)."""
    from fdi_ros.plants.diesel import discrepancy_scenarios as sc

    return sc.diesel_baseline(seed=1000, runs=3, duration_s=90.0)
