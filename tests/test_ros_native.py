"""fdi_ros as ROS's own tools see it: the venv as an ament prefix (the package found and its
executables resolved as `ros2 run` does), and the plant node driven the way a user at a terminal
would: malformed fault injections from a default-QoS publisher and the service, parameter
descriptions, and a live change of the real-time factor."""

from __future__ import annotations

import math
import os
import py_compile
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from ros_helpers import ROOT, RosHarness, spawn, stop

PACKAGE = "fdi_ros"
NODES = ("plant_node", "preprocessor_node", "residual_node", "model_host_node",
         "supervisor_node", "recorder_node", "replayer_node")


@pytest.fixture(scope="module", autouse=True)
def ament_prefix_path():
    """Resolve packages through this venv's prefix, as a shell that sourced .venv/setup.sh."""
    old = os.environ.get("AMENT_PREFIX_PATH")
    os.environ["AMENT_PREFIX_PATH"] = os.pathsep.join(p for p in (sys.prefix, old) if p)
    yield
    if old is None:
        os.environ.pop("AMENT_PREFIX_PATH", None)
    else:
        os.environ["AMENT_PREFIX_PATH"] = old


def executable(name: str) -> Path:
    """Where `ros2 run fdi_ros <name>` finds an executable: package prefix / lib / package."""
    from ament_index_python.packages import get_package_prefix

    return Path(get_package_prefix(PACKAGE)) / "lib" / PACKAGE / name


def test_venv_is_an_ament_prefix():
    from ament_index_python.packages import (
        get_package_prefix,
        get_package_share_directory,
        get_packages_with_prefixes,
    )

    packages = get_packages_with_prefixes()
    assert PACKAGE in packages and "fdi_msgs" in packages
    assert Path(get_package_prefix(PACKAGE)).resolve() == Path(sys.prefix).resolve()
    share = Path(get_package_share_directory(PACKAGE))
    assert ET.parse(share / "package.xml").getroot().findtext("name") == PACKAGE
    launch = share / "launch" / "fdi_graph.launch.py"
    py_compile.compile(str(launch), doraise=True)  # `ros2 launch` cannot run here: it compiles
    assert (share / "config" / "diesel.yaml").is_file()
    # a configuration opened through the share directory resolves paths against the checkout
    from fdi_ros.core.graphconfig import load_graph_config

    cfg = load_graph_config(share / "config" / "diesel.yaml")
    assert cfg.resolve("not/yet/built") == str(ROOT / "not" / "yet" / "built")
    for name in NODES:
        exe = executable(name)
        assert exe.is_file() and os.access(exe, os.X_OK), exe
        assert exe.read_text().startswith(f"#!{Path(sys.prefix)}/bin/python"), exe
    assert (Path(sys.prefix) / "setup.sh").is_file()


# -- the plant node, started from lib/fdi_ros/plant_node --------------------------------------
@pytest.fixture(scope="module")
def plant():
    """The plant as `ros2 run fdi_ros plant_node` starts it, and a harness subscribed to it."""
    from diagnostic_msgs.msg import DiagnosticArray
    from fdi_msgs.msg import FaultEvent, SensorBlock
    from rosgraph_msgs.msg import Clock

    from fdi_ros.nodes.common import DATA_QOS, LATCHED_QOS

    ros = RosHarness("fdi_test_native")
    seen = {"blocks": [], "truth": [], "diag": [], "clock": []}
    node = ros.node
    node.create_subscription(SensorBlock, "/fdi/sensor_block",
                             lambda m: seen["blocks"].append((time.monotonic(),
                                                              float(m.stamp_s[-1]))), DATA_QOS)
    node.create_subscription(FaultEvent, "/fdi/fault_truth", seen["truth"].append, LATCHED_QOS)
    node.create_subscription(DiagnosticArray, "/diagnostics", seen["diag"].append, 50)
    node.create_subscription(Clock, "/clock", seen["clock"].append, 10)
    proc = spawn([str(executable("plant_node")), "--ros-args", "-r", "__node:=fdi_plant",
                  "-p", "plant:=diesel"])
    ros.seen, ros.proc = seen, proc
    try:
        ros.spin_until(lambda: len(seen["blocks"]) >= 3, 30.0, "sensor blocks", [proc])
        yield ros
    finally:
        out = stop(proc)
        ros.close()
        print(out[-3000:])


