"""The ``warpnerf`` command line: ``warpnerf --help`` lists the subcommands.

Modules: ``parser`` (``build_parser``, ``main``), ``train`` (train box/nerf/volsdf/sdf and the
registered methods' commands), ``run_tools`` (the commands on a run folder: eval, render, mesh,
export), ``view`` (view, and the live viewer's flags of train), ``misc`` (the commands on no
run folder: demo, bench, data), ``tool_configs`` (the run tools' flags), ``_common`` (argparse
types and shared helpers).
"""

from .parser import build_parser, main

__all__ = ["build_parser", "main"]
