"""Fleets of bags: `fdi-ros diagnose BAG... --workers N` on a local process pool and on a
local Dask cluster (loopback only) give every bag exactly its serial result; a bad bag is
reported and loses nothing of the others; the fleet report has a row per bag and a plot."""

from __future__ import annotations

import ipaddress
import json
import subprocess
import sys
from pathlib import Path

import pytest

from fdi_ros.offline import diagnose_fleet, without_timing, write_report

ROOT = Path(__file__).resolve().parents[1]


def _bag(path: Path, *, seed: int, duration: float, fault: dict | None) -> Path:
    from fdi_ros.plants.diesel.scenario import simulate_to_bag

    doc = {"name": path.name, "seed": seed, "duration_s": duration, "dalpha_deg": 1.0,
           "block_deg": 720.0,
           "inputs": {"kind": "points", "points": [{"t": 0.0, "n": 2000, "torque": 130}]},
           "faults": [fault] if fault else []}
    simulate_to_bag(doc, path)
    return path


@pytest.fixture(scope="module")
def fleet(tmp_path_factory, diesel_bank) -> list[str]:
    d = tmp_path_factory.mktemp("fleet")
    leak = {"t": 2.0, "fault": "leak_ic_engine", "size": 5, "unit": "mm", "profile": "step"}
    vent = {"t": 1.5, "fault": "crankcase_vent_open", "size": 6, "unit": "mm", "profile": "step"}
    return [str(_bag(d / f"b{i}", seed=i, duration=dur, fault=f)) for i, (dur, f) in
            enumerate([(4.0, leak), (3.0, None), (4.5, vent), (3.5, leak)])]


def test_local_pool_equals_serial(fleet, tmp_path):
    serial = diagnose_fleet(fleet, workers=1)
    pool = diagnose_fleet(fleet, workers=2)
    assert list(serial) == list(pool) == fleet
    for b in fleet:
        assert "error" not in serial[b], serial[b]
        assert without_timing(pool[b]) == without_timing(serial[b])
    assert serial[fleet[0]]["isolated_faults"] == ["leak_ic_engine"]
    assert serial[fleet[1]]["isolated_faults"] == []
    files = write_report(serial, tmp_path / "report")
    rows = Path(files["csv"]).read_text().splitlines()
    assert len(rows) == 1 + len(fleet) and "leak_ic_engine" in rows[1]
    assert Path(files["plot"]).stat().st_size > 1000


def _listening(pids: set[int]) -> list[tuple[int, str]]:
    import psutil

    out = []
    for pid in pids:
        try:
            conns = psutil.Process(pid).net_connections(kind="inet")
        except psutil.Error:
            continue
        out += [(pid, c.laddr.ip) for c in conns if c.status == psutil.CONN_LISTEN]
    return out


def test_dask_local_cluster_loopback_only_and_equal_to_serial(fleet):
    pytest.importorskip("distributed")
    import os

    import psutil
    from dask.distributed import Client

    from fdi_ros.offline import local_dask_cluster

    serial = diagnose_fleet(fleet[:2], workers=1)
    with local_dask_cluster(2) as cluster, Client(cluster) as client:
        client.wait_for_workers(2)
        me = psutil.Process(os.getpid())
        pids = {me.pid} | {p.pid for p in me.children(recursive=True)}
        socks = _listening(pids)
        assert socks, "the cluster listens somewhere"
        for pid, ip in socks:
            assert ipaddress.ip_address(ip).is_loopback, f"process {pid} listens on {ip}"
        addr = cluster.scheduler_address
    assert addr.startswith("tcp://127.0.0.1:")
    on_dask = diagnose_fleet(fleet[:2], workers=2, engine="dask")
    for b in fleet[:2]:
        assert without_timing(on_dask[b]) == without_timing(serial[b])


def test_cli_fleet_bad_bag_reported_others_kept(fleet, tmp_path):
    bad = tmp_path / "not_a_bag"
    bad.mkdir()
    out = tmp_path / "fleet.json"
    r = subprocess.run([sys.executable, "-m", "fdi_ros.cli", "diagnose", fleet[0], str(bad),
                        fleet[1], "--workers", "2", "--json", str(out),
                        "--report", str(tmp_path / "rep")],
                       cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 1, r.stderr
    doc = json.loads(out.read_text())
    assert list(doc) == [fleet[0], str(bad), fleet[1]]
    assert "not a rosbag2 directory" in doc[str(bad)]["error"]
    assert doc[fleet[0]]["isolated_faults"] == ["leak_ic_engine"]
    assert "not_a_bag" in (tmp_path / "rep" / "fleet.md").read_text()
    # one bag keeps the single-bag output shape
    r = subprocess.run([sys.executable, "-m", "fdi_ros.cli", "diagnose", fleet[1]],
                       cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["bag"] == fleet[1]
