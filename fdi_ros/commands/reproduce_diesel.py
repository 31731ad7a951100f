"""``fdi-ros reproduce diesel``: the diesel wing's paper experiment
(:mod:`fdi_ros.plants.diesel.reproduce`)."""

from __future__ import annotations

from fdi_ros.plants.diesel.reproduce import HELP, add_arguments, run

COMMAND = ("reproduce", "diesel")
__all__ = ["COMMAND", "HELP", "add_arguments", "run"]
