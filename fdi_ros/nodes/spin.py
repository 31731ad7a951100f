"""How every fdi_ros node process runs: the loopback guard, and a main() wrapper that spins
its nodes (one, or several for a model host, as a component container holds components) on
one executor until SIGINT/SIGTERM and shuts them down cleanly."""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from typing import Any

# After a stop signal, keep executing callbacks this long for data already delivered.
DRAIN_S = 0.3
# After a stop signal, a process still alive this much later (a teardown stuck in the
# middleware) prints every thread's stack and exits: 0 if the nodes' shutdown hooks (a
# recorder closing its bag) had run, 3 if not. The launcher waits 15 s before SIGKILL.
STOP_GRACE_S = 10.0


def ensure_loopback_env() -> None:
    """Keep DDS discovery on this machine unless the user chose otherwise explicitly."""
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def run_node(make_node: Callable[[], Any], *, executor_threads: int = 1,
             on_shutdown: Callable[[Any], None] | None = None,
             args: list[str] | None = None) -> int:
    """Initialise rclpy, spin one node until SIGINT/SIGTERM, shut down cleanly.

    SIGTERM is turned into the same orderly shutdown as SIGINT, so a node killed by the
    launcher still runs ``on_shutdown`` (the recorder closes its bag there). One thread: the
    executor named by ``$FDI_ROS_EXECUTOR`` (:data:`EXECUTORS`), by default rclpy's
    EventsExecutor, which costs a node about half the CPU of the SingleThreadedExecutor per
    message (the 20 s diesel graph: 39 instead of 60 CPU seconds).
    """
    kind = "multi" if executor_threads > 1 else os.environ.get("FDI_ROS_EXECUTOR", "events")
    return run_nodes(lambda: [make_node()], executor=kind, threads=executor_threads,
                     on_shutdown=on_shutdown, args=args)


EXECUTORS = ("single", "events", "multi")


def make_executor(kind: str, threads: int = 2) -> Any:
    """An rclpy executor by name: ``single`` (SingleThreadedExecutor), ``events``
    (rclpy.experimental.EventsExecutor) or ``multi`` (MultiThreadedExecutor)."""
    from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor

    if kind == "events":
        from rclpy.experimental import EventsExecutor

        return EventsExecutor()
    if kind == "multi":
        return MultiThreadedExecutor(num_threads=threads)
    if kind == "single":
        return SingleThreadedExecutor()
    raise ValueError(f"unknown executor {kind!r}; known: {', '.join(EXECUTORS)}")


def run_nodes(make_nodes: Callable[[], Sequence[Any]], *, executor: str = "single",
              threads: int = 2, on_shutdown: Callable[[Any], None] | None = None,
              args: list[str] | None = None) -> int:
    """Initialise rclpy, spin the nodes ``make_nodes()`` returns on ONE executor of the kind
    ``executor`` until SIGINT/SIGTERM, drain, shut down cleanly (``on_shutdown`` per node).

    Several nodes in one process on one executor is how a component container hosts them:
    each stays a node of its own (name, parameters, services), only the process is shared.
    """
    ensure_loopback_env()
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    # Our own SIGINT/SIGTERM handling: stop spinning, then drain what DDS already delivered
    # (a recorder must not lose acknowledged messages), then shut down.
    rclpy.init(args=args if args is not None else sys.argv,
               signal_handler_options=SignalHandlerOptions.NO)
    nodes: list[Any] = []
    # stopping: a stop signal came; hooks: the shutdown hooks are "running" or "done"
    state = {"stopping": False, "hooks": ""}

    def _give_up() -> None:
        import faulthandler

        if state["hooks"] == "running":
            _arm()  # a shutdown hook at work (a recorder closing a large bag): let it finish
            return
        print(f"[fdi_ros] still not shut down {STOP_GRACE_S:.0f} s after the stop signal; "
              "thread stacks follow, exiting", file=sys.stderr, flush=True)
        faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
        os._exit(0 if state["hooks"] == "done" else 3)

    def _arm() -> None:
        timer = threading.Timer(STOP_GRACE_S, _give_up)
        timer.daemon = True
        timer.start()

    def _stop(signum: int, frame: Any) -> None:
        if not state["stopping"]:
            _arm()
        state["stopping"] = True

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    code = 0
    try:
        nodes = list(make_nodes())
        ex = make_executor(executor, threads)
        for node in nodes:
            ex.add_node(node)
        while not state["stopping"] and rclpy.ok():
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
        state["hooks"] = "running"
        for node in nodes:
            if on_shutdown is not None:
                try:
                    on_shutdown(node)
                except Exception:
                    traceback.print_exc()
                    code = 1
        state["hooks"] = "done"
        for node in nodes:
            try:
                node.destroy_node()
            except Exception:
                pass
        rclpy.try_shutdown()
    return code


def wall_timer(node: Any, period_s: float, callback: Callable[[], Any]) -> Any:
    """A timer on the steady clock, whatever ``use_sim_time`` says: health checks and holds
    run while plant time stands still (no /clock from a source held back or ended)."""
    from rclpy.clock import Clock, ClockType

    return node.create_timer(period_s, callback, clock=Clock(clock_type=ClockType.STEADY_TIME))
