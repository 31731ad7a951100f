"""Residual generator: a LifecycleNode holding ONE model of the bank (one process per model).

Lifecycle (standard services ``/<node>/change_state``, ``/<node>/get_state``):

* ``configure``: load the model named by the parameters (``model_id``, ``model``: a spec or
  file understood by :func:`fdi_ros.plants.load_residual_model`); residual publisher and
  features subscription. A model that fails to load -> FAILURE, the reason logged.
* ``activate``: the model's state is reset (it starts from the measured state); residuals
  from the step after the bank switch that brought it on line (the features since then were
  kept, /fdi/diagnosis followed while not active: :class:`fdi_ros.core.modelfeed.ModelFeed`).
* ``deactivate``: nothing is published; ``cleanup``: model, publisher, subscriptions gone.

Parameters: ``model_id`` (string, required), ``model`` (spec string / path, required),
``batched`` (true: the vectors of a sensor block in one message each way,
``feature_blocks_topic`` in and ``residual_blocks_topic`` out, plus one message per vector
on ``residuals_topic`` while anyone reads it; false: one message per vector each way,
``features_topic`` in and ``residuals_topic`` out), ``features_topic`` (/fdi/features),
``residuals_topic`` (/fdi/residuals), ``feature_blocks_topic`` (/fdi/feature_blocks),
``residual_blocks_topic`` (/fdi/residual_blocks).

The model answers vector by vector either way; batching saves the messages (and, in a model
host, the nodes of one process decode each FeatureBlock once).
"""

from __future__ import annotations

import traceback
from collections import OrderedDict
from typing import Any

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from fdi_ros import msgs
from fdi_ros.core.modelfeed import ModelFeed
from fdi_ros.core.types import FeatureVector
from fdi_ros.nodes.common import DATA_IN_QOS, DATA_QOS, Param, declare_params, run_node

# Read on configure: a change applies at the next configure (hence read-only while running).
PARAMS = (
    Param("model_id", "", "bank model id, e.g. 'nominal'", read_only=True),
    Param("model", "", "model spec (YAML/JSON mapping) or model file path", read_only=True),
    Param("features_topic", "/fdi/features", "feature vectors in", read_only=True),
    Param("residuals_topic", "/fdi/residuals", "residuals out", read_only=True),
    Param("batched", True, "true: a sensor block's feature vectors in one message, its "
          "residuals in one message; false: one message per vector", read_only=True),
    Param("feature_blocks_topic", "/fdi/feature_blocks", "feature blocks in (batched)",
          read_only=True),
    Param("residual_blocks_topic", "/fdi/residual_blocks", "residual blocks out (batched)",
          read_only=True),
)

BLOCK_MAX = 200  # residual vectors per ResidualBlock at most

# FeatureBlocks decoded in this process (the nodes of a model host receive the same block):
# key -> feature vectors; a hit is the same bytes
_DECODED: OrderedDict[tuple, list[Any]] = OrderedDict()


def decoded_block(m: Any) -> list[Any]:
    """The feature vectors of FeatureBlock ``m``, decoded once per process."""
    key = (m.plant, m.block_index, m.header.stamp.sec, m.header.stamp.nanosec, tuple(m.names),
           bytes(memoryview(m.index)), bytes(memoryview(m.values)), tuple(m.status),
           tuple(m.valid))
    hit = _DECODED.get(key)
    if hit is None:
        hit = _DECODED[key] = msgs.to_feature_list(m)
        if len(_DECODED) > 8:
            _DECODED.popitem(last=False)
    return hit


