"""Residual generator: a LifecycleNode holding ONE model of the bank (one process per model).

Lifecycle (standard services ``/<node>/change_state``, ``/<node>/get_state``):

* ``configure``: load the model named by the parameters (``model_id``, ``model``: a spec or
  file understood by :func:`fdi_ros.plants.load_residual_model`); residual publisher and
  features subscription. A model that fails to load -> FAILURE, the reason logged.
* ``activate``: the model's state is reset (it starts from the measured state); residuals
  from the step after the bank switch that brought it on line (the features since then were
  kept, /fdi/diagnosis followed while not active: :class:`fdi_ros.core.modelfeed.ModelFeed`).
* ``deactivate``: nothing is published; ``cleanup``: model, publisher, subscriptions gone.

Parameters: ``model_id`` (string, required), ``model`` (spec string / path, required), and
how the vectors travel (``batched``, topics: :mod:`fdi_ros.nodes.bankio`).
"""

from __future__ import annotations

import traceback
from typing import Any

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from fdi_ros.core.modelfeed import ModelFeed
from fdi_ros.nodes import bankio
from fdi_ros.nodes.common import DATA_IN_QOS, Param, declare_params, run_node

# Read on configure: a change applies at the next configure (hence read-only while running).
PARAMS = (
    Param("model_id", "", "bank model id, e.g. 'nominal'", read_only=True),
    Param("model", "", "model spec (YAML/JSON mapping) or model file path", read_only=True),
    *bankio.PARAMS,
)


class ResidualNode(LifecycleNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("fdi_residual", **kwargs)
        declare_params(self, PARAMS)
        self._model: Any = None
        self._io: bankio.ModelIO | None = None
        self._subs: dict[str, Any] = {}
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
            self._feed = ModelFeed(mid)
            self._io = bankio.ModelIO(self, self._on_vectors)
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
        if self._io is not None:
            self._io.release()
        self._subs, self._io, self._model = {}, None, None

    # -- data -----------------------------------------------------------------------------------
    def _on_vectors(self, fvs: list[Any]) -> None:
        out: list[Any] = []
        for fv in fvs:
            out += self._feed.features(fv.index, fv)
        self._answer(out)

    def _on_diagnosis(self, m: Any) -> None:
        self._answer(self._feed.diagnosis(m.index, m.models_online))

    def _answer(self, features: list[Any]) -> None:
        out = []
        try:  # a block's segments computed together where the model can (else one by one)
            if (pre := getattr(self._model, "prefetch", None)) is not None and features:
                pre(features)
        except Exception as exc:
            self.get_logger().warn(f"prefetch: {exc}", throttle_duration_sec=5.0)
        for fv in features if self._model is not None else ():
            try:
                out.append(self._model.residuals(fv))
            except Exception as exc:  # a bad feature vector must not kill the model node
                self.get_logger().warn(f"features {fv.index}: {exc}", throttle_duration_sec=5.0)
        if out and self._io is not None:
            self._io.publish(out)
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
