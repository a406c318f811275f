"""The argument parser of the ``warpnerf`` command and ``main``."""

from __future__ import annotations

import argparse
import dataclasses
import difflib
import os
import re
import sys

from ..errors import UserError, exit_status
from ..fields.model import fields_with
from ..options import add_flags
from ._common import add_data_format_flags, positive_arg, sigterm_exits
from .no_run_tools import cmd_bench, cmd_data, cmd_demo
from .run_tools import cmd_eval, cmd_export, cmd_mesh, cmd_render
from .tool_configs import EvalConfig, ExportConfig, MeshConfig, RenderConfig
from .train import cmd_train_nerf
from .train_commands import add_train_commands
from .view import cmd_view, view_flags, viewer_after_training

# the command line, and the helpers the tools in scripts/ may use
__all__ = [
    "main",
    "build_parser",
    "split_command",
    "step_tool_args",
    "tool_parser",
    "nerf_task_from_argv",
    "CommandParser",
    "version_line",
]

# the runs eval, render and export read (the NeRF runner: any --field)
RADIANCE_RUNS = "train nerf or train volsdf"


class CommandParser(argparse.ArgumentParser):
    """The parser of the ``warpnerf`` command and of each of its subcommands (argparse makes the
    subparsers of a parser's own class). An argument error is one line on stderr, ``warpnerf
    train nerf: error: argument --iters: ...``, exit status 2, as the library's errors are (the
    usage is left to ``--help``, which stays whole); an unknown flag is reported by the deepest
    subcommand given, with its nearest flag ("did you mean --iters?"), also when a required
    flag is missing too; an invalid choice names the nearest one."""

    def parse_known_args(self, args=None, namespace=None):
        self._argv = list(sys.argv[1:] if args is None else args)  # (what this parser reads)
        return super().parse_known_args(args, namespace)

    def parse_args(self, args=None, namespace=None):
        ns, extras = self.parse_known_args(args, namespace)
        if extras:  # (argparse hands a subcommand's unknown arguments up to the top parser)
            leaf = _chosen(self, ns)
            leaf.error(leaf.unrecognized(extras))
        return ns

    def error(self, message):
        if message.startswith("the following arguments are required") and not _subcommands(self):
            # a typo of a required flag's name leaves it missing: the typo is the error
            argv = getattr(self, "_argv", [])
            argv = argv[: argv.index("--")] if "--" in argv else argv
            unknown = [a for a in argv if self._unknown_flag(a)]
            if unknown:
                message = self.unrecognized(unknown)
        elif (m := _INVALID_CHOICE.search(message)) is not None:
            # (the choices quoted, or bare as newer Pythons write them)
            choices = re.findall(r"'([^']*)'", m.group(2)) or m.group(2).split(", ")
            near = _nearest(m.group(1), choices)
            if near is not None:
                message = f"{message}; did you mean {near!r}?"
        self.exit(2, f"{self.prog}: error: {message}\n")

    def unrecognized(self, extras: list) -> str:
        """The error of arguments this parser does not know, with the nearest flag to the first
        unknown flag among them."""
        message = f"unrecognized arguments: {' '.join(extras)}"
        # (names compared without their dashes, which would make any two flags look alike)
        flags = [s[2:] for a in self._actions for s in a.option_strings if s.startswith("--")]
        for arg in extras:
            if arg.startswith("--") and len(arg) > 2:
                near = _nearest(arg[2:].split("=", 1)[0], flags)
                if near is not None:
                    return f"{message}; did you mean --{near}?"
        return message

    def _unknown_flag(self, arg: str) -> bool:
        """Whether ``arg`` is a long flag this parser has no flag for (nor one it abbreviates)."""
        if not arg.startswith("--") or len(arg) <= 2:
            return False
        name = arg.split("=", 1)[0]
        return not any(s.startswith(name) for s in self._option_string_actions)


_INVALID_CHOICE = re.compile(r"invalid choice: '([^']*)' \(choose from (.*)\)$")


def _nearest(word: str, candidates: list) -> str | None:
    """The candidate closest to ``word`` (letter case ignored), or None when none is close."""
    lower = {c.lower(): c for c in candidates}
    near = difflib.get_close_matches(word.lower(), list(lower), n=1, cutoff=0.6)
    return lower[near[0]] if near else None


def _subcommands(parser):
    """The subcommands action of ``parser``, or None."""
    return next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)


def _chosen(parser, ns):
    """The deepest subcommand's parser that the parsed ``ns`` chose below ``parser``."""
    while (sub := _subcommands(parser)) is not None and getattr(ns, sub.dest, None) in sub.choices:
        parser = sub.choices[getattr(ns, sub.dest)]
    return parser


