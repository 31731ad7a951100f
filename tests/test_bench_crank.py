"""``fdi-ros bench crank`` runs as the README says (it broke once when the diesel segmenter
asked every block for a VGT command the bench's blocks do not carry): the front end's figures
and its baseline measured in the same run, the two agreeing on the amplitudes."""

from __future__ import annotations

import json

from fdi_ros.cli import main


def test_bench_crank_prints_figures_against_its_baseline(capsys):
    code = main(["bench", "crank", "--json", "--seconds", "2", "--repeat", "1"])
    out = capsys.readouterr().out
    assert code == 0, out
    d = json.loads(out)
    assert d["segments"] > 0 and d["streaming_segments_per_s"] > 0
    assert d["speedup_vs_baseline"] > 1.0
    assert d["max_amp_diff_vs_baseline"] < 1e-6
