"""Files warpnerf writes into run and output folders, which may hold anything: a run folder is
downloaded, unpacked and shared, so a name where warpnerf writes may be a symbolic link, a FIFO
or a device. Every file and folder the program creates or updates there is opened without
following links (``O_NOFOLLOW``; ``O_EXCL`` where it creates), special files (FIFOs, devices,
sockets) are refused with a :class:`~warpnerf.errors.UserError` naming the path (a FIFO is opened
with ``O_NONBLOCK`` before ``fstat``, so it cannot hang a command), and every read of a file
warpnerf wrote earlier is bounded by the bytes actually read, never by ``st_size``.

- :func:`atomic_path`: an output is written to a temporary name beside its target (created with
  ``O_EXCL | O_NOFOLLOW``), flushed, and renamed onto the target only when the target is absent or
  a regular file warpnerf wrote (or, for the file named on the command line, any regular file or
  a link, which is replaced, never written through). An interrupted write leaves the previous
  complete file or the new complete one; a SIGKILL mid-write can leave the hidden temporary file
  (``.NAME.XXXXXXXX.SUFFIX``), never a partial target.
- The manifest (:data:`MANIFEST`): per folder, an append-only log of the files warpnerf wrote, one
  JSON record ``["name", size, mtime_ns]`` per line (a file counts as warpnerf's while it still
  has the recorded size and time). A record is one ``O_APPEND`` write, so recording costs the same
  in a folder of 30,000 outputs as in an empty one; the log is rewritten without stale records
  when it has doubled since it was last read or rewritten (so its size stays proportional to the
  live outputs). Manifests of earlier versions (one JSON object ``{name: [size, mtime_ns]}``) are
  read as well and appended to. Records are not fsynced one by one: a record lost in a power cut
  only makes its file count as foreign (refused, never deleted).
- The folder lock (:data:`LOCK`, :func:`output_lock`; :func:`lock_holder` probes it; the lock
  file is removed when its holder ends) and the folders warpnerf makes inside a run
  (:func:`make_folder`: ``eval_*``, ``render_*``, ``snapshots``, export's ``images``), checked with
  ``lstat`` to be real folders.

Reading (:mod:`warpnerf.safe_open`, re-exported here): :func:`open_input` /
:func:`read_input` are the one way a command opens a file it is
given or a run holds (run configs, checkpoints, run records, camera paths, SDF scenes, dataset
indexes, images, COLMAP models, arrays): non-blocking (a FIFO is refused, never waited on), a
regular file only (a device, socket or folder is refused by name), no link followed unless the
caller asks (files named by the user and dataset files, whose links are checked by their
loaders), and :func:`read_input` bounded by the bytes actually read.

The threat is a folder prepared in advance (an archive), not a process racing the program on the
same machine: paths are checked, then used by name (writers such as ffmpeg and ``torch.save``
need a path).
"""

from __future__ import annotations

import contextlib
import json
import os
import stat
import tempfile
import threading
from pathlib import Path

from .safe_open import (
    CLOEXEC,
    NOFOLLOW,
    NONBLOCK,
    file_kind,
    open_input,
    open_regular,
    read_input,
    read_regular,
    read_upto,
    refusal,
    user_error,
)

__all__ = [
    "MANIFEST",
    "LOCK",
    "atomic_path",
    "owned_files",
    "record",
    "adopt",
    "check_foreign",
    "remove_own",
    "output_lock",
    "lock_holder",
    "make_folder",
    "read_regular",
    "open_input",
    "read_input",
]

MANIFEST = ".warpnerf-files.json"  # per folder: the files warpnerf wrote there (a JSON-lines log)
LOCK = ".warpnerf.lock"  # per output folder: held (flock) by the process writing into it
_MANIFEST_MAX_BYTES = 1 << 28  # 256 MiB: about 3 million records
_COMPACT_MIN_BYTES = 1 << 20  # the log is never rewritten below this size


def _create_temp(folder: Path, prefix: str, suffix: str = "") -> tuple[int, str]:
    """A new file ``folder/PREFIX<random>SUFFIX``: (descriptor open for writing, its path).
    ``tempfile.mkstemp`` opens it with ``O_CREAT | O_EXCL | O_NOFOLLOW``; its mode becomes the
    usual 0o666 less the umask (mkstemp makes 0o600)."""
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=folder)
    try:
        os.chmod(tmp, 0o666 & ~_umask())
    except BaseException:
        os.close(fd)
        os.remove(tmp)
        raise
    return fd, tmp


