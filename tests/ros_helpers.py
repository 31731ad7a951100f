"""Helpers for tests that talk to real ROS 2 processes over DDS (loopback, own domain id).

Nothing here sleeps for a fixed time: every wait spins an executor until a condition holds or
a deadline passes, and then fails with what was expected.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
PROCS = Path(__file__).resolve().parent / "procs"


def child_env(**extra: str) -> dict[str, str]:
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra)
    return env


def spawn(argv: list[str], **env: str) -> subprocess.Popen:
    """Start a child process in its own process group, output captured."""
    return subprocess.Popen(argv, env=child_env(**env), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)


def spawn_script(name: str, *args: str, **env: str) -> subprocess.Popen:
    return spawn([sys.executable, str(PROCS / name), *args], **env)


def stop(proc: subprocess.Popen, sig: int = signal.SIGINT, timeout: float = 15.0) -> str:
    """Signal a child, wait for it, return its output (kill it if it does not stop)."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    out = proc.stdout.read() if proc.stdout else ""
    return out


class RosHarness:
    """An rclpy context, node and executor of the test's own, shut down by the fixture."""

    def __init__(self, name: str = "fdi_test") -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, cond: Callable[[], Any], timeout: float, what: str,
                   procs: list[subprocess.Popen] | None = None) -> Any:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            value = cond()
            if value:
                return value
            for p in procs or []:
                if p.poll() is not None:
                    raise AssertionError(f"child exited ({p.returncode}) while waiting for "
                                         f"{what}:\n{p.stdout.read() if p.stdout else ''}")
            self.executor.spin_once(timeout_sec=0.05)
        raise AssertionError(f"timed out after {timeout} s waiting for {what}")

    def call(self, client: Any, request: Any, timeout: float, what: str) -> Any:
        if not client.wait_for_service(timeout_sec=timeout):
            raise AssertionError(f"service for {what} not available after {timeout} s")
        fut = client.call_async(request)
        self.spin_until(fut.done, timeout, what)
        return fut.result()

    def close(self) -> None:
        import rclpy

        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)
