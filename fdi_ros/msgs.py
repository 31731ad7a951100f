"""The fdi_msgs message definitions, for bags without ROS and for live topics.

One source of truth: the ``.msg`` files of ``msg_defs/fdi_msgs/msg`` are (a) built by rosidl for
rclpy and (b) registered here into a rosbags typestore, so a bag written live (serialized CDR
from rclpy) and a bag written offline (rosbags) are the same bytes.

This module also converts between the core's records (:mod:`fdi_ros.core.types`) and message
objects. The conversion works on *any* object with the message's attribute names, so the same
functions serve rosbags' dataclasses and rclpy's generated classes: pass the class to build.
"""

from __future__ import annotations

import array
import math
import os
import sys
from collections import OrderedDict
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal

import numpy as np

from fdi_ros.core.types import Diagnosis, FaultEvent, FeatureVector, ResidualVector, SampleBlock

PACKAGE = "fdi_msgs"
MESSAGES = ("SensorBlock", "Features", "Residuals", "FeatureBlock", "ResidualBlock",
            "ResidualBundle", "Symptoms", "Diagnosis", "FaultEvent", "FaultRecord")

# Topic -> message type of the graph. One table, used by nodes, recorder, replayer and bag tools.
TOPICS: dict[str, str] = {
    "/fdi/sensor_block": f"{PACKAGE}/msg/SensorBlock",
    "/fdi/features": f"{PACKAGE}/msg/Features",
    "/fdi/residuals": f"{PACKAGE}/msg/Residuals",
    # the batched path of the live graph: the vectors of one sensor block per message
    "/fdi/feature_blocks": f"{PACKAGE}/msg/FeatureBlock",
    "/fdi/residual_blocks": f"{PACKAGE}/msg/ResidualBlock",
    # a model host's ResidualBlocks of one feature block together (nodes/bundle.py)
    "/fdi/residual_bundles": f"{PACKAGE}/msg/ResidualBundle",
    "/fdi/symptoms": f"{PACKAGE}/msg/Symptoms",
    "/fdi/diagnosis": f"{PACKAGE}/msg/Diagnosis",
    "/fdi/fault_inject": f"{PACKAGE}/msg/FaultEvent",
    "/fdi/fault_truth": f"{PACKAGE}/msg/FaultEvent",
}
# the same vectors as /fdi/features and /fdi/residuals, a sensor block per message (transport
# between the graph's nodes): not recorded unless asked for
BATCHED_TOPICS = ("/fdi/feature_blocks", "/fdi/residual_blocks", "/fdi/residual_bundles")


def msg_dir() -> Path:
    """Directory holding the ``.msg`` files: the checkout's msg_defs, else an installed prefix."""
    here = Path(__file__).resolve().parents[1] / "msg_defs" / PACKAGE / "msg"
    if here.is_dir():
        return here
    prefixes = os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) + [sys.prefix]
    for prefix in prefixes:
        cand = Path(prefix) / "share" / PACKAGE / "msg"
        if prefix and cand.is_dir():
            return cand
    raise FileNotFoundError(
        f"cannot find the {PACKAGE} .msg files (looked in msg_defs/ and share/{PACKAGE}/msg "
        "under AMENT_PREFIX_PATH and the Python prefix)")


def msg_definitions() -> dict[str, str]:
    """Message type name -> ``.msg`` text, for every fdi_msgs message."""
    d = msg_dir()
    return {f"{PACKAGE}/msg/{name}": (d / f"{name}.msg").read_text() for name in MESSAGES}