_UMASK: list = []


def _umask() -> int:
    """The process's umask, read once (reading it means setting it: not done per file, where
    another thread could create a file meanwhile)."""
    if not _UMASK:
        mask = os.umask(0o022)
        os.umask(mask)
        _UMASK.append(mask)
    return _UMASK[0]


def make_folder(path, what: str = "output folder") -> Path:
    """Creates ``path``, a folder warpnerf makes inside a run or output folder (``eval_val``,
    ``render_spiral``, ``snapshots``; its parents as needed), and checks with ``lstat`` that it is
    a real folder: a link to another folder (a whole render written elsewhere) or a file there is
    a :class:`UserError`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with contextlib.suppress(FileExistsError):
        os.mkdir(path)
    st = os.lstat(path)
    if stat.S_ISLNK(st.st_mode):
        raise user_error(f"{path}: is a symbolic link; warpnerf writes its {what} only into a "
                          "real folder (remove the link or choose another output)")  # fmt: skip
    if not stat.S_ISDIR(st.st_mode):
        raise user_error(f"{path}: exists and is a {file_kind(st.st_mode)}, not a folder; move it "
                          "away or choose another output")  # fmt: skip
    return path


# --- the manifest -----------------------------------------------------------------------------


def _plain_name(name: str) -> bool:
    return name not in ("", ".", "..") and "/" not in name and "\\" not in name and "\0" not in name


def _valid(name, stamp) -> bool:
    return (isinstance(name, str) and _plain_name(name) and isinstance(stamp, list)
            and len(stamp) == 2 and all(type(x) is int for x in stamp))  # fmt: skip


def _parse(data: bytes) -> dict:
    """{name: [size, mtime_ns]} of a manifest's text: records ``["name", size, mtime_ns]`` one a
    line (later ones win) and objects ``{name: [size, mtime_ns]}`` (the earlier format); anything
    malformed is skipped (the manifest is untrusted: it can only narrow what is warpnerf's)."""
    entries = {}
    text = data.decode("utf-8", errors="replace")
    try:  # the earlier format: one object, possibly over several lines
        whole = json.loads(text) if text.lstrip().startswith("{") else None
    except (ValueError, RecursionError):
        whole = None
    lines = [whole] if isinstance(whole, dict) else text.split("\n")
    for line in lines:
        if isinstance(line, str):
            if not line.strip():
                continue
            try:
                line = json.loads(line)
            except (ValueError, RecursionError):
                continue
        if isinstance(line, list) and len(line) == 3:
            line = {line[0]: line[1:]} if isinstance(line[0], str) else {}
        if isinstance(line, dict):
            entries.update((n, s) for n, s in line.items() if _valid(n, s))
    return entries


class _Cached:
    """A folder's manifest as last read or written by this process: ``ident`` (device, inode,
    size, mtime) says whether the file on disk is still that one."""

    def __init__(self, ident, entries: dict, base: int):
        self.ident, self.entries, self.base = ident, entries, base


_CACHE: dict = {}
_LOCK = threading.RLock()  # the cache and the appends (a checkpoint written by a thread)


def _ident(st) -> tuple:
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def _entries(folder: Path) -> dict:
    """{name: [size, mtime_ns]} of ``folder``'s manifest ({} when absent); read again only when
    the file changed since this process last read or wrote it. :class:`UserError` for a link, a
    special file or a manifest over :data:`_MANIFEST_MAX_BYTES`."""
    p = folder / MANIFEST
    key = os.path.abspath(folder)
    with _LOCK:
        try:
            st = os.lstat(p)
        except (FileNotFoundError, NotADirectoryError):
            _CACHE.pop(key, None)
            return {}
        c = _CACHE.get(key)
        if c is not None and c.ident == _ident(st):
            return c.entries
        fd = open_regular(p, os.O_RDONLY, "manifest")
        try:
            st = os.fstat(fd)
            data = read_upto(fd, _MANIFEST_MAX_BYTES + 1)
        finally:
            os.close(fd)
        if len(data) > _MANIFEST_MAX_BYTES:
            raise user_error(
                f"{p}: the manifest is larger than {_MANIFEST_MAX_BYTES} bytes, which warpnerf "
                "never writes; remove it (warpnerf then treats the folder's files as not its own)"
            )
        entries = _parse(data)
        _CACHE[key] = _Cached(_ident(st), entries, st.st_size)
        return entries


def _stamp_of(path: Path):
    """[size, mtime_ns] of a regular file (not a link), else None."""
    try:
        st = os.lstat(path)
    except OSError:
        return None
    return [st.st_size, st.st_mtime_ns] if stat.S_ISREG(st.st_mode) else None


def owned_files(folder, names=None) -> set:
    """Names of the files warpnerf wrote in ``folder`` and nobody changed since (of ``names``
    only, when given): the :data:`MANIFEST` records each file's size and modification time at
    the write, and a file replaced, edited or turned into a link afterwards no longer counts as
    warpnerf's. The manifest is untrusted like the rest of a run folder: only plain file names
    (no separators, no ``..``) count, so it can never widen what is deleted or replaced beyond
    files of that folder."""
    folder = Path(folder)
    entries = _entries(folder)
    pick = entries if names is None else [n for n in names if n in entries]
    return {n for n in pick if _stamp_of(folder / n) == entries[n]}


def record(path) -> None:
    """Records ``path`` (a regular file warpnerf just wrote) in its folder's manifest: one line
    appended (``O_APPEND | O_NOFOLLOW``); the log is rewritten without stale records once it has
    doubled (and passed :data:`_COMPACT_MIN_BYTES`) since it was last read or rewritten."""
    path = Path(path)
    stamp = _stamp_of(path)
    if path.name == MANIFEST or stamp is None or not _plain_name(path.name):
        return
    folder, line = path.parent, (json.dumps([path.name, *stamp]) + "\n").encode()
    key = os.path.abspath(folder)
    with _LOCK:
        _entries(folder)  # (refuses a planted manifest; fills the cache)
        fd = open_regular(folder / MANIFEST, os.O_RDWR | os.O_APPEND | os.O_CREAT, "manifest")
        try:
            before = os.fstat(fd)
            if before.st_size and _last_byte(fd, before.st_size) != b"\n":
                line = b"\n" + line  # (an earlier version's manifest ends without one)
            while line:
                line = line[os.write(fd, line) :]
            after = os.fstat(fd)
        finally:
            os.close(fd)
        c = _CACHE.get(key)
        if c is not None and c.ident[:3] == _ident(before)[:3]:  # nobody else wrote meanwhile
            c.entries[path.name] = stamp
            c.ident = _ident(after)
        else:
            _CACHE.pop(key, None)
            c = None
        base = c.base if c is not None else before.st_size
        if after.st_size > max(_COMPACT_MIN_BYTES, 2 * base):
            _compact(folder)


def _last_byte(fd: int, size: int) -> bytes:
    if hasattr(os, "pread"):
        return os.pread(fd, 1, size - 1)
    os.lseek(fd, size - 1, os.SEEK_SET)
    return os.read(fd, 1)


def _compact(folder: Path) -> None:
    """Rewrites ``folder``'s manifest with one record per file that is still warpnerf's
    (atomically: a temporary file fsynced, then renamed over the manifest)."""
    entries = _entries(folder)
    live = {n: s for n, s in entries.items() if _stamp_of(folder / n) == s}
    text = "".join(json.dumps([n, *s]) + "\n" for n, s in live.items()).encode()
    fd, tmp = _create_temp(folder, f"{MANIFEST}.")
    try:
        try:
            while text:
                text = text[os.write(fd, text) :]
            os.fsync(fd)
        finally:
            os.close(fd)
        _check_replaceable(folder / MANIFEST, "manifest")
        os.replace(tmp, folder / MANIFEST)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise
    st = os.lstat(folder / MANIFEST)
    _CACHE[os.path.abspath(folder)] = _Cached(_ident(st), live, st.st_size)


def adopt(folder, names) -> None:
    """Records ``names`` (those that are regular files) as warpnerf's in ``folder``'s manifest:
    the files of a run that the user resumes, written before manifests existed."""
    for name in names:
        if _plain_name(name):
            record(Path(folder) / name)


def check_foreign(paths) -> None:
    """:class:`UserError` if any of ``paths`` exists and was not written by warpnerf (is not in
    its folder's manifest, or is a link or a special file): commands replace only their own
    files. Called with every target before the work starts, so that a refusal costs nothing
    (each folder's manifest is read once, and refused there and then if it is a link, a special
    file or oversized, even when no target exists yet)."""
    by_folder: dict = {}
    for p in map(Path, paths):
        by_folder.setdefault(p.parent, []).append(p.name)
    for folder, names in by_folder.items():
        present = [n for n in names if os.path.lexists(folder / n)]
        owned = owned_files(folder, present)
        for n in present:
            if n not in owned:
                raise user_error(
                    f"{folder / n}: exists and was not written by warpnerf; refusing to replace "
                    "it (move it away or choose another output)"
                )


def remove_own(folder, names) -> list:
    """Removes those of ``names`` in ``folder`` that warpnerf wrote there (listed in its
    manifest, unchanged, regular files); any other file is left alone. Returns the names
    removed."""
    folder = Path(folder)
    names = [n for n in names if _plain_name(n)]
    owned, gone = owned_files(folder, names), []
    for name in names:
        if name in owned:
            os.unlink(folder / name)
            gone.append(name)
    return gone


# --- the folder lock --------------------------------------------------------------------------


_HELD: dict = {}
_LOCK_TRIES = 50  # opens of a lock file that its holder removed meanwhile, before giving up
_BUSY_TRIES = 5  # tries of a held lock, _BUSY_WAIT apart (a probe holds it for microseconds)
_BUSY_WAIT = 0.02


@contextlib.contextmanager
def output_lock(folder, what: str = "output folder"):
    """Holds an exclusive lock on ``folder`` (its :data:`LOCK` file, created if needed, never
    through a link, a regular file with one name only) for the block: a second process writing
    into the same folder gets a :class:`UserError` naming the holder's pid instead of mixing two
    runs' files. The lock is the OS's (``flock``): it is released on every exit path, a crash or
    SIGKILL included, so a lock file left by a dead process is stale by construction and simply
    taken over. At the end of the block (refused or finished) the lock file is removed while it
    is still held, if it is still the file this process locked, and so is ``folder`` when this
    call made it and it is empty: a refusal leaves nothing behind. A locker checks, once it holds
    the lock, that the file it locked is still the one in the folder (a holder that finished
    may have removed it meanwhile) and otherwise locks the one there now. Re-entrant within one
    process."""
    folder = Path(folder)
    key = str(folder.resolve())
    if key in _HELD:
        _HELD[key] += 1
        try:
            yield
        finally:
            _HELD[key] -= 1
        return
    path = folder / LOCK
    made = False
    for _ in range(_LOCK_TRIES):
        made = _make_lock_folder(folder) or made
        fd = _open_lock(path, what, folder)
        if fd is not None:
            break
    else:
        raise user_error(f"{path}: the lock file keeps disappearing (removed by another "
                          "process as it is opened); try again")  # fmt: skip
    try:
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, f"{os.getpid()}\n".encode())
        _HELD[key] = 1
        yield
    finally:
        _HELD.pop(key, None)
        try:
            if _same_file(fd, path):  # (never a file that replaced ours: only ours goes)
                os.unlink(path)  # still held: a process that opened it finds it gone, retries
        except OSError:  # (Windows: an open file cannot be removed; it stays, stale)
            pass
        finally:
            os.close(fd)  # closing the descriptor releases the lock
        if made:
            with contextlib.suppress(OSError):  # (only when empty: nothing of anyone's goes)
                os.rmdir(folder)


