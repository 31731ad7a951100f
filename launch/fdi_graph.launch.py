"""ros2 launch fdi_ros fdi_graph.launch.py config:=<path to config/diesel.yaml>

For real ROS 2 installs (colcon build). Thin on purpose: the node list comes from the same
graph configuration and the same code as ``fdi-ros launch`` (fdi_ros.launcher.Graph), so the
two cannot drift apart.
"""

from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription


def _nodes(context):
    from fdi_ros.launcher import Graph

    graph = Graph(LaunchConfiguration("config").perform(context), echo=None)
    actions = []
    for n in graph.nodes:
        params_file = n.argv[n.argv.index("--params-file") + 1]
        actions.append(Node(package="fdi_ros", executable=n.module, name=n.name,
                            parameters=[params_file], output="screen"))
    return actions


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument("config", description="graph configuration YAML"),
        OpaqueFunction(function=_nodes),
    ])
