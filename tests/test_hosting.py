"""Hosting of bank model nodes (no ROS graph): the configuration's ``hosting`` section, the
launcher's process layout for each mode, the model host's arguments, and the parity residuals
shared by the bank models of one process (equal to computing them per model)."""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import pytest
import yaml

from fdi_ros.core.graphconfig import Hosting, load_graph_config

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config" / "diesel.yaml"


@pytest.mark.parametrize("doc, reason", [
    ({"mode": "threads"}, "hosting mode"), ({"mode": "container", "containers": 0}, ">= 1"),
    ({"containers": 1.5}, ">= 1"), ({"containers": True}, ">= 1"),
    ({"executor": "multi"}, "executor"), ({"modes": "process"}, "unknown key"),
    (["container"], "mapping"),
])
def test_hosting_refuses_malformed(doc, reason):
    with pytest.raises(ValueError, match=reason):
        Hosting.parse(doc)


def test_hosting_groups_cover_every_node_once():
    rng = random.Random(12)
    for _ in range(30):
        names = [f"n{i}" for i in range(rng.randint(1, 20))]
        k = rng.randint(1, 25)
        groups = Hosting(mode="container", containers=k).groups(names)
        assert sorted(n for g in groups for n in g) == sorted(names)
        assert len(groups) == min(k, len(names)) and all(groups)
        assert max(map(len, groups)) - min(map(len, groups)) <= 1
    assert Hosting().groups(["a", "b"]) == [["a"], ["b"]]
    assert Hosting.parse("container") == Hosting(mode="container")


def test_config_hosting_section_and_launcher_layouts(tmp_path):
    from fdi_ros.launcher import RESPAWN_MODULES, Graph

    doc = yaml.safe_load(CONFIG.read_text())
    doc["fdi_graph"]["hosting"] = {"mode": "container", "containers": 3, "executor": "events"}
    cfgfile = tmp_path / "c.yaml"
    cfgfile.write_text(yaml.safe_dump(doc))
    cfg = load_graph_config(cfgfile)
    assert cfg.hosting == Hosting("container", 3, "events")
    names = [e.node_name for e in cfg.bank]

    g = Graph(cfgfile, echo=None)
    hosts = [n for n in g.nodes if n.module == "model_host_node"]
    assert [n.name for n in hosts] == ["fdi_model_host_0", "fdi_model_host_1",
                                       "fdi_model_host_2"]
    assert sorted(h for n in hosts for h in n.hosted) == sorted(names)
    assert not any(n.module == "residual_node" for n in g.nodes)
    for n in hosts:
        assert "--executor=events" in n.argv and "model_host_node" in RESPAWN_MODULES
        for h in n.hosted:  # each hosted node has its own parameter file, named after it
            arg = next(a for a in n.argv if a.startswith(f"--node={h}="))
            pfile = Path(arg.split("=", 2)[2])
            params = yaml.safe_load(pfile.read_text())[h]["ros__parameters"]
            assert params["model_id"] == cfg.entry(
                next(e.id for e in cfg.bank if e.node_name == h)).id
            assert g.node(h) is n  # a hosted node's process is its host
    assert g.alive()[names[0]] is False
    g.stop()

    # the caller's choice over the file's; process: one residual node process per model
    g = Graph(cfgfile, echo=None, hosting={"mode": "process"})
    assert [n.name for n in g.nodes if n.module == "residual_node"] == names
    g.stop()
    with pytest.raises(ValueError, match="containers"):
        Graph(CONFIG, echo=None, hosting={"mode": "container", "containers": 0})
    doc["fdi_graph"]["hosting"] = {"mode": "pods"}
    cfgfile.write_text(yaml.safe_dump(doc))
    with pytest.raises(ValueError, match="hosting mode"):
        load_graph_config(cfgfile)


@pytest.mark.parametrize("argv", [[], ["--node", "x"], ["--node", "=p.yaml"],
                                  ["--node", "a=p", "--executor", "multi"]])
def test_model_host_refuses_bad_arguments(argv):
    from fdi_ros.nodes.model_host_node import parse_args

    with pytest.raises(SystemExit):
        parse_args(argv)
    assert parse_args(["--node", "a=p.yaml", "--ros-args", "-r", "x:=y"]).node == ["a=p.yaml"]


