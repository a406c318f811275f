"""Shared pieces of the command line: argparse types, output-path checks, the saved run config,
shared flags and the SIGTERM guard."""

from __future__ import annotations

import contextlib
import signal
import threading
from pathlib import Path

from ..errors import UserError, check_device
from ..options import CHECKS


def parse_device(name: str) -> str:
    """The --device flag's value, checked (:func:`~warpnerf.errors.check_device`)."""
    return check_device(name)


def positive_arg(kind):
    return CHECKS[(kind.__name__, "positive")]


nonnegative_arg = CHECKS[("int", "nonnegative")]
seed_arg = CHECKS[("int", "seed")]
finite_arg = CHECKS[("float", "finite")]
nonnegative_float = CHECKS[("float", "nonnegative")]


def check_out(path, flag: str = "--out", file: bool = False) -> None:
    """UserError unless ``path`` can be written as a folder (or, with ``file``, as a file): it is
    not an existing file (folder) and its nearest existing parent is a folder."""
    p = Path(path)
    if file and p.is_dir():
        raise UserError(f"{flag} {path} is a folder, not a file")
    for q in p.parents if file else (p, *p.parents):
        if q.is_dir():
            return
        if q.exists():
            raise UserError(f"{flag} {path}: {q} is a file, not a folder")


def check_existing(path, what: str = "run folder") -> None:
    """UserError ``PATH: not found`` when nothing exists at ``path`` (a run, a point cloud): the
    loaders' own messages ("not a training run") are for paths that exist."""
    import os

    if not os.path.lexists(path):
        raise UserError(f"{path}: not found (expected a {what})")


def saved_config(run) -> dict:
    """RUN/config.json as a dict; {} when absent or unreadable (the run loaders say why)."""
    from ..json_input import read_run_config

    try:
        saved = read_run_config(Path(run) / "config.json")
    except UserError:
        return {}
    return saved if isinstance(saved, dict) else {}


def add_data_format_flags(p) -> None:
    """--format and --holdout (`data`, `train nerf`, `train volsdf`)."""
    from ..data.loading import FORMATS

    p.add_argument("--format", default="auto", choices=FORMATS, help="data format (auto: detect)")
    p.add_argument(
        "--holdout",
        type=nonnegative_arg,
        default=8,
        help="COLMAP/LLFF: every Nth image (sorted names) is val/test; 0 = none (default 8)",
    )


@contextlib.contextmanager
def sigterm_exits():
    """SIGTERM outside a training loop (loading, meshing, rendering, writing) raises SystemExit(143)
    instead of killing the process outright, so atomic writers remove their temporary files. The
    training loops install their own handler while they run (finish the step, checkpoint)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise SystemExit(128 + signum)

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)
