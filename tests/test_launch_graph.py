"""``fdi-ros launch`` as a user runs it: a replay that ends by itself with the same diagnosis
as ``fdi-ros diagnose``, respawn of a killed node, a recorder that cannot record, and SIGINT
to a launcher started as a background job. Every node a separate process over real DDS."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.graph, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
FDI = [sys.executable, "-m", "fdi_ros.cli"]
DURATION_S = 7.5  # the demo leak opens at 6 s and is isolated offline at 6.435 s


def _fdi(*args: str, timeout: float = 240.0) -> subprocess.CompletedProcess:
    return subprocess.run([*FDI, *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def demo_bag(diesel_bank, tmp_path_factory) -> tuple[Path, dict]:
    """The demo scenario as a bag of sensor blocks, and its offline diagnosis."""
    d = tmp_path_factory.mktemp("launch")
    bag = d / "demo"
    r = _fdi("simulate", "config/scenarios/demo_diesel_leak.yaml", "--out", str(bag),
             "--duration", str(DURATION_S))
    assert r.returncode == 0, r.stderr
    r = _fdi("diagnose", str(bag), "--json", str(d / "offline.json"))
    assert r.returncode == 0, r.stderr
    return bag, json.loads((d / "offline.json").read_text())


def _first_isolation(events: list[dict]) -> tuple[str, float] | None:
    for e in events:
        if e.get("state") == "isolated":
            return e["fault_model"], e["t"]
    return None


def _own_temp_dirs() -> set[str]:
    return {p.name for p in Path(tempfile.gettempdir()).glob("fdi_launch_*")}


# (a replay at 4 x real time, held back by the diagnosis: tests/test_graph.py)
@pytest.mark.parametrize("rate", [1.0])
def test_replay_ends_by_itself_with_the_offline_isolation(demo_bag, tmp_path, rate):
    bag, offline = demo_bag
    before = _own_temp_dirs()
    out = tmp_path / "live.json"
    t0 = time.monotonic()
    # the bank's seven model nodes in two model-host processes (the CLI's hosting flags, as in
    # the recorder test below; the scenario run and the respawn test keep one process per node)
    r = _fdi("launch", "config/diesel.yaml", "--replay", str(bag), "--rate", str(rate),
             "--hosting", "container", "--containers", "2", "--json", str(out), timeout=180)
    wall = time.monotonic() - t0
    print(f"rate {rate}: launcher exited {r.returncode} after {wall:.1f} s wall")
    assert r.returncode == 0, r.stderr[-3000:]
    assert "end of data" in r.stderr
    live = json.loads(out.read_text())["events"]
    want = _first_isolation(offline["events"])
    got = _first_isolation(live)
    assert want is not None and want[0] == "leak_ic_engine"
    assert got is not None, live
    segment = 0.015 * 2  # one segment either side
    assert got[0] == want[0] and abs(got[1] - want[1]) <= segment, (got, want)
    # every event to the segment, at any rate: a replay the graph cannot follow is held back
    last = offline["segments"] - 1
    assert _events_from(live, 0, last) == _events_from(offline["events"], 0, last), \
        r.stderr[-3000:]
    assert _own_temp_dirs() <= before  # the parameter files went with the launcher


def _children(pid: int) -> dict[int, str]:
    out = {}
    for p in Path("/proc").iterdir():
        if not p.name.isdigit():
            continue
        try:
            stat = (p / "stat").read_text()
            cmd = (p / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            out[int(p.name)] = cmd
    return out


def _wait(cond, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = cond()
        if v:
            return v
        time.sleep(0.1)
    raise TimeoutError(what)


def test_killed_supervisor_is_respawned_and_sigint_stops_a_background_launcher(demo_bag):
    bag, _ = demo_bag
    # a background job of a non-interactive shell: SIGINT inherited as ignored
    sh = subprocess.Popen(
        ["bash", "-c", f"{' '.join(FDI)} launch config/diesel.yaml --replay {bag} "
         "--rate 0.5 --respawn-limit 2 & echo $!; wait $!; echo rc=$?"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        launcher = int(sh.stdout.readline())

        def supervisor() -> int | None:
            return next((p for p, c in _children(launcher).items()
                         if "fdi_ros.nodes.supervisor_node" in c), None)

        first = _wait(supervisor, 60, "supervisor process")
        os.kill(first, signal.SIGKILL)
        second = _wait(lambda: (p := supervisor()) not in (None, first) and p, 30,
                       "respawned supervisor")
        assert second != first
        # SIGINT once the respawned supervisor is up (its start-up handshake done): a signal
        # during its imports would end it with a traceback, not a clean stop
        for line in sh.stdout:
            if line.startswith("[fdi_supervisor") and "graph ready" in line:
                break
        os.kill(launcher, signal.SIGINT)
        out, err = sh.communicate(timeout=60)
    finally:
        if sh.poll() is None:
            sh.kill()
    assert "respawning in" in err and "attempt 1/2" in err, err[-3000:]
    assert "rc=130" in out, (out, err[-2000:])


def test_recorder_that_cannot_record_stops_the_graph(demo_bag, tmp_path):
    bag, _ = demo_bag
    taken = tmp_path / "taken"
    taken.mkdir()
    r = _fdi("launch", "config/diesel.yaml", "--replay", str(bag), "--record", str(taken),
             timeout=60)
    assert r.returncode == 2 and "already exists" in r.stderr
    assert list(taken.iterdir()) == []  # nothing written into the user's folder


def test_sigkilled_recorder_stops_the_launcher_and_its_bag_recovers(demo_bag, tmp_path):
    """The dead recorder is on /diagnostics at once, the launcher exits 1, the bag recovers,
    and its offline diagnosis equals the live one from the first segment (the start-up
    handshake: recorder and supervisor saw the first block)."""
    from fdi_ros.graphwatch import GraphWatcher

    bag, _ = demo_bag
    rec = tmp_path / "rec"
    w = GraphWatcher()
    p = subprocess.Popen([*FDI, "launch", "config/diesel.yaml", "--replay", str(bag),
                          "--rate", "1", "--record", str(rec), "--hosting", "container",
                          "--containers", "2"], cwd=ROOT,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        # killed mid-run, once a few 1 MiB chunks are on disk
        w.spin_until(lambda: sum(f.stat().st_size for f in rec.glob("*.mcap")) > 4_000_000,
                     90, "4 MB recorded")
        recorder = next(q for q, c in _children(p.pid).items()
                        if "fdi_ros.nodes.recorder_node" in c)
        os.kill(recorder, signal.SIGKILL)
        st = w.spin_until(lambda: w.diagnostic_status("fdi_launch: recorder"), 30,
                          "the dead recorder on /diagnostics")
        assert st.level == b"\x02" and "not being recorded" in st.message, st
        _, err = p.communicate(timeout=60)
    finally:
        w.close()
        if p.poll() is None:
            p.kill()
    assert p.returncode == 1 and "recorder exited" in err, err[-2000:]
    assert not (rec / "metadata.yaml").exists()
    r = _fdi("bag", "recover", str(rec))
    assert r.returncode == 0, r.stderr
    from fdi_ros import bag as bagio
    from fdi_ros.core.events import diagnosis_events

    tops = bagio.topics(rec)
    assert "/clock" in tops and "/fdi/sensor_block" in tops  # /clock recorded when published
    import yaml

    meta = yaml.safe_load((rec / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["ros_distro"] == "jazzy"
    offered = {t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"]
               for t in meta["topics_with_message_count"]}
    # the replayer's own offer, as the recorder saw it on the graph
    assert offered["/fdi/sensor_block"][0]["reliability"] == "reliable"
    assert offered["/fdi/sensor_block"][0]["durability"] == "volatile"
    live = sorted(bagio.read_diagnoses(rec), key=lambda d: d.index)
    assert len(live) > 20
    r = _fdi("diagnose", str(rec), "--json", str(tmp_path / "off.json"))
    assert r.returncode == 0, r.stderr
    offline = json.loads((tmp_path / "off.json").read_text())["events"]
    last = live[-1].index
    lev = diagnosis_events(live)
    assert lev[0]["index"] == offline[0]["index"] == 0, (lev[:2], offline[:2])
    assert _events_from(lev, 0, last) == _events_from(offline, 0, last), err[-4000:]


def test_scenario_run_ends_by_itself_with_the_offline_isolation(demo_bag, tmp_path):
    _, offline = demo_bag
    src = (ROOT / "config" / "scenarios" / "demo_diesel_leak.yaml").read_text()
    assert "duration_s: 20.0" in src
    sc = tmp_path / "short.yaml"
    sc.write_text(src.replace("duration_s: 20.0", f"duration_s: {DURATION_S}"))
    out = tmp_path / "live.json"
    r = _fdi("launch", "config/diesel.yaml", "--scenario", str(sc), "--json", str(out),
             timeout=180)
    assert r.returncode == 0, r.stderr[-3000:]
    got = _first_isolation(json.loads(out.read_text())["events"])
    want = _first_isolation(offline["events"])
    assert got is not None and got[0] == want[0] and abs(got[1] - want[1]) <= 0.03, \
        (got, want, r.stderr[-3000:])


def _events_from(events: list[dict], start: int, last: int) -> list[tuple]:
    """The state holding at segment ``start`` and every change after it, up to ``last``."""
    held = [e for e in events if e["index"] <= start and "state" in e][-1]
    out = [(start, held["state"], held["fault_model"])]
    out += [(e["index"], "bank_switch", tuple(e["bank_switch"]["models_online"]))
            if "bank_switch" in e else
            (e["index"], e["state"], e["fault_model"], e["min_residual_model"],
             tuple(e["candidate_faults"])) for e in events if start < e["index"] <= last]
    return out
