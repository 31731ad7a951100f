"""Rewrite the build machine's Python paths inside the ROS wheels' CMake exports.

The Jazzy wheels were built under ``/opt/python/cp311-cp311``; their exported CMake targets
name that prefix for the Python include directory and numpy's include directory, and CMake's
generate step fails on the missing paths. This rewrites them to the venv's real paths.
"""

from __future__ import annotations

import re
import sys
import sysconfig
from pathlib import Path

import numpy


def main(venv: str) -> int:
    include = sysconfig.get_paths()["include"]
    purelib = sysconfig.get_paths()["purelib"]
    np_include = numpy.get_include()
    pattern = re.compile(r"/opt/python/cp311-cp311[^;\"\s)]*")

    def fix(match: re.Match[str]) -> str:
        path = match.group(0)
        if "numpy" in path:
            return np_include
        if "/include" in path:
            return include
        if "site-packages" in path:
            return purelib
        return str(Path(include).parents[1])

    changed = 0
    for f in Path(venv, "share").rglob("*.cmake"):
        text = f.read_text(errors="replace")
        if "/opt/python/cp311-cp311" in text:
            f.write_text(pattern.sub(fix, text))
            changed += 1
    print(f"[setup] rewrote build-machine paths in {changed} CMake files")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
