"""``fdi-ros bench all``: every benchmark in turn, one JSON document out."""

from __future__ import annotations

import argparse
import importlib
import json
import pkgutil
import subprocess
import sys

COMMAND = ("bench", "all")
HELP = "run every benchmark (each in its own process) and print their JSON together"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="JSON output (the default)")
    p.add_argument("--skip", nargs="*", default=[], help="benchmarks to leave out")


def run(args: argparse.Namespace) -> int:
    from fdi_ros import commands

    names = []
    for info in pkgutil.iter_modules(commands.__path__):
        mod = importlib.import_module(f"{commands.__name__}.{info.name}")
        words: tuple[str, ...] = tuple(getattr(mod, "COMMAND", ()))
        if len(words) == 2 and words[0] == "bench" and words[1] != "all":
            names.append(words[1])
    out: dict[str, object] = {}
    for name in sorted(n for n in names if n not in args.skip):
        print(f"[bench] {name} ...", file=sys.stderr, flush=True)
        r = subprocess.run([sys.executable, "-m", "fdi_ros.cli", "bench", name, "--json"],
                           capture_output=True, text=True)
        if r.returncode != 0:
            out[name] = {"error": r.stderr.strip().splitlines()[-1:] or ["failed"]}
            continue
        try:
            out[name] = json.loads(r.stdout[r.stdout.index("{"):])
        except ValueError:
            out[name] = {"error": "no JSON output", "stdout": r.stdout[-500:]}
    print(json.dumps(out, indent=2))
    return 0
