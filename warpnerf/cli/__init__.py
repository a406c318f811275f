"""The ``warpnerf`` command line: ``warpnerf --help`` lists the subcommands.

Modules: ``parser`` (``build_parser``, ``main``), ``train`` (train box/nerf/volsdf/sdf),
``run_tools`` (eval, render, mesh), ``misc`` (demo, bench, data), ``_common`` (argparse types and
shared helpers).
"""

from .parser import build_parser, main

__all__ = ["build_parser", "main"]