def version_line() -> str:
    """What ``warpnerf --version`` prints: warpnerf's version and those of Warp, PyTorch and
    Python (the installed distributions' metadata; nothing is imported)."""
    import platform
    from importlib import metadata

    def version(dist):
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return None

    from .. import __version__

    own = version("warpnerf") or __version__
    warp, torch = version("warp-lang") or "not installed", version("torch") or "not installed"
    return f"warpnerf {own} (warp {warp}, torch {torch}, Python {platform.python_version()})"


class _Version(argparse.Action):
    """``--version``: prints :func:`version_line` and exits 0."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help=None):  # fmt: skip
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(version_line())
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    p = CommandParser(
        prog="warpnerf",
        description="Differentiable volume rendering with NVIDIA Warp kernels and PyTorch.",
    )
    p.add_argument(
        "--version", action=_Version,
        help="print the versions of warpnerf, Warp, PyTorch and Python and exit",
    )  # fmt: skip
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    d = sub.add_parser(
        "demo",
        help="main job: fit an analytic box to rendered views, write a "
        "spiral video, images and metrics.json (built-in scene, no data needed)",
    )
    d.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    d.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    d.add_argument("--iters", type=positive_arg(int), default=300,
                   help="optimisation steps of the box fit (default 300)")  # fmt: skip
    d.add_argument("--size", type=positive_arg(int), default=64, help="training image size")
    d.add_argument("--frames", type=positive_arg(int), default=40, help="spiral video frames")
    d.add_argument("--video-size", type=positive_arg(int), default=128,
                   help="spiral video width and height, pixels (default 128)")  # fmt: skip
    d.add_argument("--quiet", action="store_true", help="no progress bar")
    d.set_defaults(func=cmd_demo)

    t = sub.add_parser("train", help="train a run: nerf, volsdf (neural SDF from images), sdf "
                       "(neural SDF from points) or box (fit an SDF box to images)")  # fmt: skip
    tsub = t.add_subparsers(dest="model", metavar="MODEL", required=True)
    add_train_commands(tsub)  # (one per command of every registered method)

    e = sub.add_parser("eval", help="PSNR/SSIM of a trained run on a split, side-by-side PNGs")
    e.add_argument("run", help=f"run folder of {RADIANCE_RUNS} (--geometry: an SDF field's, "
                   f"{', '.join(fields_with(geometry='sdf'))})")  # fmt: skip
    add_flags(e, EvalConfig)
    e.set_defaults(func=cmd_eval)

    r = sub.add_parser("render", help="colour and depth videos of a trained run along a path")
    r.add_argument("run", help=f"run folder of {RADIANCE_RUNS}")
    add_flags(r, RenderConfig)
    r.set_defaults(func=cmd_render)

    m = sub.add_parser("mesh", help="marching cubes of an SDF scene or a trained run -> PLY + PNG")
    m.add_argument("run", nargs="?", help="run folder of train nerf (density level set), "
                   "volsdf or sdf (the SDF's zero level set); or give --sdf")  # fmt: skip
    add_flags(m, MeshConfig)
    m.set_defaults(func=cmd_mesh)

    v = sub.add_parser("view", help="web viewer of any run on a local port (viser): renders, "
                       "training cameras, occupancy grid, mesh, camera-path editor")  # fmt: skip
    view_flags(v)
    v.set_defaults(func=cmd_view)

    x = sub.add_parser(
        "export", help="a run as files other tools open: a coloured point cloud with normals "
        "(PLY) or its cameras (nerfstudio transforms.json)",
    )  # fmt: skip
    x.add_argument("run", help=f"run folder of {RADIANCE_RUNS}")
    x.add_argument(
        "what", choices=["pointcloud", "cameras"], help="pointcloud: rendered surface points "
        "with colours and normals (PLY); cameras: the cameras as nerfstudio transforms.json",
    )  # fmt: skip
    add_flags(x, ExportConfig)
    x.set_defaults(func=cmd_export)

    dp = sub.add_parser(
        "data", help="check a dataset folder and print a JSON summary (format, splits, cameras)"
    )
    dp.add_argument("dir", help="Blender, nerfstudio, COLMAP or LLFF folder")
    add_data_format_flags(dp)
    dp.add_argument(
        "--downscale", type=positive_arg(int), default=1,
        help="load the images at 1/N resolution, as train --downscale N (default 1)",
    )  # fmt: skip
    dp.add_argument(
        "--allow-outside-paths", action="store_true",
        help="let the dataset's files name images outside its folder (absolute paths, '..', "
        "symlinks out of it); refused by default",
    )  # fmt: skip
    dp.set_defaults(func=cmd_data)

    b = sub.add_parser("bench", help="benchmark kernels against their PyTorch twins")
    b.add_argument(
        "kernel",
        nargs="?",
        default="composite",
        choices=["composite", "march", "encoding", "sphere-trace", "all"],
        help="kernel family to time (default composite; all: every family)",
    )
    b.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    b.add_argument("--json", default=None, help="write the results as JSON here")
    b.add_argument("--quick", action="store_true", help="smallest sizes only")
    b.add_argument(
        "--rays", type=positive_arg(int), default=None,
        help="composite: time this many rays only (default: the size list; 2^20 rays on cuda, "
        "2^12 on cpu when only --samples is given)",
    )  # fmt: skip
    b.add_argument(
        "--samples", type=positive_arg(int), default=None,
        help="composite: samples per ray of that one size (default 128)",
    )  # fmt: skip
    b.set_defaults(func=cmd_bench)
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0

    from contextlib import nullcontext

    from ..train.provenance import command_line

    # what a run's run.json records as its command: this argv when called from Python
    recorded = nullcontext() if argv is None else command_line(["warpnerf", *argv])

    def run():
        # torchrun (WORLD_SIZE > 1) is for the data-parallel trainers; any other command would run
        # whole on every rank and write the same outputs from each
        if args.func is not cmd_train_nerf and int(os.environ.get("WORLD_SIZE", "1") or 1) > 1:
            raise UserError(f"warpnerf {args.command} runs in one process; data-parallel "
                            "launches (torchrun) are for train nerf and train volsdf")  # fmt: skip
        from ..json_input import one_read_per_command

        # (each run folder's config.json is read from the disk once in the command)
        with sigterm_exits(), recorded, one_read_per_command(), viewer_after_training(args):
            return args.func(args)

    code = exit_status(f"warpnerf {args.command}", run)
    dist = sys.modules.get("warpnerf.train.distributed")
    if argv is None and dist is not None and dist.LOST:
        # a data-parallel run that lost a rank: its process group is broken, and tearing the
        # interpreter down with the backend's threads still alive aborts in C++ ("terminate
        # called without an active exception") after the one-line error; leave at once
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


def split_command(argv: list) -> tuple:
    """(a tool's own arguments, the command line after ``--``) of a measuring script's argv,
    e.g. ``--steps 50 -- train nerf --data lego`` (no ``--``: all the tool's own)."""
    if "--" not in argv:
        return list(argv), []
    i = argv.index("--")
    return list(argv[:i]), list(argv[i + 1 :])


def tool_parser(doc: str, argv=None) -> tuple:
    """(parser, its subcommands, the tool's own arguments, the train command line after
    ``--``) of a measuring tool with subcommands (scripts/time_to_quality.py, dp_scaling.py);
    ``doc``: its docstring (the first paragraph is the description)."""
    own, train_argv = split_command(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    return p, p.add_subparsers(dest="cmd", required=True), own, train_argv


def step_tool_args(doc: str, warm: int, steps: int, argv=None, add=None) -> tuple:
    """(its own parsed flags, the train command line after ``--``) of a tool that measures
    training steps (scripts/profile_train_step.py, sync_sites.py, dp_profile.py): ``--warm``
    untimed steps, then ``--steps`` measured ones, ``--json`` the file of its results;
    ``add(parser)`` adds the tool's own flags. ``doc``: the tool's docstring (its first
    paragraph is the description); ``argv``: default ``sys.argv[1:]``."""
    own, train_argv = split_command(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    p.add_argument("--warm", type=int, default=warm, help=f"untimed steps first (default {warm})")
    p.add_argument("--steps", type=int, default=steps, help=f"steps measured (default {steps})")
    p.add_argument("--json", default=None, help="write the results as JSON here")
    if add is not None:
        add(p)
    return p.parse_args(own), train_argv


def nerf_task_from_argv(argv: list, dist=None, device: str | None = None):
    """(cfg, task, optimiser) of a `warpnerf train nerf|volsdf ...` command line, built as the
    command builds them but without a run folder (for the profiling and measuring tools).
    ``dist``/``device``: one rank of a data-parallel run and its device (``from_env``)."""
    import torch

    from ..train.nerf import NeRFTask, build_model, settle_new_run
    from .train import nerf_config_from_args

    cfg = nerf_config_from_args(build_parser().parse_args([*argv, "--out", "unused"]))
    if device is not None:
        cfg = dataclasses.replace(cfg, device=device)
    # (the training split read, the config resolved, checked and frozen as train_nerf does)
    cfg, train = settle_new_run(cfg)
    task = NeRFTask(cfg, build_model(cfg), train, None, log=lambda *x: None, dist=dist)
    if cfg.device.startswith("cuda"):
        torch.backends.cuda.matmul.allow_tf32 = cfg.tf32
    return cfg, task, task.optimizer(task.parameters(), cfg.lr)
