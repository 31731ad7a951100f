"""A model brought on line by a bank switch answers from the step after the switch, live as
offline, however late its activation and in whatever order the messages come (no ROS: the
supervisor's core, each model node's feed and the lifecycle calls as timed events)."""

from __future__ import annotations

import heapq
import itertools
import random
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from toy_bank import toy_config

from fdi_ros.core.bankdriver import ACTIVE, INACTIVE, ChangeState, GetState
from fdi_ros.core.diagnoser import diagnose_offline
from fdi_ros.core.graphconfig import load_graph_config
from fdi_ros.core.modelfeed import ModelFeed
from fdi_ros.core.residual_models import register_residual_model
from fdi_ros.core.supervision import Publish, SupervisorCore
from fdi_ros.core.types import FeatureVector, ResidualVector


def test_feed_answers_from_the_step_after_the_switch_whatever_comes_first():
    seed = int(time.time_ns() % 2**31)
    rng = random.Random(seed)
    for _ in range(200):
        feed: ModelFeed[int] = ModelFeed("m")
        answered: list[int] = []
        # features k come at k, their diagnosis at k + lag; the switch at step ``switch``
        # is decided when its diagnosis is sent (a little before it comes), the activation
        # comes a random time later (or earlier than that diagnosis)
        switch, lag = rng.randint(1, 30), rng.randint(0, 40) + 0.5
        activated = max(lag + 0.1, switch + lag + rng.uniform(-3.0, 40.0))
        # the features' own channel late by a random time, in order: features of steps up to
        # the switch may reach the node after its activation
        arrive = list(itertools.accumulate(
            (k + rng.expovariate(1 / 10.0) for k in range(80)), max))
        events = sorted([("f", k, arrive[k]) for k in range(80)] +
                        [("d", k, k + lag) for k in range(80)] +
                        [("a", -1, activated)], key=lambda e: e[2])
        for kind, k, _ in events:
            if kind == "f":
                answered += feed.features(k, k)
            elif kind == "d":
                answered += feed.diagnosis(k, ["m"] if k >= switch else ["other"])
            elif kind == "a":
                answered += feed.activate()
        assert answered == list(range(switch + 1, 80)), seed


def test_feed_without_a_switch_seen_answers_from_now_and_keeps_nothing_once_off():
    feed: ModelFeed[int] = ModelFeed("m", keep=5)
    assert feed.features(0, 0) == [] and feed.activate() == []  # start-up: from now on
    assert feed.features(1, 1) == [1]
    feed.diagnosis(1, ["m"])
    feed.deactivate()  # an external change: nothing answered while off, from now on after
    assert [feed.features(k, k) for k in (2, 3)] == [[], []]
    assert feed.activate() == [] and feed.features(4, 4) == [4]
    feed.deactivate()
    feed.diagnosis(5, ["x"])
    for k in range(6, 20):  # off line, the switch at 12: only the last 5 kept
        feed.features(k, k)
    feed.diagnosis(12, ["m"])
    assert feed.activate() == [15, 16, 17, 18, 19]


class Settling:
    """A model with a state, as the turbofan's open-loop models: its residual starts at 0 at
    the first sample after a reset and settles to ``y - offset`` over ``settle`` samples, so
    a model started one step off gives other residuals."""

    def __init__(self, offset: float, settle: int, model_id: str) -> None:
        self.offset, self.settle, self.model_id, self.n = offset, settle, model_id, 0

    def reset(self) -> None:
        self.n = 0

    def residuals(self, fv: FeatureVector) -> ResidualVector:
        r = (fv.get("y") - self.offset) * min(1.0, self.n / self.settle)
        self.n += 1
        return ResidualVector(self.model_id, fv.index, fv.t_end, True, "", ("r",), ("1",),
                              np.array([r]), abs(r))


@register_residual_model("toy_settling")
def _settling(spec: dict, *, base_dir: Path, model_id: str) -> Settling:
    return Settling(float(spec["offset"]), int(spec["settle"]), model_id)


BANK = (("nominal", (), 0.0), ("a", ("a",), 1.0), ("b", ("b",), -1.0), ("ab", ("a", "b"), 0.8))


def _config(tmp_path: Path):
    text = toy_config(0.3, BANK).replace("type: toy_offset", "type: toy_settling, settle: 40")
    path = tmp_path / "toy.yaml"
    path.write_text(text)
    return load_graph_config(path)


