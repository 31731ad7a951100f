"""rosbag2 bags (MCAP storage) without ROS: write and read fdi_msgs and standard messages.

Bags are plain rosbag2 directories (``metadata.yaml`` + one ``.mcap`` file), readable by
``rosbags`` and by ``mcap``'s ROS 2 reader with nothing of ours but the ``.msg`` definitions,
which every connection carries in the file.

Writing takes either message objects of the rosbags typestore (offline tools) or serialized CDR
bytes straight from a ``raw=True`` rclpy subscription (the recorder: no re-encoding).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from fdi_ros import msgs
from fdi_ros.core.types import Diagnosis, FaultEvent, FeatureVector, ResidualVector, SampleBlock

BAG_VERSION = 8  # rosbag2 metadata version understood by Jazzy's rosbag2 and by rosbags


class BagError(ValueError):
    """A bag that cannot be read: missing, malformed, or not of the expected content."""


class BagWriter:
    """Write a rosbag2 MCAP bag.

    Parameters
    ----------
    path : the bag directory to create (must not exist).

    Use as a context manager; ``close()`` writes the MCAP footer and ``metadata.yaml``.
    Timestamps are nanoseconds of plant time unless given otherwise.
    """

    def __init__(self, path: str | Path) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"bag {self.path} already exists: choose another --out")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._store = msgs.typestore()
        self._factory = msgs.MessageFactory("rosbags")
        self._writer = Writer(self.path, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._conns: dict[tuple[str, str], Any] = {}
        self.count = 0

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def _conn(self, topic: str, msgtype: str) -> Any:
        key = (topic, msgtype)
        if key not in self._conns:
            self._conns[key] = self._writer.add_connection(topic, msgtype, typestore=self._store)
        return self._conns[key]

    def write_raw(self, topic: str, msgtype: str, data: bytes | memoryview, t_ns: int) -> None:
        """Write serialized CDR bytes (e.g. from an rclpy ``raw=True`` subscription)."""
        self._writer.write(self._conn(topic, msgtype), int(t_ns), data)
        self.count += 1

    def write(self, topic: str, msgtype: str, msg: Any, t_ns: int) -> None:
        """Write a rosbags typestore message object."""
        self.write_raw(topic, msgtype, self._store.serialize_cdr(msg, msgtype), t_ns)

    # core records ------------------------------------------------------------------------------
    def write_block(self, b: SampleBlock, topic: str = "/fdi/sensor_block") -> None:
        t = float(b.t[-1]) if b.t.size else 0.0
        self.write(topic, msgs.TOPICS["/fdi/sensor_block"], self._factory.sensor_block(b),
                   _ns(t))

    def write_features(self, f: FeatureVector, topic: str = "/fdi/features") -> None:
        self.write(topic, msgs.TOPICS["/fdi/features"], self._factory.features(f), _ns(f.t_end))

    def write_residuals(self, r: ResidualVector, topic: str = "/fdi/residuals") -> None:
        self.write(topic, msgs.TOPICS["/fdi/residuals"], self._factory.residuals(r), _ns(r.t))

    def write_diagnosis(self, d: Diagnosis, topic: str = "/fdi/diagnosis") -> None:
        self.write(topic, msgs.TOPICS["/fdi/diagnosis"], self._factory.diagnosis(d), _ns(d.t))

    def write_fault(self, e: FaultEvent, topic: str = "/fdi/fault_truth") -> None:
        self.write(topic, msgs.TOPICS["/fdi/fault_truth"], self._factory.fault_event(e),
                   _ns(e.t))


def write_snapshot(path: str | Path, records: Iterable[tuple[float, str, Any]]) -> str:
    """A bag of core records ``(t, kind, record)``, kind one of "features", "residuals",
    "diagnosis", "block", "fault" (the supervisor's ring buffer at a confirmation); returns
    what was done, for the log (a failure is reported there, never raised: the supervisor
    goes on)."""
    try:
        with BagWriter(path) as w:
            for _t, kind, rec in list(records):
                getattr(w, f"write_{kind}")(rec)
            return f"snapshot bag {path}: {w.count} messages"
    except (OSError, ValueError) as exc:
        return f"snapshot bag {path} not written: {exc}"


def _ns(t_s: float) -> int:
    return int(round(max(t_s, 0.0) * 1e9))


def _open_reader(path: str | Path) -> Any:
    from rosbags.rosbag2 import Reader

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"bag {p} does not exist")
    if not p.is_dir() or not (p / "metadata.yaml").is_file():
        raise BagError(f"{p} is not a rosbag2 directory (no metadata.yaml)")
    try:
        reader = Reader(p)
        reader.open()
    except Exception as exc:  # rosbags raises its own error classes for every kind of damage
        raise BagError(f"cannot open bag {p}: {exc}") from exc
    return reader


def topics(path: str | Path) -> dict[str, tuple[str, int]]:
    """Topic -> (message type, message count) of a bag."""
    reader = _open_reader(path)
    try:
        out: dict[str, tuple[str, int]] = {}
        for c in reader.connections:
            typ, n = out.get(c.topic, (c.msgtype, 0))
            out[c.topic] = (typ, n + c.msgcount)
        return out
    finally:
        reader.close()


def read(path: str | Path, topics: Iterable[str] | None = None,
         raw: bool = False) -> Iterator[tuple[str, str, int, Any]]:
    """Yield ``(topic, msgtype, t_ns, msg)`` in log-time order.

    ``msg`` is a rosbags message object, or the serialized bytes with ``raw=True``.
    A message that does not deserialize raises :class:`BagError` naming topic and time.
    """
    reader = _open_reader(path)
    store = msgs.typestore()
    try:
        wanted = set(topics) if topics is not None else None
        conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
        try:
            for conn, t_ns, data in reader.messages(connections=conns):
                if raw:
                    yield conn.topic, conn.msgtype, t_ns, data
                    continue
                try:
                    msg = store.deserialize_cdr(data, conn.msgtype)
                except Exception as exc:
                    raise BagError(f"{path}: message on {conn.topic} at {t_ns} ns does not "
                                   f"deserialize as {conn.msgtype}: {exc}") from exc
                yield conn.topic, conn.msgtype, t_ns, msg
        except BagError:
            raise
        except Exception as exc:
            raise BagError(f"{path}: damaged bag: {exc}") from exc
    finally:
        reader.close()


def read_blocks(path: str | Path, topic: str = "/fdi/sensor_block") -> list[SampleBlock]:
    return [msgs.to_sample_block(m) for _, _, _, m in read(path, [topic])]


def read_features(path: str | Path, topic: str = "/fdi/features") -> list[FeatureVector]:
    return [msgs.to_features(m) for _, _, _, m in read(path, [topic])]


def read_residuals(path: str | Path, topic: str = "/fdi/residuals") -> list[ResidualVector]:
    return [msgs.to_residuals(m) for _, _, _, m in read(path, [topic])]


def read_diagnoses(path: str | Path, topic: str = "/fdi/diagnosis") -> list[Diagnosis]:
    return [msgs.to_diagnosis(m) for _, _, _, m in read(path, [topic])]


def read_faults(path: str | Path, topic: str = "/fdi/fault_truth") -> list[FaultEvent]:
    return [msgs.to_fault_event(m) for _, _, _, m in read(path, [topic])]