def _make_lock_folder(folder: Path) -> bool:
    """Makes ``folder`` (and its parents) if missing; whether this call made ``folder`` itself."""
    try:
        os.mkdir(folder)
    except FileExistsError:
        return False
    except FileNotFoundError:
        folder.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.mkdir(folder)
        except FileExistsError:
            return False
    return True


def _same_file(fd: int, path: Path) -> bool:
    """Whether ``path`` (not followed if a link) is the open file ``fd``."""
    try:
        st = os.lstat(path)
    except OSError:
        return False
    held = os.fstat(fd)
    return (st.st_dev, st.st_ino) == (held.st_dev, held.st_ino) and stat.S_ISREG(st.st_mode)


def _open_lock(path: Path, what: str, folder: Path) -> int | None:
    """The descriptor of the lock file ``path``, opened (created if needed) and locked; None
    when the file it locked is no longer the one in the folder (its holder removed it as it was
    opened: try again). :class:`UserError` when another process holds it."""
    try:
        fd = open_regular(path, os.O_RDWR | os.O_CREAT, "lock file", 0o644)
    except FileNotFoundError:  # the folder went (an empty one removed by its last holder)
        return None
    except OSError as e:
        raise user_error(f"{path}: cannot create the lock file ({e.strerror or e})") from None
    try:
        links = os.fstat(fd).st_nlink
        if links > 1:  # a hard link to a file elsewhere: never truncated
            raise user_error(f"{path}: the lock file has other names (hard links); warpnerf "
                              "refuses to write it (remove it)")  # fmt: skip
        for busy in range(_BUSY_TRIES):
            try:
                _try_lock(fd)
                break
            except BlockingIOError:
                if busy + 1 == _BUSY_TRIES:
                    os.lseek(fd, 0, os.SEEK_SET)
                    holder = os.read(fd, 64).decode(errors="replace").strip() or "?"
                    raise user_error(
                        f"{folder}: this {what} is in use by another warpnerf process (pid "
                        f"{holder}); wait for it to finish or choose another output"
                    ) from None
                import time

                time.sleep(_BUSY_WAIT)  # (a reader's probe of the lock: lock_holder)
        if not _same_file(fd, path):  # removed (or replaced) before we locked it
            os.close(fd)
            return None
    except BaseException:
        with contextlib.suppress(OSError):
            os.close(fd)
        raise
    return fd