class ResidualNode(LifecycleNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("fdi_residual", **kwargs)
        declare_params(self, PARAMS)
        self._model: Any = None
        self._pub: Any = None
        self._pub_blocks: Any = None
        self._subs: dict[str, Any] = {}
        self._fac = msgs.MessageFactory("rclpy")
        self._feed: ModelFeed[Any] = ModelFeed(self.model_id)
        self.n_published = 0

    @property
    def model_id(self) -> str:
        return str(self.get_parameter("model_id").value)

    # -- lifecycle ------------------------------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            from fdi_ros.plants import load_residual_model

            mid = self.model_id
            spec = self.get_parameter("model").value
            if not mid or not spec:
                raise ValueError("parameters 'model_id' and 'model' are required")
            if spec.lstrip().startswith("{"):  # an inline YAML/JSON mapping, not a path
                import yaml

                spec = yaml.safe_load(spec)
            self._model = load_residual_model(spec, model_id=mid)
            from fdi_msgs.msg import FeatureBlock, Features, ResidualBlock, Residuals

            self._pub = self.create_lifecycle_publisher(
                Residuals, self.get_parameter("residuals_topic").value, DATA_QOS)
            self._feed = ModelFeed(mid)
            if self.get_parameter("batched").value:
                self._pub_blocks = self.create_lifecycle_publisher(
                    ResidualBlock, self.get_parameter("residual_blocks_topic").value, DATA_QOS)
                self._subs["features"] = self.create_subscription(
                    FeatureBlock, self.get_parameter("feature_blocks_topic").value,
                    self._on_feature_block, DATA_IN_QOS)
            else:
                self._subs["features"] = self.create_subscription(
                    Features, self.get_parameter("features_topic").value, self._on_features,
                    DATA_IN_QOS)
            self._watch()
        except Exception:
            self.get_logger().error(f"configure failed:\n{traceback.format_exc()}")
            self._release()
            return TransitionCallbackReturn.FAILURE
        self.get_logger().info(f"model {self.model_id!r} loaded")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            reset = getattr(self._model, "reset", None)
            if callable(reset):
                reset()
        except Exception:
            self.get_logger().error(f"activate failed:\n{traceback.format_exc()}")
            return TransitionCallbackReturn.FAILURE
        self.get_logger().info(f"model {self.model_id!r} on line")
        done = super().on_activate(state)
        self._answer(self._feed.activate())
        return done

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._feed.deactivate()
        self._watch()
        self.get_logger().info(f"model {self.model_id!r} off line")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    on_shutdown = on_cleanup

    def _release(self) -> None:
        self._feed.deactivate()
        for sub in self._subs.values():
            self.destroy_subscription(sub)
        for pub in (self._pub, self._pub_blocks):
            if pub is not None:
                self.destroy_lifecycle_publisher(pub)
        self._subs, self._pub, self._pub_blocks, self._model = {}, None, None, None

    # -- data -----------------------------------------------------------------------------------
    def _on_features(self, m: Any) -> None:
        self._answer(self._feed.features(m.index, m))

    def _on_feature_block(self, m: Any) -> None:
        try:
            fvs = decoded_block(m)
        except (ValueError, TypeError) as exc:
            self.get_logger().error(f"malformed feature block dropped: {exc}")
            return
        out: list[Any] = []
        for fv in fvs:
            out += self._feed.features(fv.index, fv)
        self._answer(out)

    def _on_diagnosis(self, m: Any) -> None:
        self._answer(self._feed.diagnosis(m.index, m.models_online))

    def _answer(self, features: list[Any]) -> None:
        out = []
        for m in features if self._model is not None else ():
            fv = m if isinstance(m, FeatureVector) else msgs.to_features(m)
            try:
                rv = self._model.residuals(fv)
            except Exception as exc:  # a bad feature vector must not kill the model node
                self.get_logger().warn(f"features {fv.index}: {exc}", throttle_duration_sec=5.0)
                continue
            out.append(rv)
        if self._pub_blocks is None or self._pub.get_subscription_count() > 0:
            for rv in out:
                self._pub.publish(self._fac.residuals(rv))
        if self._pub_blocks is not None:
            for i in range(0, len(out), BLOCK_MAX):  # a backlog answered at activation
                for msg in self._fac.residual_blocks(out[i:i + BLOCK_MAX]):
                    self._pub_blocks.publish(msg)
        self.n_published += len(out)
        self._watch()

    def _watch(self) -> None:  # /fdi/diagnosis only while the feed needs it (not answering)
        need = self._model is not None and not self._feed.answering
        if need and "diagnosis" not in self._subs:
            from fdi_msgs.msg import Diagnosis

            self._subs["diagnosis"] = self.create_subscription(
                Diagnosis, "/fdi/diagnosis", self._on_diagnosis, DATA_IN_QOS)
        elif not need and "diagnosis" in self._subs:
            self.destroy_subscription(self._subs.pop("diagnosis"))


def main(args: list[str] | None = None) -> int:
    return run_node(ResidualNode, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
