"""A plant is a wing: a first-order tank with a sensor-offset fault (tests/tank_wing.py), added
with no edit to fdi_ros, is diagnosed by ``fdi-ros diagnose`` and runs as a live two-node graph
(plant node + preprocessor node, separate processes over DDS) with a fault injected at run
time. The wing is found through ``FDI_ROS_WINGS``, as every process of a graph would find it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent
WINGS = "tank=tank_wing"
ONSET = 8.0       # s
OFFSET = 0.2      # m, the injected sensor offset (about 7 thresholds of the nominal model)
CONFIG = """
fdi_graph:
  plant: tank
  t0_s: 0.5
  symptoms:
    model: nominal
    config: {names: [r_y], centre: [0.0], threshold: [0.03], scale: [0.005],
             filter_len: 3, debounce_on: 2, debounce_off: 4}
    table: fst.yaml
    table_key: tank
  bank:
    - {id: nominal, faults: [], model: {type: tank_level, threshold: 0.03}}
    - {id: sensor_offset, faults: [sensor_offset], model: {type: tank_offset, threshold: 0.03}}
fdi_plant:
  ros__parameters: {plant: tank}
fdi_preprocessor:
  ros__parameters: {plant: tank}
"""
FST = "symptoms: [s_y]\ntables:\n  tank:\n    sensor_offset: '+'\n"


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["FDI_ROS_WINGS"] = WINGS
    env["PYTHONPATH"] = os.pathsep.join([str(HERE), env.get("PYTHONPATH", "")])
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    return env


@pytest.fixture
def tank(monkeypatch):
    monkeypatch.setenv("FDI_ROS_WINGS", WINGS)
    from fdi_ros import plants

    return plants.get_wing("tank")


def test_registry_finds_the_wing_and_its_kinds(tank):
    from fdi_ros import plants
    from fdi_ros.core.residual_models import registered_types
    from fdi_ros.core.types import FaultEvent

    assert "tank" in plants.known_plants() and tank.name == "tank"
    assert {"tank_level", "tank_offset"} <= set(registered_types())
    with pytest.raises(ValueError, match="unknown tank fault"):
        plants.validate_fault("tank", FaultEvent(t=0.0, fault="leak", size=1.0))
    with pytest.raises(ValueError, match="unknown plant"):
        plants.get_wing("no_such_plant")


def test_tank_through_fdi_ros_diagnose(tank, tmp_path):
    from fdi_ros import bag, plants
    from fdi_ros.core.types import FaultEvent

    seed = int(np.random.default_rng().integers(1_000_000))
    print(f"seed {seed}")
    runner = plants.make_runner("tank", {"duration_s": 16.0}, seed=seed)
    runner.inject(FaultEvent(t=ONSET, fault="sensor_offset", size=OFFSET, size_unit="m"))
    with bag.BagWriter(tmp_path / "bag") as w:
        while not runner.done:
            w.write_block(runner.next_block())
            for ev in runner.pop_truth():
                w.write_fault(ev)
    (tmp_path / "tank.yaml").write_text(CONFIG)
    (tmp_path / "fst.yaml").write_text(FST)
    r = subprocess.run([sys.executable, "-m", "fdi_ros.cli", "diagnose", str(tmp_path / "bag"),
                        "--config", str(tmp_path / "tank.yaml"), "--json"],
                       capture_output=True, text=True, env=_env(), cwd=tmp_path, timeout=300)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["plant"] == "tank" and out["segments"] == 320
    assert out["fault_truth"][0]["fault"] == "sensor_offset"
    assert out["cleared_detections_s"] == []
    # detected within the filter + debounce samples after the onset, never before
    assert 0 < out["detection_delay_s"] <= 5 * 0.05 + 1e-9
    assert out["first_symptom_s"]["s_y"] >= ONSET
    assert out["isolated_faults"] == ["sensor_offset"]
    assert out["isolation_delay_s"] < 3.0


@pytest.mark.graph
def test_tank_as_a_live_two_node_graph(tmp_path):
    from ros_helpers import RosHarness, spawn, stop

    from fdi_ros import msgs
    from fdi_ros.core.types import FaultEvent
    from fdi_ros.nodes.common import DATA_QOS, LATCHED_QOS

    env = {"FDI_ROS_WINGS": WINGS,
           "PYTHONPATH": os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")])}
    (tmp_path / "sc.yaml").write_text("duration_s: 14.0\nseed: 3\n")
    h = RosHarness("tank_test")
    procs = [spawn([sys.executable, "-m", "fdi_ros.nodes.preprocessor_node", "--ros-args",
                    "-p", "plant:=tank"], **env),
             spawn([sys.executable, "-m", "fdi_ros.nodes.plant_node", "--ros-args",
                    "-p", "plant:=tank", "-p", f"scenario:={tmp_path / 'sc.yaml'}",
                    "-p", "realtime_factor:=4.0", "-p", "publish_clock:=false",
                    "-p", "min_subscribers:=2"], **env)]
    try:
        from fdi_msgs.msg import FaultEvent as FaultMsg
        from fdi_msgs.msg import Features, SensorBlock

        feats, truth = [], []
        sub = h.node.create_subscription(Features, "/fdi/features",
                                         lambda m: feats.append(msgs.to_features(m)), DATA_QOS)
        h.spin_until(lambda: sub.get_publisher_count() >= 1, 60.0,
                     "the preprocessor's features publisher", procs)
        # plant time starts once the preprocessor and this node read the blocks (2 readers):
        # by then this node already reads the features, so none is missed
        h.node.create_subscription(SensorBlock, "/fdi/sensor_block", lambda m: None, DATA_QOS)
        h.node.create_subscription(FaultMsg, "/fdi/fault_truth",
                                   lambda m: truth.append(msgs.to_fault_event(m)), LATCHED_QOS)
        inject = h.node.create_publisher(FaultMsg, "/fdi/fault_inject", LATCHED_QOS)
        h.spin_until(lambda: feats, 60.0, "the first tank features", procs)
        # the plant reads injections as a volatile reader (nothing replayed into a restarted
        # plant): a request sent before its reader matched this writer is not delivered
        h.spin_until(lambda: inject.get_subscription_count() >= 1, 60.0,
                     "the plant's fault-injection reader", procs)
        inject.publish(msgs.MessageFactory("rclpy").fault_event(
            FaultEvent(t=ONSET, fault="sensor_offset", size=OFFSET, size_unit="m")))
        h.spin_until(lambda: truth, 30.0, "the fault truth of the injected offset", procs)
        h.spin_until(lambda: feats[-1].t_end >= 13.0, 60.0, "features past 13 s", procs)
    finally:
        outs = [stop(p) for p in procs]
        h.close()
    assert truth[0].fault == "sensor_offset" and truth[0].t == ONSET, outs
    assert all(f.plant == "tank" and f.names == ("u", "y") for f in feats)
    idx = [f.index for f in feats]
    # none lost on the way. The first few may be: this node has matched the preprocessor's
    # publisher, but DDS discovery is not symmetric, so the preprocessor's writer may match this
    # reader a moment later (volatile features are not replayed to a late reader). They must
    # still start early enough to see the fault-free level before the onset.
    assert idx == list(range(idx[0], idx[0] + len(idx))), idx[:20]
    assert feats[0].t_end < 3.0, feats[0].t_end
    # the offset is in the measured level after the onset: the tank model's residual shows it
    from tank_wing import TankLevelModel

    model = TankLevelModel("nominal", threshold=0.03)
    r = np.array([model.residuals(f).values[0] for f in feats])
    t = np.array([f.t_end for f in feats])
    before = r[(t > 3.0) & (t < ONSET)]
    after = r[(t > ONSET + 0.5) & (t < 13.0)]
    assert np.abs(before).max() < 0.03
    assert np.mean(after) == pytest.approx(OFFSET, abs=0.03)