@lru_cache(maxsize=1)
def typestore():
    """A rosbags typestore for ROS 2 Jazzy with the fdi_msgs messages registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict = {}
    for name, text in msg_definitions().items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


# -- time ---------------------------------------------------------------------------------------

def stamp_fields(t_s: float) -> tuple[int, int]:
    """Seconds -> (sec, nanosec) of a builtin_interfaces/Time (non-negative times only)."""
    if not math.isfinite(t_s) or t_s < 0:
        raise ValueError(f"a message stamp needs a finite time >= 0 s, got {t_s}")
    ns = int(round(t_s * 1e9))
    return ns // 1_000_000_000, ns % 1_000_000_000


def stamp_seconds(header: Any) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


# -- array helpers that suit both rclpy (array.array) and rosbags (numpy) ---------------------

def _f64(values: Any, rclpy_style: bool) -> Any:
    arr = np.ascontiguousarray(values, dtype=np.float64).ravel()
    return array.array("d", arr.tobytes()) if rclpy_style else arr


def _i8(values: Any, rclpy_style: bool) -> Any:
    arr = np.ascontiguousarray(values, dtype=np.int8).ravel()
    return array.array("b", arr.tobytes()) if rclpy_style else arr


def _u64(values: Any, rclpy_style: bool) -> Any:
    arr = np.asarray(values, dtype=np.uint64)
    return array.array("Q", arr.tobytes()) if rclpy_style else arr


def _bool(values: Any, rclpy_style: bool) -> Any:
    return [bool(v) for v in values] if rclpy_style else np.asarray(values, dtype=bool)


def _runs(items: list[Any], key: Callable[[Any], Any]) -> list[list[Any]]:
    """``items`` cut into runs of consecutive items with equal ``key``."""
    out: list[list[Any]] = []
    last: Any = object()
    for it in items:
        k = key(it)
        if not out or k != last:
            out.append([])
            last = k
        out[-1].append(it)
    return out


def _np(values: Any, dtype: type = np.float64) -> np.ndarray:
    if isinstance(values, np.ndarray):
        return values.astype(dtype, copy=False)
    return np.asarray(values, dtype=dtype)


class MessageFactory:
    """Builds message objects of one flavour: rosbags typestore classes or rclpy classes.

    Parameters
    ----------
    flavour : "rosbags" (offline bags) or "rclpy" (live topics; needs the built fdi_msgs).
    """

    def __init__(self, flavour: str = "rosbags") -> None:
        if flavour not in ("rosbags", "rclpy"):
            raise ValueError(f"flavour must be 'rosbags' or 'rclpy', not {flavour!r}")
        self.flavour = flavour
        self.rclpy_style = flavour == "rclpy"
        if self.rclpy_style:
            import importlib

            from builtin_interfaces.msg import Time
            from std_msgs.msg import Header

            mod = importlib.import_module(f"{PACKAGE}.msg")
            self._cls: Callable[[str], Any] = lambda name: getattr(mod, name)
            self._header, self._time = Header, Time
        else:
            store = typestore()
            self._cls = lambda name: store.types[f"{PACKAGE}/msg/{name}"]
            self._header = store.types["std_msgs/msg/Header"]
            self._time = store.types["builtin_interfaces/msg/Time"]

    def cls(self, name: str) -> Any:
        return self._cls(name)

    def header(self, t_s: float, frame_id: str = "") -> Any:
        sec, nsec = stamp_fields(max(t_s, 0.0))
        return self._header(stamp=self._time(sec=sec, nanosec=nsec), frame_id=frame_id)

    # core record -> message ------------------------------------------------------------------
    def sensor_block(self, b: SampleBlock) -> Any:
        t0 = float(b.t[0]) if b.t.size else 0.0
        return self.cls("SensorBlock")(
            header=self.header(t0), plant=b.plant, block_index=int(b.index),
            stamp_s=_f64(b.t, self.rclpy_style), crank_angle_deg=_f64(b.alpha, self.rclpy_style),
            channels=list(b.channels), units=list(b.units),
            values=_f64(b.values, self.rclpy_style))

    def features(self, f: FeatureVector) -> Any:
        return self.cls("Features")(
            header=self.header(f.t_end), plant=f.plant, index=int(f.index),
            t_start_s=float(f.t_start), t_end_s=float(f.t_end),
            crank_angle_start_deg=float(f.alpha_start), valid=bool(f.valid), status=f.status,
            names=list(f.names), units=list(f.units), values=_f64(f.values, self.rclpy_style))

    def residuals(self, r: ResidualVector) -> Any:
        return self.cls("Residuals")(
            header=self.header(r.t), model_id=r.model_id, index=int(r.index), t_s=float(r.t),
            valid=bool(r.valid), status=r.status, names=list(r.names), units=list(r.units),
            values=_f64(r.values, self.rclpy_style), norm=float(r.norm), regime=r.regime)

    def feature_blocks(self, fs: list[FeatureVector], block_index: int) -> list[Any]:
        """FeatureBlock messages of the vectors one sensor block completed: one per run of
        consecutive vectors with the same plant, names and units (normally one)."""
        s = self.rclpy_style
        return [self.cls("FeatureBlock")(
            header=self.header(g[-1].t_end), plant=g[0].plant, block_index=int(block_index),
            index=_u64([f.index for f in g], s), t_start_s=_f64([f.t_start for f in g], s),
            t_end_s=_f64([f.t_end for f in g], s),
            crank_angle_start_deg=_f64([f.alpha_start for f in g], s),
            valid=_bool([f.valid for f in g], s), status=[f.status for f in g],
            names=list(g[0].names), units=list(g[0].units),
            values=_f64(np.concatenate([np.asarray(f.values, dtype=float) for f in g]), s))
            for g in _runs(fs, lambda f: (f.plant, f.names, f.units))]

    def residual_blocks(self, rs: list[ResidualVector]) -> list[Any]:
        """ResidualBlock messages of one model's residual vectors: one per run of
        consecutive vectors with the same model, names and units (normally one)."""
        s = self.rclpy_style
        return [self.cls("ResidualBlock")(
            header=self.header(g[-1].t), model_id=g[0].model_id,
            index=_u64([r.index for r in g], s), t_s=_f64([r.t for r in g], s),
            valid=_bool([r.valid for r in g], s), status=[r.status for r in g],
            names=list(g[0].names), units=list(g[0].units),
            values=_f64(np.concatenate([np.asarray(r.values, dtype=float) for r in g]), s),
            norm=_f64([r.norm for r in g], s), regime=[r.regime for r in g])
            for g in _runs(rs, lambda r: (r.model_id, r.names, r.units))]

    def symptoms(self, *, index: int, t: float, valid: bool, status: str, names: Any,
                 levels: Any, residuals: Any, threshold_low: Any, threshold_high: Any,
                 threshold_intense: Any, regime: str = "") -> Any:
        s = self.rclpy_style
        return self.cls("Symptoms")(
            header=self.header(t), index=int(index), t_s=float(t), valid=bool(valid),
            status=status, names=list(names), levels=_i8(levels, s),
            residuals=_f64(residuals, s), threshold_low=_f64(threshold_low, s),
            threshold_high=_f64(threshold_high, s), threshold_intense=_f64(threshold_intense, s),
            regime=regime)

    def symptom_state(self, index: int, t: float, s: Any) -> Any:
        """Symptoms message from a symptom stage's state record."""
        return self.symptoms(index=index, t=t, **{f: getattr(s, f) for f in (
            "valid", "status", "names", "levels", "residuals", "threshold_low",
            "threshold_high", "threshold_intense", "regime")})

    def diagnosis(self, d: Diagnosis) -> Any:
        return self.cls("Diagnosis")(
            header=self.header(d.t), index=int(d.index), t_s=float(d.t), state=d.state,
            min_residual_index=int(d.min_residual_index), min_residual_model=d.min_residual_model,
            fault_index=int(d.fault_index), fault_model=d.fault_model,
            candidate_faults=list(d.candidate_faults), isolated_faults=list(d.isolated_faults),
            models_online=list(d.models_online), detection_time_s=float(d.detection_time),
            isolation_time_s=float(d.isolation_time))

    def fault_event(self, e: FaultEvent) -> Any:
        return self.cls("FaultEvent")(
            header=self.header(e.t), t_s=float(e.t), fault=e.fault, size=float(e.size),
            size_unit=e.size_unit, profile=e.profile, ramp_s=float(e.ramp_s),
            active=bool(e.active))