def test_shared_parity_residuals_equal_per_model(diesel_reference_dir):
    from fdi_ros.core.types import FeatureVector
    from fdi_ros.plants.diesel.reference import ReferenceModelSet
    from fdi_ros.plants.diesel.symptoms import residual_vector, shared_residual_vector

    models = ReferenceModelSet.load(diesel_reference_dir)
    assert ReferenceModelSet.load(diesel_reference_dir) is models  # one set per process
    rng = np.random.default_rng(5)
    names = ("n", "rho2", "eta_v", "maf_amp", "maf_phase", "p2_amp", "p2_phase", "p2",
             "fuel", "egr_cmd", "swirl_cmd")
    base = np.array([2000.0, 1.6, 0.84, 20.0, 10.0, 0.05, 5.0, 1.5e5, 20.0, 0.0, 0.0])
    for i in range(40):
        vals = base * (1 + 0.2 * rng.standard_normal(base.size))
        fv = FeatureVector(plant="diesel", index=i % 3, t_start=0.0, t_end=0.01, alpha_start=0,
                           valid=bool(i % 7), status="", names=names, units=("",) * len(names),
                           values=vals)
        want = residual_vector(models, fv, model_id="a")
        for mid in ("a", "b"):  # a hit for the second model, re-labelled
            got = shared_residual_vector(models, fv, model_id=mid)
            for f in ("index", "t", "valid", "status", "names", "units"):
                assert getattr(got, f) == getattr(want, f), f
            assert got.norm == want.norm or (np.isnan(got.norm) and np.isnan(want.norm))
            np.testing.assert_array_equal(got.values, want.values)
            assert got.model_id == mid and got.valid == want.valid
            assert got.status == want.status
            got.values[:] = -1.0  # a model changing its copy changes nobody else's


def test_block_parity_residuals_equal_segment_by_segment(diesel_reference_dir):
    """residual_vectors (a sensor block's segments in one evaluation, what prefetch fills the
    shared cache with) gives each segment's residual_vector: values to rounding, validity,
    status and regime exactly, for blocks with invalid and out-of-region segments."""
    from fdi_ros.core.types import FeatureVector
    from fdi_ros.plants.diesel.reference import ReferenceModelSet
    from fdi_ros.plants.diesel.symptoms import residual_vector, residual_vectors

    models = ReferenceModelSet.load(diesel_reference_dir)
    seed = int(np.random.SeedSequence().entropy % 2**32)
    rng = np.random.default_rng(seed)
    names = ("n", "rho2", "eta_v", "maf_amp", "maf_phase", "p2_amp", "p2_phase", "p2",
             "fuel", "egr_cmd", "swirl_cmd")
    base = np.array([2000.0, 1.6, 0.84, 20.0, 10.0, 0.05, 5.0, 1.5e5, 20.0, 0.0, 0.0])
    for _ in range(10):
        block = []
        for i in range(int(rng.integers(1, 8))):
            vals = base * (1 + 0.3 * rng.standard_normal(base.size))
            vals[9] = rng.choice([0.0, 0.0, 0.4])  # EGR open: outside the region
            if rng.random() < 0.1:
                vals[1] = np.nan
            block.append(FeatureVector(
                plant="diesel", index=i, t_start=0.015 * i, t_end=0.015 * (i + 1),
                alpha_start=180.0 * i, valid=bool(rng.random() < 0.85),
                status="", names=names, units=("",) * len(names), values=vals))
        got = residual_vectors(models, block, model_id="a")
        for fv, g in zip(block, got, strict=True):
            w = residual_vector(models, fv, model_id="a")
            assert (g.valid, g.status, g.regime, g.index) == (w.valid, w.status, w.regime,
                                                              w.index), seed
            np.testing.assert_allclose(g.values, w.values, rtol=1e-10, atol=1e-12)


def test_bench_pace_gives_the_segment_rate_asked():
    """bench graph above the plant's speed range: the plant at its top speed, plant time
    faster by rpm / top, so the graph sees rpm / 30 segments per wall second."""
    from fdi_ros.commands.bench_graph import plant_pace
    from fdi_ros.plants.diesel.plant import SPEED_RANGE_RPM

    top = SPEED_RANGE_RPM[1]
    assert plant_pace(3600.0) == (3600.0, 1.0)
    assert plant_pace(top) == (top, 1.0)
    rpm, pace = plant_pace(6000.0)
    assert rpm == top and abs(rpm * pace / 30.0 - 200.0) < 1e-9


@pytest.mark.parametrize("domain", ["233", "241", "-1", "abc"])
def test_a_domain_id_without_dds_ports_is_refused_before_any_node_starts(domain):
    """Above 232 Fast DDS has no ports for the domain: every node process would log an RTPS
    error and the graph would never discover itself; the launcher says so instead."""
    from fdi_ros.launcher import Graph

    with pytest.raises(ValueError, match="domain id is 0-232"):
        Graph(ROOT / "config" / "diesel.yaml", env={"ROS_DOMAIN_ID": domain}, echo=None)
    assert Graph(ROOT / "config" / "diesel.yaml", env={"ROS_DOMAIN_ID": "232"}, echo=None)
