"""How a run was made: ``RUN/run.json`` lists the sessions that trained it (a new run, then each
``--resume``), each with its command line, start time, steps, the software (warpnerf version and
git commit, Python, PyTorch, Warp, CUDA), the device and the data-parallel world size; and
:func:`environment`, the same software and device facts for other outputs (eval's metrics.json).

Why a file of its own rather than keys in ``config.json``: the config holds the run's settings,
validated field by field when a run loads and rewritten from the config object on every resume;
provenance is a log that grows with each session, and runs from before it existed (no
``run.json``) load and resume as before. Nothing here changes training: no random numbers are
drawn, and a run trains the same with or without it.

The host name is not recorded (runs are shared; it says who ran them, not how).
"""

from __future__ import annotations

import contextlib
import datetime
import os
import platform
import subprocess
import sys
from pathlib import Path

import torch

from ..outputs import write_json

__all__ = [
    "RUN_INFO",
    "environment",
    "output_provenance",
    "git_commit",
    "device_name",
    "command_line",
    "command_now",
    "start_session",
    "finish_session",
]

RUN_INFO = "run.json"  # a run folder's record of the sessions that trained it
MAX_SESSIONS = 256  # kept in run.json: the first and the latest (a run resumed without end)
_GIT_TIMEOUT = 5.0  # seconds for `git status` (the dirty flag); None beyond

_command: list | None = None  # set by the command line when it is called in-process


@contextlib.contextmanager
def command_line(argv: list):
    """Records ``argv`` as the command line of what runs inside the block (``main(argv)`` called
    from Python, where ``sys.argv`` is the caller's); outside any block it is ``sys.argv``."""
    global _command
    old, _command = _command, [str(a) for a in argv]
    try:
        yield
    finally:
        _command = old


def current_command() -> list:
    """The command line being run: the one set by :func:`command_line`, else ``sys.argv``."""
    return list(_command) if _command is not None else list(sys.argv)


def command_now() -> dict:
    """``{"command": [...], "time": ISO 8601 UTC}``: what made an output, and when."""
    return {"command": current_command(), "time": now()}


def now() -> str:
    """The current time, ISO 8601 in UTC to the second: ``2025-01-31T12:00:00Z``."""
    t = datetime.datetime.now(datetime.timezone.utc).replace(microsecond=0)
    return t.isoformat().replace("+00:00", "Z")


def _version(dist: str, module: str | None = None) -> str | None:
    from importlib import metadata

    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        mod = sys.modules.get(module or dist)
        return getattr(mod, "__version__", None)


def _source_root() -> Path:
    """The folder holding the warpnerf package (a git checkout's root when run from one)."""
    return Path(__file__).resolve().parents[2]


def _git_dir(root: Path) -> Path | None:
    """``root/.git``, or the folder a ``.git`` file (worktree, submodule) points to."""
    dot = root / ".git"
    if dot.is_dir():
        return dot
    if dot.is_file():
        with contextlib.suppress(OSError, UnicodeDecodeError):
            text = dot.read_text()[:4096].strip()
            if text.startswith("gitdir:"):
                gd = Path(text[len("gitdir:") :].strip())
                gd = gd if gd.is_absolute() else root / gd
                return gd if gd.is_dir() else None
    return None


def _is_sha(text: str) -> bool:
    return len(text) in (40, 64) and all(c in "0123456789abcdef" for c in text)


def _resolve_ref(git_dir: Path, ref: str) -> str | None:
    """The commit of ``ref`` (``refs/heads/main``): its loose file, else packed-refs, in the
    git folder or (worktrees) the common folder."""
    folders = [git_dir]
    with contextlib.suppress(OSError, UnicodeDecodeError):
        common = (git_dir / "commondir").read_text().strip()
        folders.append((git_dir / common).resolve())
    for folder in folders:
        with contextlib.suppress(OSError, UnicodeDecodeError):
            sha = (folder / ref).read_text()[:100].strip()
            if _is_sha(sha):
                return sha
        with contextlib.suppress(OSError, UnicodeDecodeError):
            for line in (folder / "packed-refs").read_text().splitlines():
                sha, _, name = line.partition(" ")
                if name.strip() == ref and _is_sha(sha):
                    return sha
    return None


