"""fdi_ros: model-based fault detection and isolation as a ROS 2 node graph.

Layout
------
fdi_ros.core      generic FDI core: names no plant, never imports rclpy, a node or a command
fdi_ros.plants    one wing per plant and the registry of wings (plant names live here)
fdi_ros.nodes     thin rclpy nodes, one module per node kind
fdi_ros.commands  the ``fdi-ros`` subcommands (auto-discovered by ``fdi_ros.cli``)
fdi_ros.msgs      the msg_defs/ message definitions registered into a rosbags typestore
fdi_ros.bag       rosbag2 / MCAP reading and writing without ROS
"""

__version__ = "0.1.0"

# The registry of plant wings installs, into the core's residual-model loader, how the kinds of
# every wing are found (cheap: wing modules are imported on first use).
from fdi_ros import plants as _plants  # noqa: E402,F401
