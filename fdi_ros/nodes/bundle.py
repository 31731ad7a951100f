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

A node the host names *urgent* (the model whose residuals give the symptoms) does not wait
for the others: it computes a block first and its answer leaves at once, in a bundle of its
own, so the symptoms need not wait for every hypothesis of the host. The executor runs the
nodes' callbacks for one message in an order of the middleware's choosing; a node's callback
for a block the urgent nodes have not answered yet is therefore deferred (:meth:`defer`) and
run right after their answer (or after ``STALE_S``, if they do not answer it). Every node
still takes its own messages in order.
"""

from __future__ import annotations

import time
from typing import Any

from fdi_ros.nodes.common import DATA_QOS

BUNDLES_TOPIC = "/fdi/residual_bundles"
STALE_S = 0.05  # a block some node has not answered this long leaves without it


class Bundler:
    """The host's collector of its nodes' ResidualBlocks per feature block."""

    def __init__(self, pub: Any, make: Any) -> None:
        """``pub``: the bundle publisher; ``make(header=, blocks=)``: a bundle message."""
        self._pub, self._make = pub, make
        self._members: list[Any] = []   # the nodes' ModelIOs reading feature blocks
        self._urgent: list[Any] = []    # members whose answers leave at once
        self._block: int | None = None  # the feature block being answered
        self._answered: list[Any] = []
        self._pending: list[tuple[Any, list[Any]]] = []
        self._since = 0.0  # steady time of the block's first answer
        self._urgent_last: dict[Any, int] = {}   # the last block each urgent node answered
        self._deferred: list[tuple[Any, Any, float]] = []   # (node io, FeatureBlock, since)

    @classmethod
    def on(cls, node: Any) -> Bundler:
        """The host's bundler, publishing and checking for stale blocks through ``node``."""
        from fdi_msgs.msg import ResidualBundle

        from fdi_ros.nodes.spin import wall_timer

        b = cls(node.create_publisher(ResidualBundle, BUNDLES_TOPIC, DATA_QOS), ResidualBundle)
        wall_timer(node, STALE_S, b._stale)
        return b

    def _stale(self) -> None:
        now = time.monotonic()
        if self._deferred and now - self._deferred[0][2] > STALE_S:
            self._run_deferred(None)   # the urgent nodes do not answer: the others go on
        if self._block is not None and now - self._since > STALE_S:
            self.flush()

    def defer(self, io: Any, m: Any) -> bool:
        """Whether ``io``'s callback for FeatureBlock ``m`` waits for the urgent nodes' answer
        to it (kept here and run after it); never for an urgent node, nor before every
        urgent node has answered a block at all (start-up), nor behind a node's own
        deferred blocks (its blocks stay in order)."""
        if not any(d[0] is io for d in self._deferred):
            if io in self._urgent or not self._urgent:
                return False
            last = min(self._urgent_last.get(u, -1) for u in self._urgent)
            if last < 0 or last >= int(m.block_index):
                return False
        self._deferred.append((io, m, time.monotonic()))
        return True

    def _run_deferred(self, through: int | None) -> None:
        """Run the deferred callbacks of blocks up to ``through`` (None: all), in order."""
        while self._deferred and (through is None
                                  or int(self._deferred[0][1].block_index) <= through):
            io, m, _ = self._deferred.pop(0)
            io.take_block(m)

    def join(self, io: Any, *, urgent: bool = False) -> None:
        self._members.append(io)
        if urgent:
            self._urgent.append(io)

    def leave(self, io: Any) -> None:
        was_urgent = io in self._urgent
        for group in (self._members, self._urgent):
            if io in group:
                group.remove(io)
        self._urgent_last.pop(io, None)
        self._deferred = [d for d in self._deferred if d[0] is not io]
        if was_urgent:
            self._run_deferred(None)
        self._answered = [a for a in self._answered if a is not io]
        self._flush_if_complete()

    def answer(self, io: Any, block: int, messages: list[Any]) -> None:
        """``io``'s ResidualBlocks for feature block ``block`` (empty: nothing to send)."""
        if block != self._block:
            self.flush()   # an older block some node never answered
            self._block, self._since = block, time.monotonic()
        self._answered.append(io)
        if io in self._urgent:   # leaves at once, then the others waiting for it run
            self._send([(io, messages)])
            self._urgent_last[io] = block
        elif messages:
            self._pending.append((io, messages))
        self._flush_if_complete()
        if io in self._urgent and all(u in self._urgent_last for u in self._urgent):
            self._run_deferred(min(self._urgent_last[u] for u in self._urgent))

    def _flush_if_complete(self) -> None:
        if self._block is not None and all(m in self._answered for m in self._members):
            self.flush()

    def flush(self) -> None:
        pending, self._pending = self._pending, []
        self._answered, self._block = [], None
        self._send(pending)

    def _send(self, pending: list[tuple[Any, list[Any]]]) -> None:
        """The nodes' blocks as one bundle, or each by its node while the bundle has fewer
        readers than the node's own topic."""
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
            self._pub.publish(self._make(header=together[-1].header, blocks=together))
