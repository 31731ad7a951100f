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
from typing import TYPE_CHECKING, Any, Final

from fdi_ros import msgs
from fdi_ros.core.types import Diagnosis, FaultEvent, FeatureVector, ResidualVector, SampleBlock

if TYPE_CHECKING:
    from rosbags.rosbag2 import Writer

BAG_VERSION: Final = 9  # the rosbag2 metadata version Jazzy writes (QoS profiles as a YAML list)
ROS_DISTRO = "jazzy"
# deadline / lifespan / lease "unset" as rosbag2 writes them (RMW_DURATION_INFINITE)
_INFINITE = (9223372036, 854775807)


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
        self._writer: Writer | None = Writer(self.path, version=BAG_VERSION,
                                             storage_plugin=StoragePlugin.MCAP)
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
            _set_distro(self.path / "metadata.yaml")

    def _open(self) -> Writer:
        if self._writer is None:
            raise ValueError(f"bag {self.path} is closed")
        return self._writer

    def _conn(self, topic: str, msgtype: str, qos: list[dict] | None = None) -> Any:
        key = (topic, msgtype)
        if key not in self._conns:
            try:
                profiles = [qos_profile(**q) for q in (qos or [default_qos(topic)])]
            except (KeyError, TypeError, ValueError):  # a policy rosbags has no name for
                profiles = [qos_profile(**default_qos(topic))]
            self._conns[key] = self._open().add_connection(
                topic, msgtype, typestore=self._store, offered_qos_profiles=profiles)
        return self._conns[key]

    def write_raw(self, topic: str, msgtype: str, data: bytes | memoryview, t_ns: int,
                  qos: list[dict] | None = None) -> None:
        """Write serialized CDR bytes (e.g. from an rclpy ``raw=True`` subscription).

        ``qos``: the publishers' offered profiles (dicts of :func:`qos_profile` arguments),
        used when the topic is first written; default: the profile this package uses."""
        conn = self._conn(topic, msgtype, qos)
        self._open().write(conn, int(t_ns), data)
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


def default_qos(topic: str) -> dict:
    """The profile this package's nodes offer on ``topic`` (see ``nodes.common``)."""
    if topic.startswith("/fdi/fault_"):
        return {"depth": 50, "durability": "transient_local"}
    if topic == "/clock":
        return {"depth": 10}
    if topic == "/diagnostics":
        return {"depth": 10}
    return {"depth": 500}


def qos_profile(depth: int = 10, history: str = "keep_last", reliability: str = "reliable",
                durability: str = "volatile", liveliness: str = "automatic") -> Any:
    """A rosbags QoS profile from policy names (lower case, as in rosbag2's metadata)."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    inf = QosTime(*_INFINITE)
    return Qos(QosHistory[history.upper()], int(depth), QosReliability[reliability.upper()],
               QosDurability[durability.upper()], inf, inf,
               QosLiveliness[liveliness.upper()], inf, False)


def _set_distro(meta: Path) -> None:
    """rosbags writes ``ros_distro: rosbags``; the bags are for (and as) Jazzy's rosbag2."""
    import yaml

    if not meta.is_file():
        return
    doc = yaml.safe_load(meta.read_text())
    doc["rosbag2_bagfile_information"]["ros_distro"] = ROS_DISTRO
    meta.write_text(yaml.safe_dump(doc, sort_keys=False))


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
    fast = _fast_topics(path)
    if fast is not None:
        return fast
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
    """The sample blocks of a bag. Little-endian CDR is decoded straight into arrays (no
    message objects); anything else, or a damaged bag, goes the general way (and its errors)."""
    fast = _fast(path, topic, msgs.TOPICS["/fdi/sensor_block"], _sensor_block_cdr)
    if fast is not None:
        return fast
    return [msgs.to_sample_block(m) for _, _, _, m in read(path, [topic])]


def _mcap_file(path: str | Path) -> Path | None:
    p = Path(path)
    files = sorted(p.glob("*.mcap")) if p.is_dir() and (p / "metadata.yaml").is_file() else []
    return files[0] if len(files) == 1 else None


def _fast(path: str | Path, topic: str, msgtype: str, decode: Any) -> list | None:
    """Messages of one topic read with mcap and decoded by ``decode`` (CDR bytes -> record);
    None when that does not apply (the general reader then decides and names any damage)."""
    from mcap.reader import make_reader

    f = _mcap_file(path)
    if f is None:
        return None
    try:
        with f.open("rb") as fh:
            found = [(m.log_time, m.data) for sc, _ch, m in
                     make_reader(fh).iter_messages(topics=[topic], log_time_order=False)
                     if sc is not None and sc.name == msgtype]
        found.sort(key=lambda x: x[0])   # log-time order, as the general reader gives
        return [decode(_Cdr(data)) for _, data in found]
    except Exception:
        return None


