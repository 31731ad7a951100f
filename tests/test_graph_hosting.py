"""Model nodes hosted several to a process (``--hosting container``), over real DDS: each hosted
node keeps its own lifecycle services, the supervisor drives them as it drives a model node in
a process of its own (get_state confirms), an external ``change_state`` on one hosted node is
seen by the supervisor and undone, and a model host that dies is respawned by the launcher with
its nodes brought back on line.

The graph runs without a data source (the bank, the preprocessor and the supervisor only): the
lifecycle handling needs no data, and the test stays light."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil
import pytest
import yaml

pytestmark = [pytest.mark.graph]

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config" / "diesel.yaml"
SUP = "fdi_supervisor: model "


def _config_without_source(tmp: Path) -> tuple[Path, list[str]]:
    from fdi_ros.core.graphconfig import load_graph_config

    cfg = load_graph_config(CONFIG)
    doc = yaml.safe_load(CONFIG.read_text())
    doc.pop("fdi_plant")
    for e in doc["fdi_graph"]["bank"]:
        e["model"] = cfg.resolve_spec(e["model"])
    sym = doc["fdi_graph"]["symptoms"]
    for k in ("config", "table"):
        sym[k] = cfg.resolve(sym[k])
    out = tmp / "diesel_no_source.yaml"
    out.write_text(yaml.safe_dump(doc))
    return out, [e.node_name for e in cfg.bank]


def _hosts(launcher: subprocess.Popen) -> dict[int, list[str]]:
    """pid -> hosted node names of the launcher's model-host processes."""
    out = {}
    for p in psutil.Process(launcher.pid).children():
        try:
            argv = p.cmdline()
        except psutil.Error:
            continue
        if "fdi_ros.nodes.model_host_node" in argv:
            out[p.pid] = [a.split("=")[1] for a in argv if a.startswith("--node=")]
    return out


def _model_status(w, node_name: str):
    mid = node_name.removeprefix("fdi_model_")
    st = w.diagnostic_status(SUP + mid)
    return None if st is None else (st, {v.key: v.value for v in st.values})


def test_container_hosted_bank_lifecycle_external_change_and_respawn(diesel_bank, tmp_path):
    from lifecycle_msgs.srv import ChangeState

    from fdi_ros.graphwatch import GraphWatcher

    config, names = _config_without_source(tmp_path)
    lines: list[str] = []
    launcher = subprocess.Popen(
        [sys.executable, "-m", "fdi_ros.cli", "launch", str(config), "--hosting", "container",
         "--containers", "2", "--executor", "events"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT)
    threading.Thread(target=lambda: lines.extend(launcher.stdout), daemon=True).start()
    w = GraphWatcher("hosting_watcher")
    try:
        alive = lambda: launcher.poll() is None  # noqa: E731

        def bank_active() -> bool:
            st = [_model_status(w, n) for n in names]
            return all(s is not None and s[1].get("state") == "active" == s[1].get("wanted")
                       for s in st)

        w.spin_until(bank_active, 120.0, "the hosted bank active (per the supervisor)", alive)
        hosts = _hosts(launcher)
        assert len(hosts) == 2, hosts
        assert sorted(n for v in hosts.values() for n in v) == sorted(names)
        assert not any("residual_node" in " ".join(p.cmdline())
                       for p in psutil.Process(launcher.pid).children())
        # every hosted node answers its own get_state
        assert {n: w.lifecycle_state(n) for n in names} == dict.fromkeys(names, "active")

        # `ros2 lifecycle set /fdi_model_egr_leaky deactivate` on one hosted node
        target = "fdi_model_egr_leaky"
        cli = w.node.create_client(ChangeState, f"/{target}/change_state")
        assert cli.wait_for_service(timeout_sec=10.0)
        req = ChangeState.Request()
        req.transition.id = 4  # deactivate
        fut = cli.call_async(req)
        w.spin_until(fut.done, 10.0, "the external deactivate", alive)
        assert fut.result().success

        mid = target.removeprefix("fdi_model_")

        def statuses() -> list:
            return [st for _, arr in w.seen.diagnostics for st in arr.status
                    if st.name == SUP + mid]

        def seen_external() -> bool:
            return any("external" in st.message and target in st.message for st in statuses())

        try:
            w.spin_until(seen_external, 20.0, "the supervisor reporting the external change",
                         alive)
        except TimeoutError:
            raise AssertionError(sorted({st.message for st in statuses()})) from None
        w.spin_until(lambda: (_model_status(w, target) or (0, {}))[1].get(
            "external_transitions") == "1" and bank_active(), 30.0,
            "the external change undone", alive)
        assert w.lifecycle_state(target) == "active"

        # a model host dies: the launcher respawns it, the supervisor brings its nodes back
        victim, hosted = next((pid, v) for pid, v in hosts.items()
                              if "fdi_model_leak_ic_engine" in v)
        psutil.Process(victim).send_signal(signal.SIGKILL)
        w.spin_until(lambda: any("respawning" in ln and "fdi_model_host_" in ln
                                 for ln in lines), 20.0, "the launcher's respawn", alive)
        w.spin_until(lambda: any(v == hosted and pid != victim
                                 for pid, v in _hosts(launcher).items()), 30.0,
                     "the model host restarted", alive)
        before = time.monotonic()

        def back_on_line() -> bool:  # per /diagnostics published after the restart
            fresh = [(wall, arr) for wall, arr in w.seen.diagnostics if wall > before]
            return bool(fresh) and all(
                {v.key: v.value for v in st.values}.get("state") == "active"
                for _, arr in fresh[-1:] for st in arr.status
                if st.name.startswith(SUP) and "fdi_model_" + st.name[len(SUP):] in hosted)

        w.spin_until(lambda: back_on_line() and bank_active(), 90.0,
                     "the respawned host's nodes back on line", alive)
        assert {n: w.lifecycle_state(n) for n in hosted} == dict.fromkeys(hosted, "active")
    finally:
        w.close()
        if launcher.poll() is None:
            launcher.send_signal(signal.SIGINT)
        code = launcher.wait(timeout=60)
    assert code == 130, "".join(lines[-30:])
