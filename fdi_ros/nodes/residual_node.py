"""Residual generator: a LifecycleNode holding ONE model of the bank (one process per model).

Lifecycle (standard services ``/<node>/change_state``, ``/<node>/get_state``):

* ``configure``: load the model named by the parameters (``model_id``, ``model``: a spec or
  file understood by :func:`fdi_ros.plants.load_residual_model`); create the
  residual publisher and the features and diagnosis subscriptions. A model that fails to
  load -> FAILURE, with the reason logged (rclpy would otherwise swallow it).
* ``activate``: the model's dynamic state is reset, so a model taken on line after an
  isolation starts from the measured state; residuals are published from now on, from the
  step after the bank switch that brought it on line (the features since then were kept:
  :class:`fdi_ros.core.modelfeed.ModelFeed`), as offline.
* ``deactivate``: nothing is published (features are kept for the next activation).
* ``cleanup``: model, publisher and subscription released.

Parameters: ``model_id`` (string, required), ``model`` (spec string / path, required),
``features_topic`` (/fdi/features), ``residuals_topic`` (/fdi/residuals).
"""

from __future__ import annotations

import traceback
from typing import Any

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from fdi_ros import msgs
from fdi_ros.core.modelfeed import ModelFeed
from fdi_ros.nodes.common import DATA_IN_QOS, DATA_QOS, Param, declare_params, run_node

# Read on configure: a change applies at the next configure (hence read-only while running).
PARAMS = (
    Param("model_id", "", "bank model id, e.g. 'nominal'", read_only=True),
    Param("model", "", "model spec (YAML/JSON mapping) or model file path", read_only=True),
    Param("features_topic", "/fdi/features", "feature vectors in", read_only=True),
    Param("residuals_topic", "/fdi/residuals", "residuals out", read_only=True),
)


class ResidualNode(LifecycleNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("fdi_residual", **kwargs)
        declare_params(self, PARAMS)
        self._model: Any = None
        self._pub: Any = None
        self._subs: list[Any] = []
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
            from fdi_msgs.msg import Diagnosis, Features, Residuals

            self._pub = self.create_lifecycle_publisher(
                Residuals, self.get_parameter("residuals_topic").value, DATA_QOS)
            self._feed = ModelFeed(mid)
            self._subs = [self.create_subscription(c, t, f, DATA_IN_QOS) for c, t, f in (
                (Features, self.get_parameter("features_topic").value, self._on_features),
                (Diagnosis, "/fdi/diagnosis", self._on_diagnosis))]
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
        self.get_logger().info(f"model {self.model_id!r} off line")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def _release(self) -> None:
        self._feed.deactivate()
        for sub in self._subs:
            self.destroy_subscription(sub)
        if self._pub is not None:
            self.destroy_lifecycle_publisher(self._pub)
        self._subs, self._pub, self._model = [], None, None

    # -- data -----------------------------------------------------------------------------------
    def _on_features(self, m: Any) -> None:
        self._answer(self._feed.features(m.index, m))

    def _on_diagnosis(self, m: Any) -> None:
        self._answer(self._feed.diagnosis(m.index, m.models_online))

    def _answer(self, features: list[Any]) -> None:
        for m in features if self._model is not None else ():
            fv = msgs.to_features(m)
            try:
                rv = self._model.residuals(fv)
            except Exception as exc:  # a bad feature vector must not kill the model node
                self.get_logger().warn(f"features {fv.index}: {exc}", throttle_duration_sec=5.0)
                continue
            self._pub.publish(self._fac.residuals(rv))
            self.n_published += 1


def main(args: list[str] | None = None) -> int:
    return run_node(ResidualNode, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