def _fast_topics(path: str | Path) -> dict[str, tuple[str, int]] | None:
    """Topic -> (type, count) from the MCAP summary; None without one (a cut-short file)."""
    from mcap.reader import make_reader

    f = _mcap_file(path)
    if f is None:
        return None
    try:
        with f.open("rb") as fh:
            summary = make_reader(fh).get_summary()
        if summary is None or summary.statistics is None:
            return None
        counts = summary.statistics.channel_message_counts
        out: dict[str, tuple[str, int]] = {}
        for c in summary.channels.values():
            typ, n = out.get(c.topic, (summary.schemas[c.schema_id].name, 0))
            out[c.topic] = (typ, n + counts.get(c.id, 0))
        return out
    except Exception:
        return None


class _Cdr:
    """A cursor over little-endian CDR (XCDR1, alignment counted from byte 4)."""

    def __init__(self, data: bytes) -> None:
        if data[:2] != b"\x00\x01":
            raise ValueError("not little-endian CDR")
        self.data, self.off = data, 4

    def _at(self, n: int) -> int:
        self.off += (-(self.off - 4)) % n
        o = self.off
        if o + n > len(self.data):
            raise ValueError("CDR message ends early")
        self.off += n
        return o

    def scalar(self, fmt: str) -> Any:
        import struct

        return struct.unpack_from("<" + fmt, self.data, self._at(struct.calcsize(fmt)))[0]

    def string(self) -> str:
        n = self.scalar("I")
        o = self.off
        if n < 1 or o + n > len(self.data) or self.data[o + n - 1] != 0:
            raise ValueError("malformed CDR string")
        self.off += n
        return bytes(self.data[o:o + n - 1]).decode()

    def strings(self) -> tuple[str, ...]:
        return tuple(self.string() for _ in range(self.scalar("I")))

    def f64s(self) -> Any:
        import numpy as np

        n = self.scalar("I")
        if n == 0:
            return np.zeros(0)
        o = self._at(8)
        if o + 8 * n > len(self.data):
            raise ValueError("CDR array past the end")
        self.off = o + 8 * n
        return np.frombuffer(self.data, "<f8", n, o)

    def header(self) -> None:
        self.scalar("i"), self.scalar("I"), self.string()

    def done(self) -> None:
        if len(self.data) - self.off > 7:
            raise ValueError("CDR message longer than its type")


_NAMES_SEEN: dict[str, tuple[bytes, tuple[tuple[str, ...], tuple[str, ...]]]] = {}


def _sensor_block_cdr(c: _Cdr) -> SampleBlock:
    c.header()
    plant, index = c.string(), int(c.scalar("Q"))
    t, alpha = c.f64s(), c.f64s()
    # channel and unit names repeat from block to block: decoded once per stream
    o, last = c.off, _NAMES_SEEN.get("block")
    if last is not None and c.data[o:o + len(last[0])] == last[0]:
        channels, units = last[1]
        c.off += len(last[0])
    else:
        channels, units = c.strings(), c.strings()
        _NAMES_SEEN["block"] = (bytes(c.data[o:c.off]), (channels, units))
    values = c.f64s()
    c.done()
    if values.size != len(channels) * t.size:
        raise ValueError("SensorBlock does not add up")
    return SampleBlock(plant=plant, index=index, t=t, alpha=alpha, channels=channels,
                       units=units, values=values.reshape(len(channels), t.size))


def _fault_event_cdr(c: _Cdr) -> FaultEvent:
    c.header()
    t, fault, size, unit, profile = c.scalar("d"), c.string(), c.scalar("d"), c.string(), \
        c.string()
    ramp, active = c.scalar("d"), bool(c.scalar("B"))
    c.done()
    return FaultEvent(t=t, fault=fault, size=size, size_unit=unit, profile=profile or "step",
                      ramp_s=ramp, active=active)


def read_features(path: str | Path, topic: str = "/fdi/features") -> list[FeatureVector]:
    return [msgs.to_features(m) for _, _, _, m in read(path, [topic])]


