"""Bags written offline (rosbags, no ROS) with every fdi_msgs type, read back by rosbags and by
mcap's ROS 2 reader; damaged bags get a clear error."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from ros_helpers import PROCS

sys.path.insert(0, str(PROCS))
from sample_messages import sample_records  # noqa: E402

from fdi_ros import bag, msgs  # noqa: E402


def test_offline_bag_every_type_roundtrip(tmp_path: Path):
    from mcap_ros2.reader import read_ros2_messages

    fac = msgs.MessageFactory("rosbags")
    sent = sample_records(fac)
    out = tmp_path / "offline"
    with bag.BagWriter(out) as w:
        for i, (topic, m) in enumerate(sent.items()):
            w.write(topic, msgs.TOPICS[topic], m, 1_000_000 * (i + 1))
    got = {t: m for t, _, _, m in bag.read(out)}
    assert set(got) == set(sent)
    store = msgs.typestore()
    for topic, m in sent.items():
        typ = msgs.TOPICS[topic]
        assert store.serialize_cdr(got[topic], typ) == store.serialize_cdr(m, typ)
    blocks = bag.read_blocks(out)
    assert blocks[0].values.shape == (4, 12) and blocks[0].index == 41
    faults = bag.read_faults(out)
    assert faults[0].fault == "leak_ic_engine" and faults[0].profile == "ramp"
    mc = {m.channel.topic: m.ros_msg for m in read_ros2_messages(str(next(out.glob("*.mcap"))))}
    assert mc["/fdi/residuals"].model_id == "nominal"
    assert np.allclose(mc["/fdi/residuals"].values, [-0.031, 2.5])


def test_missing_and_damaged_bags_clear_errors(tmp_path: Path):
    with pytest.raises(FileNotFoundError):
        list(bag.read(tmp_path / "nope"))
    (tmp_path / "notabag").mkdir()
    with pytest.raises(bag.BagError, match="no metadata.yaml"):
        list(bag.read(tmp_path / "notabag"))
    out = tmp_path / "b"
    with bag.BagWriter(out) as w:
        w.write("/fdi/fault_truth", msgs.TOPICS["/fdi/fault_truth"],
                sample_records(msgs.MessageFactory("rosbags"))["/fdi/fault_truth"], 1)
    mcap = next(out.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[:40])  # truncated file
    with pytest.raises(bag.BagError):
        list(bag.read(out))
    with pytest.raises(FileExistsError):
        bag.BagWriter(out)


def test_typestore_uses_the_msg_files():
    defs = msgs.msg_definitions()
    assert set(defs) == {f"fdi_msgs/msg/{n}" for n in msgs.MESSAGES}
    store = msgs.typestore()
    for name in defs:
        assert name in store.types
    assert store.types["fdi_msgs/msg/Symptoms"].INTENSE_POSITIVE == 2
