"""Bags as rosbag2 Jazzy writes them, and recovery of a bag cut short (a killed recorder)."""

from __future__ import annotations

import random
import shutil
from pathlib import Path

import pytest
import yaml

from fdi_ros import bag
from fdi_ros.cli import main as cli_main

SAMPLE = Path(__file__).resolve().parents[1] / "bags" / "diesel_leak_5mm_features"


def _copy_as_recorded(tmp_path: Path, repeat: int = 1) -> tuple[Path, list]:
    """The sample bag rewritten by our writer (as the recorder writes), ``repeat`` times one
    after the other in time (the writer flushes 1 MiB chunks: a long recording has several)."""
    one = [(t, ty, ns, bytes(d)) for t, ty, ns, d in bag.read(SAMPLE, raw=True)]
    span = one[-1][2] - one[0][2] + 1
    orig = [(t, ty, ns + k * span, d) for k in range(repeat) for t, ty, ns, d in one]
    out = tmp_path / "rec"
    with bag.BagWriter(out) as w:
        for topic, typ, t_ns, data in orig:
            w.write_raw(topic, typ, data, t_ns)
    return out, orig


def test_metadata_as_jazzy_writes_it(tmp_path: Path) -> None:
    out, orig = _copy_as_recorded(tmp_path)
    info = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["ros_distro"] == "jazzy"
    assert info["version"] == 9
    qos = {t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"]
           for t in info["topics_with_message_count"]}
    assert qos["/fdi/fault_truth"][0]["durability"] == "transient_local"
    assert qos["/fdi/features"][0]["reliability"] == "reliable"
    assert qos["/fdi/features"][0]["depth"] == 500
    # both readers still read it, to the same message count
    assert sum(n for _, n in bag.topics(out).values()) == len(orig)
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with next(out.glob("*.mcap")).open("rb") as fh:
        n = sum(1 for _ in make_reader(fh, decoder_factories=[DecoderFactory()])
                .iter_decoded_messages())
    assert n == len(orig)


def test_recover_truncated_bag_keeps_a_prefix(tmp_path: Path) -> None:
    out, orig = _copy_as_recorded(tmp_path, repeat=4)
    mcap = next(out.glob("*.mcap"))
    seed = random.randrange(1 << 30)
    print(f"seed {seed}")
    frac = random.Random(seed).uniform(0.4, 0.9)
    data = mcap.read_bytes()
    mcap.write_bytes(data[: int(len(data) * frac)])  # a SIGKILL: no summary, no footer
    (out / "metadata.yaml").unlink()
    with pytest.raises(bag.BagError):
        bag.topics(out)
    assert cli_main(["bag", "recover", str(out)]) == 0
    got = list(bag.read(out, raw=True))
    assert 0 < len(got) < len(orig)
    # what survives is exactly the beginning of the recording, byte for byte
    for (t1, ty1, ns1, d1), (t2, ty2, ns2, d2) in zip(got, orig):
        assert (t1, ty1, ns1, bytes(d1)) == (t2, ty2, ns2, bytes(d2))
    assert (out / (mcap.name + ".orig")).stat().st_size == int(len(data) * frac)
    feats = bag.read_features(out)  # deserializes: usable by fdi-ros diagnose
    assert feats


def test_recover_intact_file_without_metadata(tmp_path: Path) -> None:
    out, orig = _copy_as_recorded(tmp_path)
    (out / "metadata.yaml").unlink()
    res = bag.recover(out)
    assert res["messages"] == len(orig) and not res["truncated"]
    assert [m[:3] for m in bag.read(out, raw=True)] == [m[:3] for m in orig]


def test_recover_refuses_what_is_not_a_bag(tmp_path: Path, capsys) -> None:
    assert cli_main(["bag", "recover", str(tmp_path / "nothing")]) == 2
    assert "not a bag directory" in capsys.readouterr().err
    shutil.copytree(SAMPLE, tmp_path / "two")
    (tmp_path / "two" / "x.mcap").write_bytes(b"")
    with pytest.raises(bag.BagError, match="one .mcap"):
        bag.recover(tmp_path / "two")