def lock_holder(folder) -> str | None:
    """The pid (as the lock file says it) of another process holding ``folder``'s lock (a
    training holds its run folder's), or None when nobody else holds it. A probe: a shared lock
    taken without waiting and given back at once (a writer that meets it tries again), never the
    lock file created; a link or a special file in its place counts as no lock."""
    folder = Path(folder)
    with contextlib.suppress(OSError):
        if str(folder.resolve()) in _HELD:
            return None
    from .errors import UserError

    try:
        fd = open_regular(folder / LOCK, os.O_RDONLY, "lock file")
    except (OSError, UserError):  # absent, a link, a special file, unreadable
        return None
    try:
        try:
            import fcntl
        except ImportError:  # Windows: no probe
            return None
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return os.read(fd, 64).decode(errors="replace").strip() or "?"
        except OSError:
            return None
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def _try_lock(fd: int) -> None:
    """Non-blocking exclusive lock of an open file; BlockingIOError when another process holds
    it."""
    try:
        import fcntl
    except ImportError:  # Windows
        import msvcrt

        try:
            msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
        except OSError:
            raise BlockingIOError from None
        return
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)


# --- atomic outputs ---------------------------------------------------------------------------


def _check_replaceable(path: Path, what: str = "output") -> None:
    """:class:`UserError` unless ``path`` is absent, a regular file or a link (a rename
    replaces the link itself): never a folder or a special file."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    if not (stat.S_ISREG(st.st_mode) or stat.S_ISLNK(st.st_mode)):
        raise refusal(path, st.st_mode, what)


@contextlib.contextmanager
def atomic_path(path, replace_foreign: bool = False):
    """Yields a temporary path next to ``path`` (same suffix; created with ``O_EXCL |
    O_NOFOLLOW``); when the block succeeds the file is fsynced and renamed onto ``path`` (then
    the folder is fsynced, so the rename survives a power cut) and recorded in the folder's
    manifest; when it raises (any exception, KeyboardInterrupt included) the file is removed. An
    existing ``path`` that warpnerf did not write (a link, a special file, another program's
    file) is never replaced (:class:`UserError`, checked before the block and again just before
    the rename) unless ``replace_foreign`` (a file the user named explicitly, such as ``mesh
    --out FILE``: a regular file, or a link, which is replaced and never written through)."""
    path = Path(path)

    def check():
        if replace_foreign:
            _check_replaceable(path)
            _entries(path.parent)  # (a planted manifest: refused before the write)
        else:
            check_foreign([path])

    check()
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = _create_temp(path.parent, f".{path.stem}.", path.suffix)
    os.close(fd)
    try:
        yield tmp
        _fsync(tmp)
        check()
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise
    record(path)
    _fsync(path.parent)


def _fsync(path) -> None:
    """Flushes a file's data to disk (best effort: a folder cannot be opened on every OS)."""
    try:
        fd = os.open(path, os.O_RDONLY | NOFOLLOW | NONBLOCK | CLOEXEC)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
