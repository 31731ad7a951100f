"""Test environment: loopback-only DDS and a ROS_DOMAIN_ID of this test session's own.

Set before anything imports rclpy so that every node started by a test, in this process or in
a child process, discovers only peers on 127.0.0.0/8 and in its own domain.
"""

from __future__ import annotations

import os

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
os.environ.setdefault("MPLBACKEND", "Agg")