def _event(fault: str, size: float = 5.0, unit: str = "mm", profile: str = "step"):
    from fdi_msgs.msg import FaultEvent

    return FaultEvent(t_s=0.0, fault=fault, size=size, size_unit=unit, profile=profile,
                      active=True)


def _injection_counts(arr) -> dict[str, int] | None:
    for st in arr.status:
        if st.name.endswith("fault injection"):
            return {kv.key: int(kv.value) for kv in st.values
                    if kv.key in ("accepted", "rejected")}
    return None


@pytest.mark.graph
def test_plant_survives_malformed_injections_and_accepts_a_valid_one(plant):
    from fdi_msgs.msg import FaultEvent
    from fdi_msgs.srv import InjectFault

    seen, proc = plant.seen, plant.proc
    # a default publisher (reliable, volatile), as `ros2 topic pub` creates
    pub = plant.node.create_publisher(FaultEvent, "/fdi/fault_inject", 10)
    plant.spin_until(lambda: pub.get_subscription_count() >= 1, 20.0,
                     "the plant's /fdi/fault_inject subscription to match a default publisher",
                     [proc])
    bad = [_event("no_such_fault"), _event("leak_ic_engine", size=-5.0),
           _event("leak_ic_engine", size=math.nan), _event("leak_ic_engine", profile="zigzag")]
    for m in bad:
        pub.publish(m)

    def rejected(n: int):
        def cond():
            counts = [_injection_counts(a) for a in seen["diag"]]
            return any(c and c["rejected"] >= n for c in counts)
        return cond

    plant.spin_until(rejected(4), 20.0, "4 rejections on /diagnostics", [proc])
    reasons = [st.message for a in seen["diag"] for st in a.status if st.level != 0]
    assert any("no_such_fault" in r for r in reasons), reasons
    assert any("profile" in r for r in reasons), reasons
    assert all(a.header.stamp.sec + a.header.stamp.nanosec * 1e-9 < 1e6
               for a in seen["diag"]), "diagnostics stamped in plant time, not wall time"
    n_blocks = len(seen["blocks"])
    plant.spin_until(lambda: len(seen["blocks"]) >= n_blocks + 5, 20.0,
                     "the plant to keep publishing after the malformed requests", [proc])
    assert seen["truth"] == [], "no ground truth for refused requests"
    assert proc.poll() is None

    # a valid one from the same publisher takes effect and is reported as ground truth
    pub.publish(_event("leak_ic_engine", size=5.0))
    plant.spin_until(lambda: any(m.fault == "leak_ic_engine" for m in seen["truth"]), 20.0,
                     "the valid injection's ground truth", [proc])
    truth = [m for m in seen["truth"] if m.fault == "leak_ic_engine"]
    assert len(truth) == 1 and truth[0].size == 5.0 and truth[0].active

    # a transient-local publisher matches too; the plant's reader is volatile, so what such a
    # publisher keeps is never replayed into a restarted plant
    from fdi_ros.nodes.common import LATCHED_QOS

    latched = plant.node.create_publisher(FaultEvent, "/fdi/fault_inject", LATCHED_QOS)
    plant.spin_until(lambda: latched.get_subscription_count() >= 1, 20.0,
                     "a transient-local publisher to match", [proc])
    latched.publish(_event("leak_ic_engine", size=math.nan))
    plant.spin_until(rejected(5), 20.0, "the 5th rejection", [proc])
    readers = plant.node.get_subscriptions_info_by_topic("/fdi/fault_inject")
    assert readers and all(r.qos_profile.durability.name == "VOLATILE" for r in readers)

    # and through the service: refused with a reason, then accepted
    cli = plant.node.create_client(InjectFault, "/fdi/inject_fault")
    res = plant.call(cli, InjectFault.Request(event=_event("egr_leaky", size=math.inf)),
                     20.0, "inject_fault (bad)")
    assert not res.accepted and "finite" in res.reason
    res = plant.call(cli, InjectFault.Request(event=_event("egr_leaky", size=2.0)), 20.0,
                     "inject_fault (good)")
    assert res.accepted and "egr_leaky" in res.reason, res.reason
    plant.spin_until(lambda: any(m.fault == "egr_leaky" for m in seen["truth"]), 20.0,
                     "the service injection's ground truth", [proc])
    assert proc.poll() is None