# message (either flavour) -> core record -------------------------------------------------------

def to_sample_block(m: Any) -> SampleBlock:
    t = _np(m.stamp_s)
    channels = tuple(m.channels)
    values = _np(m.values)
    n = t.shape[0]
    if values.size != len(channels) * n:
        raise ValueError(f"SensorBlock {m.block_index}: {values.size} values for "
                         f"{len(channels)} channels x {n} samples")
    return SampleBlock(plant=m.plant, index=int(m.block_index), t=t, alpha=_np(m.crank_angle_deg),
                       channels=channels, units=tuple(m.units),
                       values=values.reshape(len(channels), n))


def to_features(m: Any) -> FeatureVector:
    return FeatureVector(plant=m.plant, index=int(m.index), t_start=float(m.t_start_s),
                         t_end=float(m.t_end_s), alpha_start=float(m.crank_angle_start_deg),
                         valid=bool(m.valid), status=m.status, names=tuple(m.names),
                         units=tuple(m.units), values=_np(m.values))


def to_residuals(m: Any) -> ResidualVector:
    return ResidualVector(model_id=m.model_id, index=int(m.index), t=float(m.t_s),
                          valid=bool(m.valid), status=m.status, names=tuple(m.names),
                          units=tuple(m.units), values=_np(m.values), norm=float(m.norm),
                          regime=m.regime)


