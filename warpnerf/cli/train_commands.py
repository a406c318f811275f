"""`warpnerf train <command>`: one command for each command of every registered method
(train/methods.py), made by one path (:func:`add_train_commands`): the front end registered for
it (:func:`register_train_command`; the built-in methods' four, in cli/train.py: presets, resume
checks, data parallel), else the one generated from the method's config and trainer
(:func:`generated_command`)."""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable

from ..errors import Interrupted
from ..options import add_flags, from_flags
from ..outputs import json_dumps
from ._common import check_out

__all__ = ["TrainCommand", "register_train_command", "generated_command", "add_train_commands",
           "cmd_train_method", "resume_hint"]  # fmt: skip


@dataclasses.dataclass(frozen=True)
class TrainCommand:
    """The front end of a `warpnerf train <command>`: its line in `warpnerf train --help`,
    ``add_flags(parser)`` (its flags) and ``run(args) -> exit status``."""

    help: str
    add_flags: Callable
    run: Callable


_FRONT_ENDS: dict = {}  # (method name, command) -> TrainCommand: the front ends registered
# what a generated `train <command>` sets itself (flags and argparse defaults)
_COMMAND_DESTS = {"out", "resume", "quiet", "func", "method", "subparser", "command", "model"}


def register_train_command(method: str, command: str, front: TrainCommand) -> None:
    """Gives command ``command`` of registered method ``method`` (its name) the front end
    ``front`` instead of the generated one (ValueError when it has one already)."""
    if (method, command) in _FRONT_ENDS:
        raise ValueError(f"`train {command}` of method {method!r} has a front end already")
    _FRONT_ENDS[(method, command)] = front


def generated_command(method, command: str) -> TrainCommand | None:
    """The front end of `train <command>` of a method with a ``config`` and a ``train``
    (None without): the config's flags, --out, --resume and --quiet, run by
    :func:`cmd_train_method`."""
    if method.config is None or method.train is None:
        return None

    def add(tm) -> None:
        clash = sorted({f.name for f in dataclasses.fields(method.config)} & _COMMAND_DESTS)
        if clash:  # (a developer's mistake: say which, rather than argparse's conflict)
            raise ValueError(
                f"the config of method {method.name!r} ({method.config.__name__}) has "
                f"fields named like `train {command}`'s own flags: {', '.join(clash)}"
            )
        add_flags(tm, method.config)
        tm.add_argument("--out", required=True, help="run folder")
        tm.add_argument("--resume", action="store_true", help="continue the run in --out")
        tm.add_argument("--quiet", action="store_true", help="no progress bar")

    return TrainCommand(method.help or f"train a {method.what}", add, cmd_train_method)


def add_train_commands(tsub) -> None:
    """`train <command>` for each command of every registered method (the first method to name
    a command keeps it): its registered front end, else the generated one; a method with
    neither has no `train` command. Listed in `train --help` as the front ends were registered
    (cli/train.py, imported by the parser, registers the built-ins' first), then the generated
    ones in the registry's order."""
    from ..train.methods import METHODS

    made, order = [], list(_FRONT_ENDS)
    for method in METHODS.values():
        for command in method.commands:
            front = _FRONT_ENDS.get((method.name, command)) or generated_command(method, command)
            if front is not None:
                key = (method.name, command)
                made.append((order.index(key) if key in order else len(order), method, command,
                             front))  # fmt: skip
    taken = set(tsub.choices)
    for _, method, command, front in sorted(made, key=lambda m: m[0]):  # (stable: registry's)
        if command in taken:
            continue
        taken.add(command)
        tm = tsub.add_parser(command, help=front.help)
        front.add_flags(tm)
        tm.set_defaults(func=front.run, method=method, subparser=tm)


def cmd_train_method(args) -> int:
    """`train <command>` of a registered method (train/methods.py) with a config and a
    trainer: the config from its flags, the method's trainer, its result printed as JSON."""
    method = args.method
    check_out(args.out)
    cfg = method.config(**from_flags(method.config, args))
    with resume_hint(args, getattr(cfg, "iters", None)):
        res = method.train(cfg, args.out, resume=args.resume, progress=not args.quiet)
    print(json_dumps(res))
    return 0


@contextlib.contextmanager
def resume_hint(args, iters):
    """An :class:`Interrupted` training's message names the command that continues it: this
    `train` subcommand with the run and the --iters it was aiming at."""
    import shlex

    try:
        yield
    except Interrupted as e:
        if e.resume is None:
            n = iters if isinstance(iters, int) and iters > 0 else "N"
            e.resume = (f"warpnerf train {args.model} --out {shlex.quote(str(e.run))} --resume "
                        f"--iters {n}")  # fmt: skip
        raise