@pytest.mark.graph
def test_parameters_described_and_validated(plant):
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import DescribeParameters, SetParameters

    names = ["realtime_factor", "seed", "scenario", "plant"]
    cli = plant.node.create_client(DescribeParameters, "/fdi_plant/describe_parameters")
    res = plant.call(cli, DescribeParameters.Request(names=names), 20.0, "describe_parameters")
    got = {d.name: d for d in res.descriptors}
    assert [d.name for d in res.descriptors] == names
    assert got["realtime_factor"].type == ParameterType.PARAMETER_DOUBLE
    assert got["seed"].type == ParameterType.PARAMETER_INTEGER
    assert got["scenario"].type == ParameterType.PARAMETER_STRING
    assert got["scenario"].read_only and got["seed"].read_only
    assert not got["realtime_factor"].read_only and got["realtime_factor"].description
    assert got["realtime_factor"].floating_point_range[0].from_value == 0.0

    setp = plant.node.create_client(SetParameters, "/fdi_plant/set_parameters")

    def set_one(name, value):
        v = (ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value)
             if isinstance(value, float) else
             ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=value))
        req = SetParameters.Request(parameters=[Parameter(name=name, value=v)])
        return plant.call(setp, req, 20.0, f"set {name}").results[0]

    r = set_one("realtime_factor", -1.0)
    assert not r.successful and r.reason
    r = set_one("seed", 7)
    assert not r.successful and "read-only" in r.reason.lower()


@pytest.mark.graph
def test_realtime_factor_raised_live_applies_from_then_on(plant):
    """1 -> 4 while running: plant time then runs about 4x wall time, with no catch-up burst
    (a retroactive change would jump by 3x the whole elapsed time at once). Timing measured on
    a shared machine, so the bounds are generous but far from the retroactive jump."""
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    seen, proc = plant.seen, plant.proc
    # let plant time run a while first: a retroactive change would jump by 3x all of it
    plant.spin_until(lambda: seen["blocks"][-1][1] >= 3.0, 30.0, "3 s of plant time", [proc])
    w0, t0 = seen["blocks"][-1]
    setp = plant.node.create_client(SetParameters, "/fdi_plant/set_parameters")
    req = SetParameters.Request(parameters=[Parameter(
        name="realtime_factor",
        value=ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=4))])
    w_set = time.monotonic()
    res = plant.call(setp, req, 20.0, "set realtime_factor 4")
    assert res.results[0].successful, res.results[0].reason
    elapsed_plant = t0  # plant time run so far: a retroactive change would add 3x this at once
    # right after the change: no burst
    w_check = time.monotonic() + 0.5
    plant.spin_until(lambda: time.monotonic() >= w_check, 5.0, "half a second")
    w1, t1 = seen["blocks"][-1]
    assert t1 - t0 < 4.0 * (w1 - w0) + 1.0, (t0, t1, w1 - w0)
    assert t1 - t0 < 3.0 * elapsed_plant, "catch-up burst"
    # steady slope over the next seconds
    n1 = len(seen["blocks"])
    plant.spin_until(lambda: seen["blocks"][-1][0] >= w_set + 3.0 and len(seen["blocks"]) > n1,
                     20.0, "3 s of blocks at rate 4", [proc])
    sample = [b for b in seen["blocks"] if b[0] >= w_set + 0.5]
    (wa, ta), (wb, tb) = sample[0], sample[-1]
    slope = (tb - ta) / (wb - wa)
    print(f"plant time per wall second after the change: {slope:.2f} (plant ran "
          f"{elapsed_plant:.1f} s before it)")
    assert 3.0 < slope < 5.0, slope


