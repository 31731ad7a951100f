"""Model host: several residual-generator lifecycle nodes in ONE process on one executor, as
an rclcpp component container hosts components.

Each hosted node is still a node of its own: its own name, parameter file and lifecycle
services (``/<node>/change_state``, ``/<node>/get_state``, ``/<node>/transition_event``), so
the supervisor drives it exactly as it drives a model node in a process of its own. Only the
process (and its DDS participant, executor and interpreter) is shared.

Usage (the launcher builds this from the graph configuration's ``hosting``)::

    python -m fdi_ros.nodes.model_host_node --executor single \\
        --node fdi_model_nominal=/tmp/p/fdi_model_nominal.yaml \\
        --node fdi_model_leak_ic_engine=/tmp/p/fdi_model_leak_ic_engine.yaml

``--executor``: ``single`` (SingleThreadedExecutor) or ``events`` (rclpy's experimental
EventsExecutor). Process-wide ROS arguments (``--ros-args ...``) are not applied to the hosted
nodes: every node reads only its own ``--node`` parameter file, as in a process of its own.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from fdi_ros.nodes.residual_node import ResidualNode
from fdi_ros.nodes.spin import EXECUTORS, run_nodes


def parse_args(argv: list[str]) -> argparse.Namespace:
    """The host's own arguments (everything before ``--ros-args``)."""
    own = argv[:argv.index("--ros-args")] if "--ros-args" in argv else argv
    p = argparse.ArgumentParser(prog="model_host_node", description=__doc__.split("\n")[0])
    p.add_argument("--node", action="append", default=[], metavar="NAME=PARAMS_FILE",
                   help="one hosted residual node: its name and its ROS parameter file")
    p.add_argument("--executor", choices=EXECUTORS[:2], default="single")
    p.add_argument("--urgent", action="append", default=[], metavar="NAME",
                   help="a hosted node whose answers leave at once, not bundled with the "
                        "others' (the symptoms' model)")
    a = p.parse_args(own)
    if not a.node:
        p.error("at least one --node NAME=PARAMS_FILE is needed")
    for spec in a.node:
        name, sep, path = spec.partition("=")
        if not sep or not name or not path:
            p.error(f"--node {spec!r}: expected NAME=PARAMS_FILE")
    return a


def hosted_node(spec: str) -> Any:
    """A residual node named and parameterised by ``NAME=PARAMS_FILE`` alone."""
    name, _, path = spec.partition("=")
    return ResidualNode(cli_args=["--ros-args", "-r", f"__node:={name}",
                                  "--params-file", path], use_global_arguments=False)


def hosted_nodes(specs: list[str], urgent: tuple[str, ...] = ()) -> list[Any]:
    """The host's nodes, sending their answers to a feature block as one message
    (:mod:`fdi_ros.nodes.bundle`); the ``urgent`` ones answer each block first, and their
    answers leave at once."""
    from fdi_ros.nodes.bundle import Bundler

    nodes = [hosted_node(s) for s in specs]
    bundler = Bundler.on(nodes[0])
    for n in nodes:
        n.bundler = bundler
        n.bundle_urgent = n.get_name() in urgent
    return nodes


def main(args: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if args is None else args)
    a = parse_args(argv)
    return run_nodes(lambda: hosted_nodes(a.node, tuple(a.urgent)), executor=a.executor,
                     args=[sys.argv[0], *argv])


if __name__ == "__main__":
    raise SystemExit(main())
