"""A child process that publishes one fully populated fdi_msgs message of each type, repeatedly
(every 0.1 s) until stopped, so the receiving test can match fields one by one."""

from rclpy.node import Node
from sample_messages import sample_records

from fdi_ros.msgs import MessageFactory
from fdi_ros.nodes.common import DATA_QOS, run_node


def make_node() -> Node:
    node = Node("msg_publisher")
    fac = MessageFactory("rclpy")
    pubs = {}
    samples = sample_records(fac)
    for topic, msg in samples.items():
        pubs[topic] = node.create_publisher(type(msg), topic, DATA_QOS)
    node.create_timer(0.1, lambda: [pubs[t].publish(m) for t, m in samples.items()])
    return node


if __name__ == "__main__":
    raise SystemExit(run_node(make_node))
