"""The ``fdi-ros`` command line: a dispatcher over the modules of :mod:`fdi_ros.commands`."""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys
from types import ModuleType

from fdi_ros import __version__, commands

# One line per command group that has subcommands of its own.
GROUP_HELP = {
    "bag": "bag tools: recover a bag cut short",
    "bench": "benchmarks: print figures and ratios against a baseline measured in the same run",
    "reproduce": "reproduce a paper's experiment in simulation and compare with its numbers",
    "figures": "save the figures of a part (plant, identification) as PNG files",
    "train": "train the models of a plant (e.g. Takagi-Sugeno node models)",
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


# Set to 1 to get the traceback of an error instead of its one line.
TRACEBACK_ENV = "FDI_ROS_TRACEBACK"


def one_line(exc: BaseException) -> str:
    """An exception as one line: a YAML error (raised, or wrapped by a loader that named the
    file) as its problem and place; whitespace collapsed."""
    import yaml

    text = str(exc) or type(exc).__name__
    cause = exc if isinstance(exc, yaml.MarkedYAMLError) else (exc.__cause__ or exc.__context__)
    if isinstance(cause, yaml.MarkedYAMLError):
        mark = cause.problem_mark
        name = f"{mark.name}, " if mark and not mark.name.startswith("<") else ""
        where = f" ({name}line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        head = text.split("not valid YAML")[0] if cause is not exc else ""
        text = f"{head}not valid YAML: {cause.problem or cause.context}{where}"
    return " ".join(text.split())


def main(argv: list[str] | None = None) -> int:
    import yaml

    args = build_parser().parse_args(argv)
    name = " ".join(w for w in (args.command, getattr(args, "subcommand", None)) if w)
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (OSError, ValueError, yaml.YAMLError) as exc:
        # Bad input is the user's to fix: say what is wrong in one line, without a traceback.
        if os.environ.get(TRACEBACK_ENV) == "1":
            raise
        print(f"fdi-ros {name}: error: {one_line(exc)}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - anything else: still one line, traceback on demand
        if os.environ.get(TRACEBACK_ENV) == "1":
            raise
        print(f"fdi-ros {name}: unexpected {type(exc).__name__}: {one_line(exc)} "
              f"({TRACEBACK_ENV}=1 shows the traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
