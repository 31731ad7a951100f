"""Who must read a writer's first messages (the start-up handshake, pure).

When the graph is ready the supervisor names every reader of the features its graph shows
(:func:`readers_text`, sent on ``/fdi/ready`` before the ready signal itself). The writer of
the features (the preprocessor) holds its first messages until *its own* DDS matches cover
those readers and every reader its own graph shows (:func:`unmatched_readers`): discovery
reaches each process at its own pace, and a reader the supervisor saw but the writer had not
yet matched would miss the first segments (a 4x replay once skipped its first segment so:
five of seven model nodes were not yet discovered by the preprocessor).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

READERS_PREFIX = "readers "


def readers_text(subs: Mapping[str, Iterable[str]]) -> str:
    """``"readers /topic=node,node;/topic=..."``: the readers of each topic."""
    return READERS_PREFIX + ";".join(f"{t}={','.join(sorted(set(n)))}"
                                     for t, n in sorted(subs.items()))


def parse_readers(text: str) -> dict[str, set[str]] | None:
    """The readers of :func:`readers_text` (None: not such a text)."""
    if not text.startswith(READERS_PREFIX):
        return None
    out: dict[str, set[str]] = {}
    for part in filter(None, text[len(READERS_PREFIX):].split(";")):
        topic, _, names = part.partition("=")
        out[topic] = set(filter(None, names.split(",")))
    return out


def unmatched_readers(needed: Mapping[str, set[str]] | None,
                      graph: Mapping[str, Iterable[str]],
                      matched: Mapping[str, int]) -> list[str]:
    """What a writer still lacks before its first messages may go (empty: nothing), per topic
    it writes: every reader its graph shows (``graph``: node names) matched by its own
    publisher (``matched``: its DDS match count), and every node of ``needed`` (the readers
    the supervisor saw; None: not known) among them."""
    out = []
    for topic, names in graph.items():
        seen = list(names)
        missing = sorted((needed or {}).get(topic, set()) - set(seen))
        if missing:
            out.append(f"{topic}: {', '.join(missing)} not discovered yet")
        elif matched.get(topic, 0) < len(seen):
            out.append(f"{topic}: {matched.get(topic, 0)}/{len(seen)} readers matched")
    return out
