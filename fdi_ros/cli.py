"""The ``fdi-ros`` command line: a dispatcher over the modules of :mod:`fdi_ros.commands`."""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from types import ModuleType

from fdi_ros import __version__, commands

# One line per command group that has subcommands of its own.
GROUP_HELP = {
    "bench": "benchmarks: print figures and ratios against a baseline measured in the same run",
    "reproduce": "reproduce a paper's experiment in simulation and compare with its numbers",
    "figures": "save the figures of a part (plant, identification) as PNG files",
    "train": "train the models of a plant (e.g. the turbofan's Takagi-Sugeno node models)",
    "benchmark": "real-data benchmarks: diagnose measured files and score them per sample",
}


def _command_modules() -> list[ModuleType]:
    mods = []
    for info in pkgutil.iter_modules(commands.__path__):
        mod = importlib.import_module(f"{commands.__name__}.{info.name}")
        if hasattr(mod, "COMMAND"):
            mods.append(mod)
    return sorted(mods, key=lambda m: m.COMMAND)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fdi-ros",
        description="Model-based fault detection and isolation as a ROS 2 node graph.",
    )
    parser.add_argument("--version", action="version", version=f"fdi-ros {__version__}")
    top = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    groups: dict[str, argparse._SubParsersAction] = {}
    for mod in _command_modules():
        words = tuple(mod.COMMAND)
        if len(words) == 1:
            sub = top.add_parser(words[0], help=mod.HELP, description=mod.HELP)
        else:
            group, name = words
            if group not in groups:
                gp = top.add_parser(group, help=GROUP_HELP.get(group, group))
                groups[group] = gp.add_subparsers(dest="subcommand", metavar="WHAT",
                                                  required=True)
            sub = groups[group].add_parser(name, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(sub)
        sub.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (FileNotFoundError, ValueError) as exc:
        # Bad input is the user's to fix: say what is wrong, without a traceback.
        print(f"fdi-ros: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
