"""Example: your own node subscribing to fdi_ros's symptoms and diagnosis.

Run it beside the graph (same ROS_DOMAIN_ID, loopback discovery):

    .venv/bin/python examples/symptom_listener.py

It prints every change of a symptom level and every change of the supervisor's state. The
messages are fdi_msgs/Symptoms and fdi_msgs/Diagnosis (msg_defs/fdi_msgs/msg); the same
information is on /diagnostics as diagnostic_msgs/DiagnosticArray for generic ROS tools.
"""

from __future__ import annotations

import os

import rclpy
from fdi_msgs.msg import Diagnosis, Symptoms
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

CODE = {-1: "-", 0: "o", 1: "+", 2: "++"}


class SymptomListener(Node):
    def __init__(self) -> None:
        super().__init__("symptom_listener")
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.create_subscription(Symptoms, "/fdi/symptoms", self.on_symptoms, qos)
        self.create_subscription(Diagnosis, "/fdi/diagnosis", self.on_diagnosis, qos)
        self._levels: dict[str, int] = {}
        self._state = ""

    def on_symptoms(self, m: Symptoms) -> None:
        for name, level in zip(m.names, m.levels):
            if self._levels.get(name, 0) != level:
                self.get_logger().info(f"t = {m.t_s:8.3f} s  {name}: {CODE[int(level)]}")
            self._levels[name] = int(level)

    def on_diagnosis(self, m: Diagnosis) -> None:
        if m.state != self._state:
            self._state = m.state
            self.get_logger().info(f"t = {m.t_s:8.3f} s  state {m.state}; isolated "
                                   f"{list(m.isolated_faults)}; on line {list(m.models_online)}")


def main() -> None:
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    rclpy.init()
    node = SymptomListener()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
