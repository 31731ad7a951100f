"""A child process with N writers of /fdi/residuals (the bank's model nodes, as DataWriters
of one topic, with the graph's data QoS) that each publish M residuals as fast as they can
once a reader is matched, wait until every one is acknowledged, print "sent" and spin on
until stopped. Arguments: N M."""

import sys

import rclpy
from fdi_msgs.msg import Residuals

from fdi_ros.nodes.common import DATA_QOS


def main() -> None:
    writers, each = int(sys.argv[1]), int(sys.argv[2])
    rclpy.init()
    node = rclpy.create_node("residual_burst")
    pubs = [node.create_publisher(Residuals, "/fdi/residuals", DATA_QOS) for _ in range(writers)]
    while any(p.get_subscription_count() < 1 for p in pubs):
        rclpy.spin_once(node, timeout_sec=0.05)
    for k in range(each):
        for w, p in enumerate(pubs):
            p.publish(Residuals(model_id=f"m{w}", index=k))
    for p in pubs:
        p.wait_for_all_acked()
    print("sent", flush=True)
    while rclpy.ok():
        rclpy.spin_once(node, timeout_sec=0.1)


if __name__ == "__main__":
    main()