@pytest.mark.graph
def test_every_node_describes_its_own_parameters(tmp_path):
    """Preprocessor, residual, recorder and replayer (started from lib/fdi_ros as `ros2 run`
    does): each parameter described under its own name with the type of its default; the
    replayer's rate changes live, a negative one is refused."""
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import DescribeParameters, SetParameters

    from fdi_ros.nodes import preprocessor_node, recorder_node, replayer_node, residual_node

    types = {float: ParameterType.PARAMETER_DOUBLE, int: ParameterType.PARAMETER_INTEGER,
             str: ParameterType.PARAMETER_STRING, bool: ParameterType.PARAMETER_BOOL,
             list: ParameterType.PARAMETER_STRING_ARRAY}
    bag = ROOT / "bags" / "diesel_leak_5mm_features"
    nodes = {
        "fdi_preprocessor": ("preprocessor_node", preprocessor_node.PARAMS,
                             ["-p", "plant:=diesel"]),
        "fdi_model_x": ("residual_node", residual_node.PARAMS, []),
        "fdi_recorder": ("recorder_node", recorder_node.PARAMS,
                         ["-p", f"bag:={tmp_path / 'bag'}"]),
        "fdi_replayer": ("replayer_node", replayer_node.PARAMS,
                         ["-p", f"bag:={bag}", "-p", "topics:=['/fdi/features']"]),
    }
    ros = RosHarness("fdi_test_params")
    procs = [spawn([str(executable(exe)), "--ros-args", "-r", f"__node:={name}", *args])
             for name, (exe, _, args) in nodes.items()]
    try:
        for name, (_, params, _) in nodes.items():
            cli = ros.node.create_client(DescribeParameters, f"/{name}/describe_parameters")
            names = [p.name for p in params]
            res = ros.call(cli, DescribeParameters.Request(names=names), 30.0,
                           f"{name} describe_parameters")
            assert [d.name for d in res.descriptors] == names
            for p, d in zip(params, res.descriptors):
                assert d.type == types[type(p.default)], (name, p.name, d.type)
                assert d.description and d.read_only == p.read_only, (name, p.name)
        setp = ros.node.create_client(SetParameters, "/fdi_replayer/set_parameters")
        for value, ok in ((4.0, True), (-2.0, False)):
            req = SetParameters.Request(parameters=[Parameter(name="rate", value=ParameterValue(
                type=ParameterType.PARAMETER_DOUBLE, double_value=value))])
            r = ros.call(setp, req, 20.0, f"replayer rate {value}").results[0]
            assert r.successful == ok, r.reason
        assert all(p.poll() is None for p in procs)
    finally:
        for p in procs:
            stop(p)
        ros.close()


def test_wall_timers_run_while_plant_time_stands_still():
    """A node on plant time (use_sim_time) with no /clock: its health and start-up timers
    (nodes.common.wall_timer) still run; a timer on the node's ROS clock does not (the
    preprocessor's start-up hold ran on it once and waited for a /clock that the held-back
    source does not publish)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from fdi_ros.nodes.common import wall_timer

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = rclpy.create_node("fdi_test_wall_timer", context=ctx, parameter_overrides=[
            Parameter("use_sim_time", Parameter.Type.BOOL, True)])
        fired = {"wall": 0, "ros": 0}
        wall_timer(node, 0.02, lambda: fired.__setitem__("wall", fired["wall"] + 1))
        node.create_timer(0.02, lambda: fired.__setitem__("ros", fired["ros"] + 1))
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        deadline = time.monotonic() + 20.0
        while fired["wall"] < 10 and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.1)
        assert fired == {"wall": 10, "ros": 0}, fired
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
