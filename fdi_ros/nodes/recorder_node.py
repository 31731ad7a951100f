"""Recorder: every fdi topic (and /diagnostics) into a rosbag2 MCAP bag, serialized as received.

Subscriptions are ``raw=True``: the CDR bytes go to the bag unchanged (no re-encoding).
A SIGINT or SIGTERM closes the bag properly (MCAP footer and metadata.yaml), so an interrupted
recording is a complete, readable bag. Topics that appear later are picked up by a periodic
scan of the graph, for the message types this package knows.

Parameters: ``bag`` (output directory, required), ``topics`` (extra topics; default: all known),
``scan_period_s`` (graph scan, 0.5 s).
"""

from __future__ import annotations

import threading
from functools import partial
from typing import Any

from rclpy.node import Node

from fdi_ros import msgs
from fdi_ros.bag import BagWriter
from fdi_ros.nodes.common import (
    DATA_IN_QOS,
    LATCHED_QOS,
    Param,
    declare_params,
    required,
    run_node,
)

# Known types we can record; topics carrying them are picked up wherever they appear (the
# batched transport topics only when asked for: their vectors are on the per-vector topics).
RECORDABLE = {**{t: v for t, v in msgs.TOPICS.items() if t not in msgs.BATCHED_TOPICS},
              "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
              "/clock": "rosgraph_msgs/msg/Clock"}


PARAMS = (
    Param("bag", "", "output bag directory (rosbag2, MCAP); required", read_only=True,
          check=required),
    Param("topics", [""], "extra topics to record besides the known ones", read_only=True),
    Param("scan_period_s", 0.5, "period of the graph scan for new topics [s]", read_only=True,
          range=(0.01, 60.0)),
)


def _msg_class(msgtype: str) -> Any:
    import importlib

    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


class RecorderNode(Node):
    def __init__(self) -> None:
        super().__init__("fdi_recorder")
        declare_params(self, PARAMS)
        path = self.get_parameter("bag").value
        extra = [t for t in self.get_parameter("topics").value if t]
        self._lock = threading.Lock()
        self._writer: BagWriter | None = BagWriter(path)
        self._subs: dict[str, Any] = {}
        self._seen: set[str] = set()
        self._wanted = dict(RECORDABLE)
        for t in extra:
            if t not in self._wanted:
                self.get_logger().warn(f"topic {t}: type unknown until it appears in the graph")
        self._extra = set(extra)
        for topic, typ in msgs.TOPICS.items():
            if topic in RECORDABLE or topic in self._extra:
                self._subscribe(topic, typ)
        self._subscribe("/diagnostics", RECORDABLE["/diagnostics"])
        self.create_timer(float(self.get_parameter("scan_period_s").value), self._scan)
        self.get_logger().info(f"recording to {path}")

    def _subscribe(self, topic: str, msgtype: str) -> None:
        if topic in self._subs:
            return
        qos = LATCHED_QOS if topic.startswith("/fdi/fault_") else DATA_IN_QOS
        cls = _msg_class(msgtype)
        self._subs[topic] = self.create_subscription(
            cls, topic, partial(self._on_msg, topic, msgtype), qos, raw=True)

    def _scan(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self._subs or topic in msgs.BATCHED_TOPICS and topic not in self._extra:
                continue
            for typ in types:
                if (topic in self._extra or typ.startswith(f"{msgs.PACKAGE}/")
                        or RECORDABLE.get(topic) == typ):
                    self._subscribe(topic, typ)
                    self.get_logger().info(f"recording new topic {topic} [{typ}]")
                    break

    def _offered_qos(self, topic: str) -> list[dict] | None:
        """The publishers' offered QoS profiles, for the bag's metadata (as rosbag2 does)."""
        out = []
        for info in self.get_publishers_info_by_topic(topic):
            q = info.qos_profile
            out.append({"depth": int(q.depth),  # 0: not known from discovery
                        "history": q.history.name.lower(),
                        "reliability": q.reliability.name.lower(),
                        "durability": q.durability.name.lower(),
                        "liveliness": q.liveliness.name.lower()})
        return out or None

    def _on_msg(self, topic: str, msgtype: str, data: bytes) -> None:
        t_ns = self.get_clock().now().nanoseconds
        with self._lock:
            if self._writer is not None:
                qos = None if topic in self._seen else self._offered_qos(topic)
                self._seen.add(topic)
                self._writer.write_raw(topic, msgtype, data, t_ns, qos)

    def close(self) -> None:
        with self._lock:
            if self._writer is not None:
                n = self._writer.count
                self._writer.close()
                self._writer = None
                print(f"[fdi_recorder] bag closed with {n} messages", flush=True)


def main(args: list[str] | None = None) -> int:
    return run_node(RecorderNode, on_shutdown=lambda n: n.close(), args=args)


if __name__ == "__main__":
    raise SystemExit(main())
