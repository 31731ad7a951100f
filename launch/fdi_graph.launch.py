"""ros2 launch fdi_ros fdi_graph.launch.py config:=<path to config/diesel.yaml>

For real ROS 2 installs (colcon build). Thin on purpose: the node list comes from the same
graph configuration and the same code as ``fdi-ros launch`` (fdi_ros.launcher.Graph), so the
two cannot drift apart. Model nodes and the supervisor are respawned when they die
(``respawn``, with the same delay and, where this ``launch`` supports it, the same limit as
``fdi-ros launch``).
"""

import inspect

from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription

_GRAPHS = []


def _nodes(context):
    from launch.actions import ExecuteProcess

    from fdi_ros.launcher import RESPAWN_MODULES, Graph, RespawnPolicy

    graph = Graph(LaunchConfiguration("config").perform(context), echo=None)
    # kept for the whole launch: its parameter files go when the launch process exits
    _GRAPHS.append(graph)
    policy = RespawnPolicy()
    has_limit = "respawn_max_retries" in inspect.signature(ExecuteProcess.__init__).parameters
    actions = []
    for n in graph.nodes:
        extra = {}
        if n.module in RESPAWN_MODULES:
            extra = {"respawn": True, "respawn_delay": policy.first_delay_s}
            if has_limit:
                extra["respawn_max_retries"] = policy.limit
        if n.hosted:  # a model host: its hosted nodes' names and parameter files are arguments
            actions.append(Node(package="fdi_ros", executable=n.module, output="screen",
                                arguments=n.argv[3:], **extra))
            continue
        params_file = n.argv[n.argv.index("--params-file") + 1]
        actions.append(Node(package="fdi_ros", executable=n.module, name=n.name,
                            parameters=[params_file], output="screen", **extra))
    return actions


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument("config", description="graph configuration YAML"),
        OpaqueFunction(function=_nodes),
    ])
