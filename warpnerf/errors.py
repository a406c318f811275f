"""User-facing errors: the CLI prints their message (no traceback) and exits with status 2."""

__all__ = [
    "UserError",
    "Interrupted",
    "Diverged",
    "describe_failure",
    "available_memory",
    "check_fits",
    "check_device",
    "exit_status",
]


class UserError(Exception):
    """A mistake in the user's input (file, field, flag); the message says what and where."""


class Interrupted(Exception):
    """Training stopped by SIGINT/SIGTERM after saving a checkpoint at ``step``; the CLI exits
    with 128 + signum. ``resume``: the command that continues the run (the `train` command sets
    it, e.g. ``warpnerf train volsdf --out RUN --resume --iters 3000``); None: a generic one."""

    def __init__(self, signum: int, step: int, run, resume: str | None = None):
        self.signum, self.step, self.run, self.resume = signum, step, run, resume
        super().__init__(signum, step, run)

    def __str__(self) -> str:
        import signal

        name = signal.Signals(self.signum).name
        how = self.resume or f"warpnerf train KIND --out {self.run} --resume --iters N"
        return f"{name} at step {self.step}: checkpoint saved in {self.run}; continue with `{how}`"


class Diverged(Exception):
    """Training met a non-finite loss or gradient at ``step``; nothing of that step was applied or
    saved (the run's checkpoint is the last good one). The CLI exits with status 3."""

    def __init__(self, step: int, what: str, run, lr: float | None = None):
        self.step, self.run = step, run
        hint = f" (learning rate {lr:g})" if lr is not None else ""
        super().__init__(
            f"training diverged at step {step}: {what} is not finite{hint}. Nothing of this step "
            f"was saved; {run} keeps its last good checkpoint. Start a new run with a lower "
            "learning rate (--lr)"
        )


_OS_HINTS = {
    "ENAMETOOLONG": "the file name is too long for the file system",
    "ENOSPC": "no space left on the device",
    "EDQUOT": "disk quota exceeded",
    "EROFS": "the file system is read-only",
    "EACCES": "permission denied",
    "EPERM": "operation not permitted",
    "ENOTDIR": "a part of the path is a file, not a folder",
    "EISDIR": "it is a folder",
    "ENOENT": "no such file or folder",
    "EEXIST": "it already exists",
    "EMFILE": "too many open files",
    "EIO": "input/output error",
}


def describe_failure(exc: BaseException) -> str | None:
    """One line for a failure of the machine rather than of the program: an OS error (naming the
    path), or memory that cannot be had (naming the size asked for); None for anything else (a
    bug, which keeps its traceback)."""
    import errno

    if isinstance(exc, OSError) and not isinstance(exc, (BlockingIOError,)):
        name = errno.errorcode.get(exc.errno or -1, "")
        why = _OS_HINTS.get(name) or exc.strerror or str(exc)
        where = exc.filename if exc.filename is not None else ""
        if exc.filename2 is not None:
            where = f"{where} -> {exc.filename2}"
        return f"{where}: {why}" + (f" ({name})" if name else "") if where else f"{why} ({name})"
    if isinstance(exc, MemoryError):
        return f"out of memory{': ' + str(exc) if str(exc) else ''}; use smaller sizes"
    text = str(exc)
    low = text.lower()
    if isinstance(exc, RuntimeError) and (
        "out of memory" in low or "can't allocate memory" in low or "failed to allocate" in low
    ):
        import re

        first = next((ln for ln in text.splitlines() if ln.strip()), text)
        m = re.search(r"allocate (memory: you tried to allocate )?([\d.]+ ?[KMGT]?i?B|\d+ bytes)",
                      text)  # fmt: skip
        if m and m.group(2).endswith(" bytes"):
            asked = human_bytes(float(m.group(2).split()[0]))
        else:
            asked = m.group(2) if m else None
        what = f"tried to allocate {asked}" if asked else first.strip()[:200]
        return f"out of memory ({what}); lower the sizes (--batch, --chunk, --size, --resolution)"
    return None


def human_bytes(n: float) -> str:
    """``n`` bytes as a short string in B, KiB, MiB, ... (one decimal)."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if n < 1024 or unit == "PiB":
            return f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} PiB"


def check_device(device: str, where: str | None = None) -> str:
    """``device`` ("cpu", "cuda" or "cuda:N"), or a UserError when it is not one or cannot be
    used here: the one device check of every command, new runs and saved ones alike.
    ``where``: the run folder a saved device comes from (None: the ``--device`` flag)."""
    ok = isinstance(device, str) and (
        device in ("cpu", "cuda") or (device[:5] == "cuda:" and device[5:].isdigit())
    )
    if not ok:
        raise UserError(f"--device must be cpu or cuda, got {device!r}")
    if device == "cpu":
        return device
    import torch

    said = f"--device {device}" if where is None else f"{where}: device {device}"
    if not torch.cuda.is_available():
        raise UserError(f"{said}: no CUDA device is available to PyTorch here (pass --device cpu)")
    count = torch.cuda.device_count()
    if device[5:] and int(device[5:]) >= count:  # (cuda:N past the devices there are)
        raise UserError(f"{said}: PyTorch sees {count} CUDA device(s) here (cuda:0 to "
                        f"cuda:{count - 1})")  # fmt: skip
    return device


def available_memory(device: str = "cpu") -> int:
    """Bytes the device has in all (CUDA: the GPU's total; CPU: physical memory)."""
    import os

    if str(device).startswith("cuda"):
        import torch

        return int(torch.cuda.mem_get_info(torch.device(device))[1])
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 1 << 62  # unknown: let the allocator decide


def check_fits(nbytes: float, device: str, what: str) -> None:
    """:class:`UserError` before allocating when ``nbytes`` cannot fit on ``device`` at all (more
    than its whole memory): an absurd --size, --batch or --chunk fails at once with the size
    asked for instead of after minutes, or with the allocator's traceback."""
    total = available_memory(device)
    if nbytes > total:
        raise UserError(
            f"{what} needs about {human_bytes(nbytes)}, more than the {human_bytes(total)} of "
            f"{device}; choose smaller sizes"
        )


def exit_status(prog: str, fn, *args, **kwargs) -> int:
    """Runs ``fn(*args, **kwargs)`` and turns the library's outcomes into an exit status, with
    one line ``PROG: error: ...`` on stderr instead of a traceback: its return value (None: 0);
    2 for a :class:`UserError`, input nested too deeply, or a refusal of the machine (an OS
    error naming its path, memory that cannot be had: :func:`describe_failure`); 3 for
    :class:`Diverged`; 128 + the signal for :class:`Interrupted` (training checkpointed its last
    step); 130 for Ctrl-C. Anything else is a bug and keeps its traceback. The ``warpnerf``
    command and the demos use it."""
    import sys

    def say(text: str) -> None:
        print(f"{prog}: {text}", file=sys.stderr)

    try:
        return int(fn(*args, **kwargs) or 0)
    except UserError as e:
        say(f"error: {e}")
        return 2
    except Interrupted as e:
        say(f"interrupted by {e}")
        return 128 + e.signum
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Diverged as e:
        say(f"error: {e}")
        return 3
    except RecursionError:
        say("error: input nested too deeply")
        return 2
    except (OSError, MemoryError, RuntimeError) as e:
        line = describe_failure(e)
        if line is None:
            raise
        say(f"error: {line}")
        return 2
