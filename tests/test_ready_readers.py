"""The start-up hold of the preprocessor's first vectors (fdi_ros.core.handshake): the readers
the supervisor saw when it said ready travel on /fdi/ready and come back unchanged, and a
writer holds until its own graph shows each of them and its own DDS matches cover its graph.
A clean-clone run skipped the first segment of a 4x replay once: five model nodes the
supervisor had seen reading the feature blocks were not yet discovered by the preprocessor,
whose first block went to the two it had matched."""

from __future__ import annotations

import random
from dataclasses import dataclass

from fdi_ros.core.handshake import parse_readers, unmatched_readers
from fdi_ros.nodes.startup import ready_messages


@dataclass
class Header:
    frame_id: str = ""


def _names(rng: random.Random, n: int) -> set[str]:
    return {f"fdi_model_{rng.choice('abcdefgh')}{rng.randrange(1000)}" for _ in range(n)}


def test_readers_round_trip_and_ready_comes_last():
    rng = random.Random(random.randrange(2**32))
    for _ in range(200):
        subs = {t: _names(rng, rng.randrange(0, 20))
                for t in rng.sample(["/fdi/features", "/fdi/feature_blocks", "/x/y"],
                                    rng.randrange(0, 4))}
        msgs = ready_messages(subs, Header)
        assert [m.frame_id for m in msgs][-1] == "ready"
        assert parse_readers(msgs[0].frame_id) == subs
        assert parse_readers("ready") is None  # the ready signal itself names nobody


def test_a_writer_holds_until_its_graph_and_matches_cover_the_readers():
    seed = random.randrange(2**32)
    rng = random.Random(seed)
    for _ in range(500):
        topics = ["/fdi/features", "/fdi/feature_blocks"]
        needed = {t: _names(rng, rng.randrange(0, 8)) for t in topics}
        graph = {t: sorted(n for n in needed[t] if rng.random() < 0.8)
                 + sorted(_names(rng, rng.randrange(0, 3))) for t in topics}
        matched = {t: rng.randrange(0, len(graph[t]) + 2) for t in topics}
        out = unmatched_readers(needed, graph, matched)
        ok = all(needed[t] <= set(graph[t]) and matched[t] >= len(graph[t]) for t in topics)
        assert (not out) == ok, (seed, needed, graph, matched, out)
        # without the supervisor's list, the writer's own graph decides alone
        own = all(matched[t] >= len(graph[t]) for t in topics)
        assert (not unmatched_readers(None, graph, matched)) == own, seed
    # the case of the failed run: two readers matched, five the supervisor saw not discovered
    needed = {"/fdi/feature_blocks": {f"fdi_model_{i}" for i in range(7)}}
    out = unmatched_readers(needed, {"/fdi/feature_blocks": ["fdi_model_0", "fdi_model_1"]},
                            {"/fdi/feature_blocks": 2})
    assert out and "fdi_model_6" in out[0] and "not discovered" in out[0]
