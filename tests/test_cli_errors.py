"""Every kind of fdi-ros command answers a malformed input file (scenario YAML, CSV, mapping,
bag, graph configuration) with one line on stderr and a non-zero status, never a traceback,
and says what it skipped."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from fdi_ros.cli import main

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = """name: short
seed: 1
duration_s: 3.0
dalpha_deg: 6.0
block_deg: 720.0
inputs:
  kind: points
  points:
    - {t: 0.0, n: 1500, torque: 80}
    - {t: 3.0, n: 2500, torque: 150}
"""


def one_error_line(capsys, argv: list[str], command: str) -> str:
    code = main(argv)
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code != 0, err
    assert "Traceback" not in err
    assert lines and lines[-1].startswith(f"fdi-ros {command}: error: "), err
    errors = [ln for ln in lines if "error" in ln]
    assert len(errors) == 1, err
    return lines[-1]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("malformed")
    (d / "short.yaml").write_text(SCENARIO)
    assert main(["simulate", str(d / "short.yaml"), "--csv", str(d / "good.csv")]) == 0
    (d / "syntax.yaml").write_text("name: x\nduration_s: [1\n")
    (d / "list.yaml").write_text("- a\n- b\n")
    (d / "types.yaml").write_text("name: x\nduration_s: abc\ninputs: 5\n")
    (d / "ragged.csv").write_text("t,n,p2\n0,1,2\n1,x\n")
    (d / "text.csv").write_text("t,n\n0,fast\n1,2\n")
    bag = d / "broken_bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("junk\n")
    trunc = d / "truncated_bag"
    shutil.copytree(ROOT / "bags" / "diesel_leak_5mm_features", trunc)
    mcap = next(trunc.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[:20000])
    (d / "map_syntax.yaml").write_text("signals: [1, 2\n")
    (d / "map_shape.yaml").write_text("time: t\nsignals: [1, 2]\n")
    (d / "cfg_bank.yaml").write_text("fdi_graph:\n  plant: diesel\n  bank: 7\n")
    (d / "cfg_empty.yaml").write_text("fdi_graph:\n  plant: diesel\n  bank: []\n")
    return d


@pytest.mark.parametrize("name, words", [("syntax.yaml", "not valid YAML"),
                                         ("list.yaml", "mapping"), ("types.yaml", "inputs"),
                                         ("absent.yaml", "not found")])
def test_simulate_malformed_scenario(files, capsys, name, words):
    line = one_error_line(capsys, ["simulate", str(files / name), "--out",
                                   str(files / "o")], "simulate")
    assert words in line


@pytest.mark.parametrize("name, words", [("ragged.csv", "line 3"), ("text.csv", "fast"),
                                         ("broken_bag", "bag"), ("syntax.yaml", "YAML")])
def test_identify_malformed_data(files, capsys, name, words):
    line = one_error_line(capsys, ["identify", "--data", str(files / name), "--out",
                                   str(files / "id")], "identify")
    assert words in line


@pytest.mark.parametrize("name", ["broken_bag", "truncated_bag", "absent_bag"])
def test_diagnose_malformed_bag(files, capsys, name):
    line = one_error_line(capsys, ["diagnose", str(files / name), "--json",
                                   str(files / "d.json")], "diagnose")
    assert name in line


@pytest.mark.parametrize("command", ["build-bank", "launch"])
@pytest.mark.parametrize("name, words", [("syntax.yaml", "not valid YAML"),
                                         ("cfg_bank.yaml", "list"), ("cfg_empty.yaml", "empty"),
                                         ("list.yaml", "fdi_graph")])
def test_graph_commands_malformed_config(files, capsys, command, name, words):
    line = one_error_line(capsys, [command, str(files / name)], command)
    assert words in line and name in line


@pytest.mark.parametrize("argv, words", [
    (["--measured", "ragged.csv"], "line 3"),
    (["--measured", "good.csv", "--mapping", "map_syntax.yaml"], "not valid YAML"),
    (["--measured", "good.csv", "--mapping", "map_shape.yaml"], "signals"),
    (["--measured", "broken_bag"], "bag"),
])
def test_discrepancy_malformed_inputs(files, capsys, argv, words):
    argv = [a if a.startswith("--") else str(files / a) for a in argv]
    line = one_error_line(capsys, ["discrepancy", "--plant", "diesel", "--ident",
                                   str(files / "good.csv"), *argv, "--json",
                                   str(files / "x.json"), "--quiet"], "discrepancy")
    assert words in line


def test_discrepancy_says_what_it_skipped(files, capsys):
    lines = (files / "good.csv").read_text().splitlines()
    head = lines[0].split(",")
    out = [lines[0]]
    for i, row in enumerate(lines[1:]):
        cells = row.split(",")
        if i % 40 == 7:
            cells[head.index("maf")] = "nan"
        if i % 97 == 3:
            cells[head.index("p2")] = ""
        out.append(",".join(cells))
    (files / "holes.csv").write_text("\n".join(out) + "\n")
    main(["discrepancy", "--plant", "diesel", "--ident", str(files / "good.csv"), "--measured",
          str(files / "holes.csv"), "--json", str(files / "holes.json"), "--quiet"])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    said = [ln for ln in err.splitlines() if "skipped" in ln]
    assert len(said) == 1 and "maf" in said[0] and "p2" in said[0], err
    skipped = json.loads((files / "holes.json").read_text())["skipped"]
    assert skipped["samples"] > 0 and set(skipped["by_signal"]) == {"maf", "p2"}
    assert skipped["samples"] <= skipped["by_signal"]["maf"] + skipped["by_signal"]["p2"]
