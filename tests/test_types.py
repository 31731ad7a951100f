"""Type checking that can fail: mypy with the settings of pyproject.toml (strict on the generic
core). Modules without errors must stay so; the others may not get more errors than the
budget in tests/mypy_budget.json (lower it when you fix some; the goal is an empty budget)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BUDGET = Path(__file__).resolve().parent / "mypy_budget.json"
ERROR = re.compile(r"^(?P<file>[^:\s]+\.py):\d+: error:")


def test_mypy_within_budget():
    r = subprocess.run([sys.executable, "-m", "mypy", "--no-color-output",
                        "--no-error-summary"], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode in (0, 1), r.stdout + r.stderr  # 2: mypy itself failed
    found = Counter(m["file"] for line in r.stdout.splitlines() if (m := ERROR.match(line)))
    budget = json.loads(BUDGET.read_text())
    over = {f: (n, budget.get(f, 0)) for f, n in found.items() if n > budget.get(f, 0)}
    detail = "\n".join(line for line in r.stdout.splitlines()
                       if (m := ERROR.match(line)) and m["file"] in over)
    assert not over, f"mypy errors above budget (found, budget): {over}\n{detail}"