def _block_columns(m: Any, kind: str, per_vector: tuple[str, ...]) -> tuple[int, np.ndarray]:
    """Number of vectors of a block message and its values as (vectors, names); ValueError
    when the per-vector fields or the values do not match."""
    n = len(m.index)
    bad = [f for f in per_vector if len(getattr(m, f)) != n]
    if bad:
        got = ", ".join(f"{len(getattr(m, f))} {f}" for f in bad)
        raise ValueError(f"{kind}: {n} vectors but {got}")
    k = len(m.names)
    if len(m.units) != k:
        raise ValueError(f"{kind}: {k} names but {len(m.units)} units")
    values = _np(m.values)
    if values.size != n * k:
        raise ValueError(f"{kind}: {values.size} values for {n} vectors x {k} names")
    return n, values.reshape(n, k)


def to_feature_list(m: Any) -> list[FeatureVector]:
    """The feature vectors of a FeatureBlock message (ValueError if malformed)."""
    n, v = _block_columns(m, f"FeatureBlock {m.block_index}", (
        "t_start_s", "t_end_s", "crank_angle_start_deg", "valid", "status"))
    names, units = tuple(m.names), tuple(m.units)
    idx, t0, t1, a0 = (_np(m.index, np.uint64), _np(m.t_start_s), _np(m.t_end_s),
                       _np(m.crank_angle_start_deg))
    return [FeatureVector(plant=m.plant, index=int(idx[i]), t_start=float(t0[i]),
                          t_end=float(t1[i]), alpha_start=float(a0[i]), valid=bool(m.valid[i]),
                          status=m.status[i], names=names, units=units, values=v[i].copy())
            for i in range(n)]


# FeatureBlocks decoded in this process: the nodes of a model host receive the same block
_DECODED: OrderedDict[tuple, list[FeatureVector]] = OrderedDict()


def to_feature_list_shared(m: Any) -> list[FeatureVector]:
    """:func:`to_feature_list`, decoded once per process for the same message content (the
    vectors are shared: read them, do not change them)."""
    key = (m.plant, m.block_index, m.header.stamp.sec, m.header.stamp.nanosec, tuple(m.names),
           bytes(memoryview(m.index)), bytes(memoryview(m.values)), tuple(m.status),
           tuple(m.valid), bytes(memoryview(m.t_start_s)), bytes(memoryview(m.t_end_s)),
           bytes(memoryview(m.crank_angle_start_deg)), tuple(m.units))
    hit = _DECODED.get(key)
    if hit is None:
        hit = _DECODED[key] = to_feature_list(m)
        if len(_DECODED) > 8:
            _DECODED.popitem(last=False)
    return hit


