"""``fdi-ros reproduce turbofan``: the turbofan wing's paper experiment
(:mod:`fdi_ros.plants.turbofan.reproduce`)."""

from __future__ import annotations

from fdi_ros.plants.turbofan.reproduce import HELP, add_arguments, run

COMMAND = ("reproduce", "turbofan")
__all__ = ["COMMAND", "HELP", "add_arguments", "run"]