def git_commit(root: Path | None = None) -> dict:
    """``{"commit": sha, "dirty": bool}`` of the git checkout warpnerf runs from (read from
    ``.git`` without running git; ``dirty``: tracked files changed, from ``git status`` with a
    timeout and no index write); each None when not known (an installed package, no git)."""
    root = _source_root() if root is None else Path(root)
    git_dir = _git_dir(root)
    if git_dir is None:
        return {"commit": None, "dirty": None}
    commit = None
    with contextlib.suppress(OSError, UnicodeDecodeError):
        head = (git_dir / "HEAD").read_text()[:1000].strip()
        if head.startswith("ref:"):
            commit = _resolve_ref(git_dir, head[4:].strip())
        elif _is_sha(head):  # a detached HEAD
            commit = head
    dirty = None
    if commit is not None:
        try:
            out = subprocess.run(
                ["git", "--no-optional-locks", "-C", str(root), "status", "--porcelain",
                 "--untracked-files=no"],
                capture_output=True, text=True, timeout=_GIT_TIMEOUT, check=False,
                env={**os.environ, "GIT_OPTIONAL_LOCKS": "0"},
            )  # fmt: skip
            if out.returncode == 0:
                dirty = bool(out.stdout.strip())
        except (OSError, subprocess.SubprocessError):
            pass
    return {"commit": commit, "dirty": dirty}


def _cpu_name() -> str:
    with contextlib.suppress(OSError, UnicodeDecodeError):
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.partition(":")[2].strip()
    return platform.processor() or platform.machine() or "cpu"


def device_name(device) -> str:
    """A device's model: the GPU's name for CUDA, the CPU's model otherwise."""
    device = torch.device(device)
    if device.type == "cuda" and torch.cuda.is_available():
        return torch.cuda.get_device_name(device)
    return _cpu_name()


def environment(device) -> dict:
    """The software and the device a result was made with: warpnerf's version and git commit,
    Python, PyTorch, Warp and CUDA versions (None when not known), the device and its model."""
    return {
        "versions": {
            "warpnerf": _version("warpnerf"),
            "python": platform.python_version(),
            "torch": torch.__version__,
            "warp": _version("warp-lang", "warp"),
            "cuda": torch.version.cuda,
        },
        "git": git_commit(),
        "device": str(device),
        "device_name": device_name(device),
    }


def output_provenance(device) -> dict:
    """The ``provenance`` block of an output's metrics.json (eval's, the demo's): the command
    line and time (:func:`command_now`) with the software and device (:func:`environment`)."""
    return {**command_now(), **environment(device)}


def _session(device, step: int, iters: int, dist) -> dict:
    world = dist.world if dist is not None else 1
    local = os.environ.get("LOCAL_WORLD_SIZE", "")
    return {
        "command": current_command(),
        "start_time": now(),
        "start_step": int(step),
        "iters": int(iters),
        **environment(device),
        "world_size": world,  # data-parallel ranks (torchrun); 1 for one process
        "nproc_per_node": int(local) if dist is not None and local.isdigit() else world,
    }


def _earlier_sessions(path: Path) -> list:
    """The sessions of an existing run.json (untrusted: anything malformed counts as none; one
    that cannot be read as JSON is named in a warning)."""
    import warnings

    from ..errors import UserError
    from ..json_input import read_json

    if not path.is_file() or path.is_symlink():
        return []
    try:
        saved = read_json(path, "run record")
    except UserError as e:
        warnings.warn(f"{e}; its earlier sessions are not kept", UserWarning, stacklevel=2)
        return []
    sessions = saved.get("sessions") if isinstance(saved, dict) else None
    return [s for s in sessions if isinstance(s, dict)] if isinstance(sessions, list) else []


def start_session(run, device, step: int, iters: int, dist=None, resume: bool = False) -> dict:
    """Writes ``RUN/run.json`` for a session starting at ``step``: a new run's first session, or
    (``resume``) the earlier sessions plus this one. Returns the record (for
    :func:`finish_session`)."""
    path = Path(run) / RUN_INFO  # (write_json refuses a run.json warpnerf did not write)
    sessions = _earlier_sessions(path) if resume else []
    sessions.append(_session(device, step, iters, dist))
    if len(sessions) > MAX_SESSIONS:  # the first (how the run began) and the latest
        sessions = sessions[:1] + sessions[-(MAX_SESSIONS - 1) :]
    info = {"sessions": sessions}
    write_json(path, info)
    return info


def finish_session(run, info: dict, step: int, outcome: str) -> None:
    """Completes the latest session of ``info`` (its last step, end time and ``outcome``:
    "finished", "stopped" by --max-seconds or "interrupted") and rewrites ``RUN/run.json``."""
    info["sessions"][-1].update(end_step=int(step), end_time=now(), outcome=outcome)
    write_json(Path(run) / RUN_INFO, info)