def read_residuals(path: str | Path, topic: str = "/fdi/residuals") -> list[ResidualVector]:
    return [msgs.to_residuals(m) for _, _, _, m in read(path, [topic])]


def read_diagnoses(path: str | Path, topic: str = "/fdi/diagnosis") -> list[Diagnosis]:
    return [msgs.to_diagnosis(m) for _, _, _, m in read(path, [topic])]


def read_faults(path: str | Path, topic: str = "/fdi/fault_truth") -> list[FaultEvent]:
    fast = _fast(path, topic, msgs.TOPICS["/fdi/fault_truth"], _fault_event_cdr)
    if fast is not None:
        return fast
    return [msgs.to_fault_event(m) for _, _, _, m in read(path, [topic])]


def _qos_from_channel(text: str) -> list[dict] | None:
    """Channel metadata ``offered_qos_profiles`` (YAML, rosbag2 v8 numbers or v9 names) ->
    :func:`qos_profile` arguments; None when absent or unreadable."""
    import yaml

    try:
        items = yaml.safe_load(text) if text else None
    except yaml.YAMLError:
        return None
    if not isinstance(items, list) or not items:
        return None
    names = {"history": ("system_default", "keep_last", "keep_all"),
             "reliability": ("system_default", "reliable", "best_effort"),
             "durability": ("system_default", "transient_local", "volatile"),
             "liveliness": ("system_default", "automatic", "manual_by_node", "manual_by_topic")}
    out = []
    for it in items:
        if not isinstance(it, dict):
            return None
        q: dict[str, Any] = {"depth": int(it.get("depth", 10))}
        for key, table in names.items():
            v = it.get(key)
            if isinstance(v, int) and 0 <= v < len(table):
                v = table[v]
            if isinstance(v, str) and v.lower() in table:
                q[key] = v.lower()
        out.append(q)
    return out


def recover(path: str | Path) -> dict:
    """Rebuild a bag that lost its ``metadata.yaml`` or the end of its MCAP file (a recorder
    killed mid-run), as ``ros2 bag reindex`` does.

    Every record the MCAP stream still holds is read in file order (past a missing summary and
    footer, up to the first damaged byte) and written into a complete MCAP file with fresh
    metadata. The original file is kept beside it as ``<name>.mcap.orig``; nothing is deleted.
    Returns ``{"messages": n, "topics": {topic: n}, "truncated": bool, "error": str}``.
    """
    import shutil
    import tempfile

    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader

    p = Path(path)
    if not p.is_dir():
        raise BagError(f"{p} is not a bag directory")
    files = sorted(f for f in p.glob("*.mcap"))
    if len(files) != 1:
        raise BagError(f"{p}: expected one .mcap file, found {len(files)}")
    src = files[0]
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str, list[dict] | None]] = {}
    kept: list[tuple[str, str, int, bytes, list[dict] | None]] = []
    error, truncated = "", False
    with src.open("rb") as fh:
        try:
            for rec in StreamReader(fh).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec.name
                elif isinstance(rec, Channel):
                    typ = schemas.get(rec.schema_id)
                    if typ is not None:
                        channels[rec.id] = (rec.topic, typ, _qos_from_channel(
                            rec.metadata.get("offered_qos_profiles", "")))
                elif isinstance(rec, Message) and rec.channel_id in channels:
                    topic, typ, qos = channels[rec.channel_id]
                    kept.append((topic, typ, rec.log_time, bytes(rec.data), qos))
        except Exception as exc:  # the file ends (or is damaged) here: keep what came before
            truncated, error = True, f"{type(exc).__name__}: {exc}"
    kept.sort(key=lambda m: m[2])
    tmp = Path(tempfile.mkdtemp(prefix="fdi_recover_", dir=p.parent))
    try:
        with BagWriter(tmp / p.name) as w:
            for topic, typ, t_ns, data, qos in kept:
                w.write_raw(topic, typ, data, t_ns, qos)
        new = tmp / p.name
        backup = src.with_name(src.name + ".orig")
        if backup.exists():
            raise BagError(f"{backup} exists: a recovery was already made; remove it first")
        src.rename(backup)
        made = next(new.glob("*.mcap"))
        shutil.move(str(made), str(src))
        meta = (new / "metadata.yaml").read_text().replace(made.name, src.name)
        (p / "metadata.yaml").write_text(meta)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    counts: dict[str, int] = {}
    for topic, *_ in kept:
        counts[topic] = counts.get(topic, 0) + 1
    return {"messages": len(kept), "topics": counts, "truncated": truncated, "error": error}
