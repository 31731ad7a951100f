"""fdi_ros: model-based fault detection and isolation as a ROS 2 node graph.

Layout
------
fdi_ros.core      pure numerical core (never imports rclpy)
fdi_ros.nodes     thin rclpy nodes, one module per node kind
fdi_ros.commands  the ``fdi-ros`` subcommands (auto-discovered by ``fdi_ros.cli``)
fdi_ros.msgs      the msg_defs/ message definitions registered into a rosbags typestore
fdi_ros.bag       rosbag2 / MCAP reading and writing without ROS
"""

__version__ = "0.1.0"