def _features(n: int) -> list[FeatureVector]:
    """Fault free, then fault a (y = 1.05: the fresh model ab is smallest for a while)."""
    return [FeatureVector("toy", k, 0.015 * k, 0.015 * (k + 1), 0.0, True, "", ("y",), ("1",),
                          np.array([0.0 if k < 30 else 1.05])) for k in range(n)]


def _live(cfg, feats: list[FeatureVector], rng: random.Random) -> list[tuple]:
    """The graph as timed events: every message on its channel in order, each late by a
    random wall time; lifecycle calls answered late; the source up to 60 segments ahead."""
    core = SupervisorCore(cfg, lag_s=60.0)
    models = {e.id: Settling(float(e.model["offset"]), 40, e.id) for e in cfg.bank}
    feeds = {m: ModelFeed[FeatureVector](m) for m in models}
    queue: list = []
    last: dict[str, float] = {}
    seq = itertools.count()
    out: list[tuple] = []

    def send(channel: str, at: float, what: object) -> None:
        t = last[channel] = max(last.get(channel, 0.0), at + rng.expovariate(1 / 0.05))
        heapq.heappush(queue, (t, next(seq), channel, what))

    def answer(m: str, fvs: list[FeatureVector], at: float) -> None:
        for fv in fvs:
            send(f"residuals {m}", at, models[m].residuals(fv))

    def do(actions: list[object], now: float) -> None:
        for a in actions:
            if isinstance(a, (ChangeState, GetState)):
                send(f"lifecycle {a.model_id}", now, a)
            elif isinstance(a, Publish) and a.what == "diagnosis":
                d = a.value
                out.append((d.index, d.state, d.min_residual_model, d.fault_model,
                            d.models_online))
                for m in models:
                    send(f"diagnosis {m}", now, d)

    for m in core.diag.models_online:  # the bank on line before the data (start-up)
        core.driver.on_get_result(m, ACTIVE, 0.0)
        feeds[m].activate()
    for m in set(models) - set(core.diag.models_online):
        core.driver.on_get_result(m, INACTIVE, 0.0)
    state = {m: core.driver.nodes[m].observed for m in models}
    sent, now = 0, 0.0
    while (sent < len(feats) or queue) and now < 60.0:  # 60 s: a step that never comes
        diagnosed = out[-1][0] if out else -1
        if sent < len(feats) and sent <= diagnosed + 60 and rng.random() < 0.5:
            for channel in ("features", *(f"features {m}" for m in models)):
                send(channel, now, feats[sent])
            sent += 1
        elif queue and queue[0][0] > now and (sent == len(feats) or sent > diagnosed + 60):
            now = queue[0][0]  # nothing to do until the next message comes
        while queue and queue[0][0] <= now:
            _, _, channel, what = heapq.heappop(queue)
            kind, _, m = channel.partition(" ")
            if kind == "features" and not m:
                do(core.features(what, now), now)
            elif kind == "features":
                answer(m, feeds[m].features(what.index, what), now)
            elif kind == "diagnosis":
                answer(m, feeds[m].diagnosis(what.index, what.models_online), now)
            elif kind == "residuals":
                do(core.residual(what, now), now)
            elif kind == "lifecycle" and isinstance(what, ChangeState):  # the node's side
                state[m] = what.goal
                if what.goal == ACTIVE:
                    models[m].reset()
                    answer(m, feeds[m].activate(), now)
                else:
                    feeds[m].deactivate()
                send(f"answer {m}", now, (what, SimpleNamespace(success=True)))
            elif kind == "lifecycle":
                send(f"answer {m}", now, (what, SimpleNamespace(
                    current_state=SimpleNamespace(id=state[m]))))
            elif kind == "answer":
                do(core.driver.on_answer(what[0], what[1], now), now)
        do(core.tick(now, dict.fromkeys(models, True), None), now)
        now += 0.005
    return out


def test_live_with_a_bank_switch_equals_offline_in_any_order_and_pace(tmp_path):
    seed = int(time.time_ns() % 2**31)
    print(f"seed {seed}")
    rng = random.Random(seed)
    cfg = _config(tmp_path)
    feats = _features(120)
    offline = [(s.diagnosis.index, s.diagnosis.state, s.diagnosis.min_residual_model,
                s.diagnosis.fault_model, s.diagnosis.models_online)
               for _, _, s in diagnose_offline(cfg, feats, batch=False)]
    switch = next(i for i, (_, st, *_rest) in enumerate(offline) if st == "isolated")
    assert offline[switch][4] == ("a", "ab")  # the switch brings ab on line ...
    assert offline[switch + 1][2] == "ab"  # ... and, just started, it is smallest for a while
    for _ in range(10):
        assert _live(cfg, feats, rng) == offline, seed
