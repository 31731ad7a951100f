"""One residual message per model host and sensor block (``ResidualBundle`` on
``/fdi/residual_bundles``) instead of one ``ResidualBlock`` per hosted node.

Every hosted node still reads the feature blocks and owns its residual publishers (the
supervisor's start-up handshake and ``ros2 topic info`` see each node as before); only where a
block's answers go changes. A node hands the ResidualBlocks it computed for a FeatureBlock to
the host's :class:`Bundler`; once every node of the host that reads the feature blocks has
answered that block (an inactive node answers with nothing), they leave as one message. One
rclpy publish costs about 0.3 ms in the loaded graph: eight per block per host were a fifth of
a host's time at 200 segments/s.

No reader loses anything: the blocks go the per-node way (each node's own lifecycle publisher)
while the bundle publisher has fewer matched readers than the node's block publisher (at start
up, before discovery has matched the supervisor's bundle reader; or while a user's node reads
the per-node blocks), and whatever a node answers outside a block callback (the backlog
answered on activation) is published by the node itself. A block one node never answers (its
message lost) leaves with the next block's, or after ``STALE_S`` on the steady clock (the
last block of the data).
"""

from __future__ import annotations

import time
from typing import Any

from fdi_ros.nodes.common import DATA_QOS

BUNDLES_TOPIC = "/fdi/residual_bundles"
STALE_S = 0.05  # a block some node has not answered this long leaves without it


class Bundler:
    """The host's collector of its nodes' ResidualBlocks per feature block."""

    def __init__(self, node: Any) -> None:
        from fdi_msgs.msg import ResidualBundle

        self._cls = ResidualBundle
        self._pub = node.create_publisher(ResidualBundle, BUNDLES_TOPIC, DATA_QOS)
        self._members: list[Any] = []   # the nodes' ModelIOs reading feature blocks
        self._block: int | None = None  # the feature block being answered
        self._answered: list[Any] = []
        self._pending: list[tuple[Any, list[Any]]] = []
        self._since = 0.0  # steady time of the block's first answer
        from fdi_ros.nodes.spin import wall_timer

        wall_timer(node, STALE_S, self._stale)

    def _stale(self) -> None:
        if self._block is not None and time.monotonic() - self._since > STALE_S:
            self.flush()

    def join(self, io: Any) -> None:
        self._members.append(io)

    def leave(self, io: Any) -> None:
        if io in self._members:
            self._members.remove(io)
        self._answered = [a for a in self._answered if a is not io]
        self._flush_if_complete()

    def answer(self, io: Any, block: int, messages: list[Any]) -> None:
        """``io``'s ResidualBlocks for feature block ``block`` (empty: nothing to send)."""
        if block != self._block:
            self.flush()   # an older block some node never answered
            self._block, self._since = block, time.monotonic()
        self._answered.append(io)
        if messages:
            self._pending.append((io, messages))
        self._flush_if_complete()

    def _flush_if_complete(self) -> None:
        if self._block is not None and all(m in self._answered for m in self._members):
            self.flush()

    def flush(self) -> None:
        pending, self._pending = self._pending, []
        self._answered, self._block = [], None
        together = []
        readers = self._pub.get_subscription_count()
        for io, messages in pending:
            pub = io.blocks_publisher
            if readers > 0 and readers >= pub.get_subscription_count():
                if pub.is_activated:   # the node's lifecycle decides, as for its own topic
                    together += messages
            else:
                for m in messages:
                    pub.publish(m)
        if together:
            self._pub.publish(self._cls(header=together[-1].header, blocks=together))
