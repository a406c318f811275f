"""Opening files that may be anything (a run or dataset folder is downloaded, unpacked and
shared): :func:`open_regular` never follows a link unless asked, never blocks on a FIFO and
returns a regular file only, refusing anything else with a :class:`~warpnerf.errors.UserError`
naming the path. The readers built on it: :func:`open_input` / :func:`read_input`, the one way a
command opens a file it is given or a run holds (bounded by the bytes actually read, never by
``st_size``), and :func:`read_regular` for a file warpnerf wrote earlier. The writers of
:mod:`warpnerf.safe_writes` open through :func:`open_regular` too."""

from __future__ import annotations

import io
import os
import stat

__all__ = [
    "open_regular",
    "read_regular",
    "open_input",
    "read_input",
    "read_upto",
    "file_kind",
    "refusal",
    "user_error",
]


# open flags: no link followed, no wait on a FIFO, not inherited by child processes
NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
NONBLOCK = getattr(os, "O_NONBLOCK", 0)
CLOEXEC = getattr(os, "O_CLOEXEC", 0)


def user_error(text: str):
    """A :class:`~warpnerf.errors.UserError` (imported late: errors imports nothing here)."""
    from .errors import UserError

    return UserError(text)


def file_kind(mode: int) -> str:
    """What a non-regular file is, in words ("symbolic link", "FIFO", ...)."""
    kinds = ((stat.S_ISLNK, "symbolic link"), (stat.S_ISDIR, "folder"), (stat.S_ISFIFO, "FIFO"),
             (stat.S_ISSOCK, "socket"), (stat.S_ISCHR, "character device"),
             (stat.S_ISBLK, "block device"))  # fmt: skip
    for test, name in kinds:
        if test(mode):
            return name
    return "special file"


def refusal(path, mode: int, what: str, reading: bool = False):
    """The UserError for a link or a special file where warpnerf reads or writes its ``what``
    (``reading``: a file a command reads, :func:`open_input`)."""
    if reading:
        if stat.S_ISLNK(mode):
            return user_error(
                f"{path}: is a symbolic link; warpnerf reads its {what} without following links "
                "(put the file itself there)"
            )
        return user_error(
            f"{path}: is a {file_kind(mode)}, not a regular file; expected the {what}"
        )
    if stat.S_ISLNK(mode):
        return user_error(
            f"{path}: is a symbolic link; warpnerf does not follow links where it writes (its "
            f"{what}); remove the link or choose another output"
        )
    return user_error(
        f"{path}: is a {file_kind(mode)}, not a regular file; warpnerf refuses it as its {what} "
        "(remove it or choose another output)"
    )


def open_regular(path, flags: int, what: str, mode: int = 0o666, follow: bool = False,
          reading: bool = False) -> int:  # fmt: skip
    """``os.open`` that never follows a link at ``path`` (unless ``follow``), never blocks on a
    FIFO and returns the descriptor of a regular file only (:class:`UserError` naming ``path``
    otherwise)."""
    try:
        fd = os.open(path, flags | (0 if follow else NOFOLLOW) | NONBLOCK | CLOEXEC, mode)
    except OSError as e:
        try:
            st = os.stat(path) if follow else os.lstat(path)
        except OSError:
            raise e from None
        if not stat.S_ISREG(st.st_mode):  # ELOOP (a link), ENXIO (a FIFO without reader), ...
            raise refusal(path, st.st_mode, what, reading) from None
        raise
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise refusal(path, st.st_mode, what, reading)
    except BaseException:
        os.close(fd)
        raise
    return fd


def read_upto(fd: int, limit: int) -> bytes:
    """At most ``limit`` bytes of an open file, counted as they are read."""
    parts, n = [], 0
    while n < limit:
        b = os.read(fd, min(limit - n, 1 << 20))
        if not b:
            break
        parts.append(b)
        n += len(b)
    return b"".join(parts)


def read_regular(path, max_bytes: int, what: str = "file") -> bytes | None:
    """The bytes of ``path``, a file warpnerf wrote earlier (or the file a command is about to
    replace), read without following a link and never blocking on a FIFO; None when absent.
    :class:`UserError` naming ``path`` for a link, a special file, or more than ``max_bytes``
    bytes (read: at most ``max_bytes + 1``, whatever ``st_size`` says)."""
    try:
        fd = open_regular(path, os.O_RDONLY, what)
    except FileNotFoundError:
        return None
    try:
        data = read_upto(fd, max_bytes + 1)
    finally:
        os.close(fd)
    if len(data) > max_bytes:
        raise user_error(f"{path}: larger than {max_bytes} bytes; not a {what} warpnerf wrote "
                          "(remove it or choose another output)")  # fmt: skip
    return data


def open_input(path, what: str = "file", follow: bool = False):
    """The file ``path`` that a command reads (a file named on its command line, in a run or a
    dataset), opened for binary reading: never blocking on a FIFO, a regular file only, a link
    at ``path`` followed only when ``follow``. :class:`UserError` naming ``path`` and ``what``
    for a missing file, a link (unless ``follow``), a FIFO, device, socket or folder; other
    ``OSError`` (permissions, I/O) propagate for the caller to word."""
    try:
        fd = open_regular(path, os.O_RDONLY, what, follow=follow, reading=True)
    except FileNotFoundError:
        raise user_error(f"{path}: no such file (expected the {what})") from None
    raw = io.FileIO(fd, "rb")
    raw.name = str(path)  # (what readers' messages show, not the descriptor's number)
    return io.BufferedReader(raw)


def _size_text(n: int) -> str:
    return f"{n >> 20} MiB" if n >= 1 << 20 and not n % (1 << 20) else f"{n} bytes"


def read_input(path, what: str, max_bytes: int, follow: bool = False) -> bytes:
    """The bytes of ``path`` opened by :func:`open_input`, at most ``max_bytes`` counted as they
    are read (whatever ``st_size`` says): a larger file is a :class:`UserError` naming ``path``
    and the limit of its kind."""
    with open_input(path, what, follow) as fh:
        data = read_upto(fh.fileno(), max_bytes + 1)
    if len(data) > max_bytes:
        raise user_error(f"{path}: larger than {_size_text(max_bytes)}, the most a {what} "
                          "holds; not a file of this kind")  # fmt: skip
    return data