def to_bundle_list(m: Any) -> list[ResidualVector]:
    """The residual vectors of a ResidualBundle message, block by block (ValueError if one
    is malformed)."""
    return [rv for block in m.blocks for rv in to_residual_list(block)]


def to_residual_list(m: Any) -> list[ResidualVector]:
    """The residual vectors of a ResidualBlock message (ValueError if malformed)."""
    n, v = _block_columns(m, f"ResidualBlock of {m.model_id!r}", (
        "t_s", "valid", "status", "norm", "regime"))
    names, units = tuple(m.names), tuple(m.units)
    idx, t, norm = _np(m.index, np.uint64), _np(m.t_s), _np(m.norm)
    return [ResidualVector(model_id=m.model_id, index=int(idx[i]), t=float(t[i]),
                           valid=bool(m.valid[i]), status=m.status[i], names=names,
                           units=units, values=v[i].copy(), norm=float(norm[i]),
                           regime=m.regime[i])
            for i in range(n)]


def to_diagnosis(m: Any) -> Diagnosis:
    return Diagnosis(index=int(m.index), t=float(m.t_s), state=m.state,
                     min_residual_index=int(m.min_residual_index),
                     min_residual_model=m.min_residual_model, fault_index=int(m.fault_index),
                     fault_model=m.fault_model, candidate_faults=tuple(m.candidate_faults),
                     isolated_faults=tuple(m.isolated_faults),
                     models_online=tuple(m.models_online),
                     detection_time=float(m.detection_time_s),
                     isolation_time=float(m.isolation_time_s))


def to_fault_event(m: Any) -> FaultEvent:
    return FaultEvent(t=float(m.t_s), fault=m.fault, size=float(m.size), size_unit=m.size_unit,
                      profile=m.profile or "step", ramp_s=float(m.ramp_s), active=bool(m.active))


def symptoms_dict(m: Any) -> dict:
    """A Symptoms message as plain Python (for JSON output and tests)."""
    return {"index": int(m.index), "t": float(m.t_s), "valid": bool(m.valid),
            "status": m.status, "regime": m.regime,
            "levels": dict(zip(m.names, (int(v) for v in m.levels))),
            "residuals": dict(zip(m.names, (float(v) for v in m.residuals)))}


def fault_records(records: Any) -> list:
    """Core fault-memory records -> fdi_msgs/FaultRecord (rclpy) messages."""
    import json

    from fdi_msgs.msg import FaultRecord

    from fdi_ros.core.faultmemory import record_dict

    return [FaultRecord(fault=r.fault, status=r.status, occurrences=r.occurrences,
                        first_t_s=r.first_t_s, last_t_s=r.last_t_s,
                        freeze_frame_json=json.dumps(record_dict(r)["freeze_frame"]))
            for r in records]


def diagnostic_array(entries: Any, t_s: float) -> Any:
    """Core /diagnostics entries -> diagnostic_msgs/DiagnosticArray (rclpy), stamped in plant
    time ``t_s``."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    arr = DiagnosticArray()
    arr.header.stamp.sec, arr.header.stamp.nanosec = stamp_fields(max(t_s, 0.0))
    arr.status = [DiagnosticStatus(level=bytes([e.level]), name=e.name, message=e.message,
                                   hardware_id=e.hardware_id,
                                   values=[KeyValue(key=k, value=v) for k, v in e.values])
                  for e in entries]
    return arr


def raw_header_stamp(raw: bytes) -> float:
    """Header stamp [s] of a serialized message whose first field is a std_msgs/Header (CDR:
    4 bytes of encapsulation, then sec and nanosec), without deserialising the rest; NaN if
    the bytes cannot hold one."""
    if len(raw) < 12:
        return math.nan
    order: Literal["little", "big"] = "little" if raw[1] & 1 else "big"
    sec = int.from_bytes(raw[4:8], order, signed=True)
    return sec + int.from_bytes(raw[8:12], order) * 1e-9
