"""``fdi-ros`` subcommands.

Every module in this package that defines ``COMMAND`` is a subcommand, found by
:func:`fdi_ros.cli.main` without being listed anywhere. A module defines

``COMMAND``  tuple of words, e.g. ``("simulate",)`` or ``("bench", "crank")``
``HELP``     one line for ``--help``
``add_arguments(parser)``  adds its options to an ``argparse.ArgumentParser``
``run(args) -> int``       does the work and returns the exit code

Modules import their heavy dependencies inside ``run`` so ``fdi-ros --help`` stays fast.
"""
