"""A model host sends its nodes' answers to a feature block as one ResidualBundle
(fdi_ros/nodes/bundle.py): the collector's rules on random orders of answers, and a live
two-host graph whose supervisor gets the bank's residuals in bundles and diagnoses every
segment."""

from __future__ import annotations

import random
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]


class _Pub:
    def __init__(self, readers: int, active: bool = True) -> None:
        self.readers, self.is_activated, self.sent = readers, active, []

    def get_subscription_count(self) -> int:
        return self.readers

    def publish(self, m) -> None:
        if self.is_activated:   # a lifecycle publisher drops what it gets while inactive
            self.sent.append(m)


class _IO:
    def __init__(self, readers: int = 1, active: bool = True) -> None:
        self.blocks_publisher = _Pub(readers, active)


class _Msg:
    def __init__(self, tag) -> None:
        self.tag, self.header = tag, None


def _bundler(readers: int):
    from fdi_ros.nodes.bundle import Bundler

    # the collector without a node: its publisher faked, a bundle is the list of its blocks
    return Bundler(_Pub(readers), lambda header, blocks: list(blocks))


def test_collector_sends_each_block_once_in_one_message_or_per_node():
    seed = random.randrange(2**32)
    print(f"seed {seed}")
    rng = random.Random(seed)
    for _ in range(200):
        n = rng.randint(1, 6)
        ios = [_IO(readers=1, active=rng.random() > 0.2) for _ in range(n)]
        b = _bundler(readers=rng.choice([0, 1, 1, 2]))
        for io in ios:
            b.join(io)
        lost = rng.random() < 0.2   # one node never answers block 0 (its message lost)
        for block in (0, 1):
            order = ios[:]
            rng.shuffle(order)
            for io in order:
                if lost and block == 0 and io is order[-1]:
                    continue
                b.answer(io, block, [_Msg((block, id(io)))] if rng.random() > 0.3 else [])
        b.flush()
        bundled = [m.tag for msg in b._pub.sent for m in msg]
        direct = [m.tag for io in ios for m in io.blocks_publisher.sent]
        # nothing twice; per node when the bundle has fewer readers than the node's topic
        assert len(bundled + direct) == len(set(bundled + direct))
        if b._pub.readers == 0:
            assert not bundled
        else:
            assert not direct
        # inactive nodes' answers never leave
        inactive = {id(io) for io in ios if not io.blocks_publisher.is_activated}
        assert not [t for t in bundled + direct if t[1] in inactive]
        # at most one message per block (a lost answer: block 0 leaves with block 1's turn)
        assert len(b._pub.sent) <= 2


def test_a_block_a_node_never_answers_leaves_after_a_while(monkeypatch):
    from fdi_ros.nodes import bundle

    clock = [100.0]
    monkeypatch.setattr(bundle.time, "monotonic", lambda: clock[0])
    b = _bundler(readers=1)
    one, two = _IO(), _IO()
    b.join(one)
    b.join(two)
    b.answer(one, 3, [_Msg("last")])   # the data's last block; two's copy was lost
    b._stale()
    assert not b._pub.sent
    clock[0] += 2 * bundle.STALE_S
    b._stale()
    assert [[m.tag for m in msg] for msg in b._pub.sent] == [["last"]]


def test_a_node_leaving_sends_what_it_holds():
    b = _bundler(readers=1)
    one, two = _IO(), _IO()
    b.join(one)
    b.join(two)
    b.answer(one, 7, [_Msg("a")])
    assert not b._pub.sent      # waiting for the second node
    b.leave(two)                # cleaned up: the block is complete without it
    assert [[m.tag for m in msg] for msg in b._pub.sent] == [["a"]]


class _Block:
    def __init__(self, index: int) -> None:
        self.block_index = index


class _Node(_IO):
    """A hosted node's ModelIO as the bundler sees it: it answers a FeatureBlock with one
    ResidualBlock tagged (block, node), in its callback or when the bundler runs it."""

    def __init__(self, bundler, name: str, log: list) -> None:
        super().__init__()
        self.bundler, self.name, self.log = bundler, name, log

    def callback(self, m: _Block) -> None:   # the subscription callback (ModelIO._on_block)
        if not self.bundler.defer(self, m):
            self.take_block(m)

    def take_block(self, m: _Block) -> None:
        self.log.append((self.name, m.block_index))
        self.bundler.answer(self, m.block_index, [_Msg((m.block_index, self.name))])


