"""Preprocessor node: sensor blocks -> feature vectors (crank-synchronous segments for an
engine, one vector per sample for others), via :func:`fdi_ros.plants.make_preprocessor`.

Every vector goes out twice: one message per vector on ``/fdi/features`` (for recorders and
users' nodes) and, batched, the vectors each sensor block completed in one ``FeatureBlock`` on
``/fdi/feature_blocks`` (what the bank and the supervisor read: one message per block instead
of one per segment for each of them).

A gap in the block counter (a dropped block) is logged and the partial segment across it is
marked invalid by the core, so a lost message never yields numbers that look valid. At the
source's end of the data it says ``end_of_features`` once every block is handled
(:class:`fdi_ros.nodes.endofdata.EndOfFeatures`).

Parameters: ``plant`` (a registered plant id; required).
"""

from __future__ import annotations

import time
from typing import Any

from rclpy.node import Node

from fdi_ros import msgs
from fdi_ros.core.handshake import parse_readers, unmatched_readers
from fdi_ros.nodes.common import (
    DATA_IN_QOS,
    DATA_QOS,
    LATCHED_QOS,
    Param,
    declare_params,
    run_node,
    wall_timer,
)
from fdi_ros.nodes.endofdata import EndOfFeatures
from fdi_ros.nodes.startup import READY_TOPIC

HOLD_MAX_S = 10.0  # wall s the first vectors wait for their readers to be matched

PARAMS = (Param("plant", "", "plant id of the plant registry: which "
                "preprocessor turns sensor blocks into feature vectors", read_only=True),)


class PreprocessorNode(Node):
    def __init__(self) -> None:
        super().__init__("fdi_preprocessor")
        declare_params(self, PARAMS)
        from fdi_msgs.msg import FeatureBlock, Features, SensorBlock
        from std_msgs.msg import Header

        from fdi_ros.plants import make_preprocessor

        self.pre = make_preprocessor(self.get_parameter("plant").value)
        self._fac = msgs.MessageFactory("rclpy")
        self._pub = self.create_publisher(Features, "/fdi/features", DATA_QOS)
        self._pub_blocks = self.create_publisher(FeatureBlock, "/fdi/feature_blocks", DATA_QOS)
        self.create_subscription(SensorBlock, "/fdi/sensor_block", self._on_block, DATA_IN_QOS)
        self._last_index: int | None = None
        self._end = EndOfFeatures(self)
        self._last_features = -1
        # the first vectors wait until every reader of them is matched: those this node's
        # graph shows and those the supervisor saw when it said ready (discovery reaches each
        # process at its own pace; a reader not yet matched would miss them), HOLD_MAX_S at most
        self._held: list[tuple[Any, Any, int]] | None = []
        self._held_since = 0.0
        self._held_blocks = 0
        self._hold_timer = wall_timer(self, 0.02, self._release)
        self._needed: dict[str, set[str]] | None = None  # the readers the supervisor saw
        self._ready_sub = self.create_subscription(Header, READY_TOPIC, self._on_ready,
                                                   LATCHED_QOS)

    def _on_ready(self, m: Any) -> None:
        needed = parse_readers(m.frame_id)  # None: the ready signal itself
        if needed is not None:
            self._needed = needed

    def _on_block(self, m: Any) -> None:
        self._push(m)
        if self._held is None:
            self._end.block(self._last_features)
        else:  # counted once its vectors are out (the end is said after them)
            self._held_blocks += 1

    def _push(self, m: Any) -> None:
        try:
            block = msgs.to_sample_block(m)
        except ValueError as exc:
            self.get_logger().error(f"malformed sensor block dropped: {exc}")
            return
        if self._last_index is not None and block.index != self._last_index + 1:
            self.get_logger().warn(f"sensor blocks {self._last_index + 1}..{block.index - 1} "
                                   "missing: the segment across the gap is invalid")
            self.pre.mark_gap()
        self._last_index = block.index
        try:
            feats = self.pre.push(block)
        except ValueError as exc:  # e.g. crank angles going backwards (a restarted source)
            self.get_logger().error(f"sensor block {block.index} rejected ({exc}); "
                                    "restarting segmentation")
            self.pre.reset()
            return
        out = [(self._pub, self._fac.features(fv), fv.index) for fv in feats]
        out += [(self._pub_blocks, m, feats[-1].index)
                for m in self._fac.feature_blocks(feats, block.index)]
        if self._held is None:
            self._send(out)
        else:
            self._held_since = self._held_since or time.monotonic()
            self._held += out
            self._release()

    def _release(self) -> None:
        if not self._held:  # nothing yet (the decision is taken with the first vectors)
            return
        pubs = {"/fdi/features": self._pub, "/fdi/feature_blocks": self._pub_blocks}
        unmatched = unmatched_readers(
            self._needed, {t: [i.node_name for i in self.get_subscriptions_info_by_topic(t)]
                           for t in pubs}, {t: p.get_subscription_count()
                                            for t, p in pubs.items()})
        if self._needed is None and self.count_publishers(READY_TOPIC):
            unmatched.append("the readers the supervisor saw (on /fdi/ready)")
        late = bool(self._held) and time.monotonic() - self._held_since > HOLD_MAX_S
        if unmatched and not late:
            return
        if unmatched:
            self.get_logger().warn(f"after {HOLD_MAX_S:g} s still {'; '.join(unmatched)}; "
                                   "sending anyway")
        elif self._held:
            self.get_logger().info(f"first vectors held {time.monotonic() - self._held_since:.3f}"
                                   " s until every reader of them was matched")
        self.destroy_subscription(self._ready_sub)
        held, self._held = self._held, None
        self.destroy_timer(self._hold_timer)
        self._send(held)
        for _ in range(self._held_blocks):
            self._end.block(self._last_features)

    def _send(self, out: list[tuple[Any, Any, int]]) -> None:
        for pub, m, index in out:
            pub.publish(m)
            self._last_features = max(self._last_features, index)


def main(args: list[str] | None = None) -> int:
    return run_node(PreprocessorNode, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
