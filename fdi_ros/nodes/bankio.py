"""How the bank's feature and residual vectors travel: a sensor block's vectors per message
(batched: ``FeatureBlock`` on ``/fdi/feature_blocks``, ``ResidualBlock`` on
``/fdi/residual_blocks``) or one vector per message (``Features``, ``Residuals``).

Batching saves the messages, not the computation: the models still answer vector by vector.
At 16 bank models a per-vector graph sends 32 messages per 180 deg CA segment through the
hosts and the supervisor; batched, two per sensor block and model (the 3600 rpm bench went
from 1.61 to 0.89 cores). A batched model node still publishes one message per vector on
``/fdi/residuals`` while anyone reads it (a recorder, a user's node).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fdi_ros import msgs
from fdi_ros.core.types import FeatureVector, ResidualVector
from fdi_ros.nodes.common import DATA_IN_QOS, DATA_QOS, Param

BLOCK_MAX = 200  # residual vectors per ResidualBlock at most (a backlog answered at once)

PARAMS = (
    Param("batched", True, "true: a sensor block's feature vectors in one message, its "
          "residuals in one message; false: one message per vector", read_only=True),
    Param("features_topic", "/fdi/features", "feature vectors in (not batched)",
          read_only=True),
    Param("residuals_topic", "/fdi/residuals", "residuals out, one per message",
          read_only=True),
    Param("feature_blocks_topic", "/fdi/feature_blocks", "feature blocks in (batched)",
          read_only=True),
    Param("residual_blocks_topic", "/fdi/residual_blocks", "residual blocks out (batched)",
          read_only=True),
)


class ModelIO:
    """A model node's features subscription and residual publishers, in the mode of its
    parameters (see :data:`PARAMS`); ``on_vectors`` receives the decoded feature vectors."""

    def __init__(self, node: Any, on_vectors: Callable[[list[FeatureVector]], None]) -> None:
        from fdi_msgs.msg import FeatureBlock, Features, ResidualBlock, Residuals

        p = lambda k: node.get_parameter(k).value  # noqa: E731
        self.node, self._on = node, on_vectors
        self.batched = bool(p("batched"))
        self._fac = msgs.MessageFactory("rclpy")
        self._pub = node.create_lifecycle_publisher(Residuals, p("residuals_topic"), DATA_QOS)
        self._blocks = node.create_lifecycle_publisher(
            ResidualBlock, p("residual_blocks_topic"), DATA_QOS) if self.batched else None
        self.sub = node.create_subscription(
            FeatureBlock if self.batched else Features,
            p("feature_blocks_topic" if self.batched else "features_topic"),
            self._on_block if self.batched else self._on_one, DATA_IN_QOS)
        # in a model host: a block's answers leave with the host's other nodes' (nodes/bundle)
        self._bundler = getattr(node, "bundler", None) if self.batched else None
        self._held: list[Any] | None = None
        if self._bundler is not None:
            self._bundler.join(self, urgent=bool(getattr(node, "bundle_urgent", False)))

    @property
    def blocks_publisher(self) -> Any:
        return self._blocks

    def _on_one(self, m: Any) -> None:
        self._decoded(lambda: [msgs.to_features(m)])

    def _on_block(self, m: Any) -> None:
        if self._bundler is None or not self._bundler.defer(self, m):
            self.take_block(m)

    def take_block(self, m: Any) -> None:
        """Answer FeatureBlock ``m`` (in a host: the answer goes to its bundler)."""
        if self._bundler is not None:
            self._held = []
        try:
            self._decoded(lambda: msgs.to_feature_list_shared(m))
        finally:
            if self._bundler is not None:
                held, self._held = self._held or [], None
                self._bundler.answer(self, int(m.block_index), held)

    def _decoded(self, decode: Callable[[], list[FeatureVector]]) -> None:
        try:
            fvs = decode()
        except (ValueError, TypeError) as exc:  # a malformed message is dropped, never fatal
            self.node.get_logger().error(f"malformed features dropped: {exc}")
            return
        self._on(fvs)

    def publish(self, out: list[ResidualVector]) -> None:
        """The residual vectors answered now, in the node's mode."""
        if self._blocks is None or self._pub.get_subscription_count() > 0:
            for rv in out:
                self._pub.publish(self._fac.residuals(rv))
        if self._blocks is not None:
            for i in range(0, len(out), BLOCK_MAX):
                for msg in self._fac.residual_blocks(out[i:i + BLOCK_MAX]):
                    if self._held is not None:  # answering a feature block in a host
                        self._held.append(msg)
                    else:
                        self._blocks.publish(msg)

    def release(self) -> None:
        if self._bundler is not None:
            self._bundler.leave(self)
        self.node.destroy_subscription(self.sub)
        for pub in (self._pub, self._blocks):
            if pub is not None:
                self.node.destroy_lifecycle_publisher(pub)


def supervisor_inputs(batched: bool
                      ) -> tuple[tuple[str, Any, Callable[[Any], list], bool], ...]:
    """(topic, message class, decode to a list of vectors, residuals (else features)) of what
    the supervisor reads (see :data:`fdi_ros.core.supervision.DATA_TOPICS`)."""
    from fdi_msgs.msg import FeatureBlock, Features, ResidualBlock, Residuals

    from fdi_ros.core.supervision import DATA_TOPICS
    from fdi_ros.nodes.bundle import BUNDLES_TOPIC

    f_t, r_t = DATA_TOPICS[batched]
    if batched:   # (model hosts send their nodes' residual blocks as one bundle: nodes/bundle)
        from fdi_msgs.msg import ResidualBundle

        return ((r_t, ResidualBlock, msgs.to_residual_list, True),
                (f_t, FeatureBlock, msgs.to_feature_list, False),
                (BUNDLES_TOPIC, ResidualBundle, msgs.to_bundle_list, True))
    return ((r_t, Residuals, lambda m: [msgs.to_residuals(m)], True),
            (f_t, Features, lambda m: [msgs.to_features(m)], False))


def fed(logger: Any, convert: Callable[[Any], list], feed: Callable[[Any, float], list],
        do: Callable[[list], None]) -> Callable[[Any], None]:
    """A subscription callback of the supervisor: the message's vectors (``convert``) fed to
    the core one by one (``feed(vector, wall time)``), the core's actions done by ``do``; a
    malformed message is dropped and logged, never fatal."""
    import time

    def callback(m: Any) -> None:
        try:
            recs = convert(m)
        except (ValueError, TypeError, KeyError, IndexError) as exc:
            logger.warn(f"malformed message dropped: {exc}")
            return
        for rec in recs:
            do(feed(rec, time.monotonic()))
    return callback