def test_the_urgent_node_answers_each_block_first_whatever_the_executor_order(monkeypatch):
    """The symptoms' model computes a block before the host's other nodes and its answer
    leaves on its own; every node answers every block once and in order, whatever order the
    executor runs the callbacks in; a block the urgent node never gets is answered by the
    others after STALE_S; a node leaving drops nothing of the others."""
    from fdi_ros.nodes import bundle

    clock = [0.0]
    monkeypatch.setattr(bundle.time, "monotonic", lambda: clock[0])
    seed = random.randrange(2**32)
    print(f"seed {seed}")
    rng = random.Random(seed)
    for _ in range(100):
        b, log = _bundler(readers=1), []
        nodes = [_Node(b, f"n{i}", log) for i in range(rng.randint(2, 6))]
        urgent = nodes[rng.randrange(len(nodes))]
        for n in nodes:
            b.join(n, urgent=n is urgent)
        lost = rng.randrange(1, 8)   # a block the urgent node's reader never gets
        queue = []                   # the executor's events: (node, block), per node in order
        for k in range(8):
            events = [(n, k) for n in nodes if not (n is urgent and k == lost)]
            rng.shuffle(events)
            queue += events
        # the executor may run a later block's events of one node before another's earlier
        # ones (separate readers), never one node's own out of order
        for _ in range(len(queue)):
            i = rng.randrange(len(queue) - 1)
            if queue[i][0] is not queue[i + 1][0] and rng.random() < 0.3:
                queue[i], queue[i + 1] = queue[i + 1], queue[i]
        for n, k in queue:
            clock[0] += 0.001
            n.callback(_Block(k))
        for _ in range(2):   # the stale timer's turns: deferred blocks run, then leave
            clock[0] += 2 * bundle.STALE_S
            b._stale()
        for n in nodes:   # each node answered its blocks once, in order
            want = [k for k in range(8) if not (n is urgent and k == lost)]
            assert [k for name, k in log if name == n.name] == want, seed
        sent = [[m.tag for m in msg] for msg in b._pub.sent]
        assert sorted(t for msg in sent for t in msg) == sorted(
            (k, n.name) for n in nodes for k in range(8) if not (n is urgent and k == lost))
        start = next(i for i, (name, _) in enumerate(log) if name == urgent.name)
        for k in range(8):
            if k == lost or any(e[1] == k for e in log[:start]):
                continue   # (before the urgent node's first answer: start-up, no waiting)
            # the urgent node's answer to block k leaves alone, before any other's answer
            first = next(i for i, msg in enumerate(sent) if any(t[0] == k for t in msg))
            assert sent[first] == [(k, urgent.name)], (seed, k, sent)
            assert log.index((urgent.name, k)) == min(
                i for i, e in enumerate(log) if e[1] == k), (seed, k)


def _short_scenario(tmp_path: Path) -> Path:
    sc = yaml.safe_load((ROOT / "config" / "scenarios" / "demo_diesel_leak.yaml").read_text())
    sc.pop("faults")
    sc["duration_s"] = 4.0
    path = tmp_path / "scenario.yaml"
    path.write_text(yaml.safe_dump(sc))
    return path


def _every_segment_diagnosed(w) -> None:
    indices = sorted(int(d.index) for _, d in w.seen.diagnoses)
    assert indices == list(range(indices[0], indices[0] + len(indices)))
    pipe = [st for _, arr in w.seen.diagnostics for st in arr.status
            if st.name == "fdi_supervisor: pipeline"]
    skipped = [int(v.value) for st in pipe for v in st.values if v.key == "skipped_segments"]
    assert skipped and max(skipped) == 0


@pytest.mark.graph
def test_two_hosts_send_bundles_and_every_segment_is_diagnosed(diesel_bank, tmp_path):
    from fdi_msgs.msg import ResidualBundle

    from fdi_ros.livegraph import run_live

    path = _short_scenario(tmp_path)
    got: list = []

    def during(graph, w, run) -> None:
        if not got:
            got.append(w.node.create_subscription(
                ResidualBundle, "/fdi/residual_bundles",
                lambda m: got.append(sorted({b.model_id for b in m.blocks})), 500))

    run, w = run_live(ROOT / "config" / "diesel.yaml", scenario=path, during=during,
                      timeout_s=120, hosting={"mode": "container", "containers": 2})
    assert run.ended
    bundles = got[1:]
    assert bundles and max(len(ids) for ids in bundles) >= 3, bundles[:5]
    _every_segment_diagnosed(w)


@pytest.mark.graph
def test_a_reader_of_the_blocks_of_your_own_gets_every_models_blocks(diesel_bank, tmp_path):
    """A node of yours reading /fdi/residual_blocks (not the bundles): the hosts send per
    node, so it gets every model's blocks, and the supervisor still diagnoses every segment."""
    from fdi_msgs.msg import ResidualBlock

    from fdi_ros.core.graphconfig import load_graph_config
    from fdi_ros.livegraph import run_live

    config = ROOT / "config" / "diesel.yaml"
    got: list = []

    def during(graph, w, run) -> None:
        if not got:
            got.append(w.node.create_subscription(
                ResidualBlock, "/fdi/residual_blocks", lambda m: got.append(m.model_id), 500))

    run, w = run_live(config, scenario=_short_scenario(tmp_path), during=during,
                      timeout_s=120, hosting={"mode": "container", "containers": 2})
    assert run.ended
    assert set(got[1:]) == {e.id for e in load_graph_config(config).bank}
    _every_segment_diagnosed(w)
