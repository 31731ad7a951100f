"""How every fdi_ros node process runs: the loopback guard, and a main() wrapper that spins one
node until SIGINT/SIGTERM and shuts it down cleanly."""

from __future__ import annotations

import os
import signal
import sys
import time
import traceback
from collections.abc import Callable
from typing import Any

# After a stop signal, keep executing callbacks this long for data already delivered.
DRAIN_S = 0.3


def ensure_loopback_env() -> None:
    """Keep DDS discovery on this machine unless the user chose otherwise explicitly."""
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def run_node(make_node: Callable[[], Any], *, executor_threads: int = 1,
             on_shutdown: Callable[[Any], None] | None = None,
             args: list[str] | None = None) -> int:
    """Initialise rclpy, spin one node until SIGINT/SIGTERM, shut down cleanly.

    SIGTERM is turned into the same orderly shutdown as SIGINT, so a node killed by the
    launcher still runs ``on_shutdown`` (the recorder closes its bag there).
    """
    ensure_loopback_env()
    import rclpy
    from rclpy.executors import (
        ExternalShutdownException,
        MultiThreadedExecutor,
        SingleThreadedExecutor,
    )
    from rclpy.signals import SignalHandlerOptions

    # Our own SIGINT/SIGTERM handling: stop spinning, then drain what DDS already delivered
    # (a recorder must not lose acknowledged messages), then shut down.
    rclpy.init(args=args if args is not None else sys.argv,
               signal_handler_options=SignalHandlerOptions.NO)
    node = None
    stopping = {"flag": False}

    def _stop(signum: int, frame: Any) -> None:
        stopping["flag"] = True

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    code = 0
    try:
        node = make_node()
        ex = (MultiThreadedExecutor(num_threads=executor_threads) if executor_threads > 1
              else SingleThreadedExecutor())
        ex.add_node(node)
        while not stopping["flag"] and rclpy.ok():
            ex.spin_once(timeout_sec=0.1)
        deadline = time.monotonic() + DRAIN_S
        while rclpy.ok() and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.02)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        traceback.print_exc()
        code = 1
    finally:
        if node is not None:
            if on_shutdown is not None:
                try:
                    on_shutdown(node)
                except Exception:
                    traceback.print_exc()
                    code = 1
            try:
                node.destroy_node()
            except Exception:
                pass
        rclpy.try_shutdown()
    return code
