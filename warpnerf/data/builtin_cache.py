"""A content-addressed disk cache of generated arrays (the built-in scene's images), shared by
every process of the user: made once, read by later commands instead of being made again.

An entry is one uncompressed ``.npz`` file named by the SHA-256 of its key (everything that
determines the arrays: the generator's parameters and a version of its code). It holds the arrays
and a ``meta`` member (JSON: the key and the SHA-256 of each array's bytes).

The cache folder is untrusted input: a file is read through a descriptor opened without following
a symlink (and not blocking on a FIFO), only when it is a regular file no larger than the key
implies; only stored (uncompressed) members of the expected names are read, never a pickle; each
array must have the shape and dtype the caller expects, finite values in its range and the
checksum the ``meta`` records for it, and ``meta`` must name the same key. Anything else is a
miss: the arrays are made again and the entry replaced. Entries are written to a temporary file
in the folder, fsynced and renamed onto their name, so a reader never sees a half-written file and
two processes making the same entry at once both end with a valid one. When the folder cannot be
written (read-only, full disk) the arrays are still returned, with one line of note on stderr.

The folder: ``$WARPNERF_CACHE`` when set (``off``, ``0``, ``no``, ``false`` or ``none``: no
cache), else ``$XDG_CACHE_HOME/warpnerf``, else ``~/.cache/warpnerf``.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import os
import sys
import tempfile
import zipfile
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

__all__ = ["ENV", "cache_dir", "entry_path", "cached_arrays", "read_entry", "write_entry"]

ENV = "WARPNERF_CACHE"
_OFF = {"off", "0", "no", "false", "none"}
_FORMAT = 1  # of the entry file; part of every key
_META_MAX = 1 << 16  # bytes of the meta member at most
_SLACK = 1 << 16  # zip and .npy headers on top of the arrays' bytes
_noted: set = set()

# {array name: (shape, dtype, lowest value, highest value)}; None bounds: any finite value
Spec = Mapping[str, tuple]


def cache_dir() -> Path | None:
    """The cache folder, or None when ``$WARPNERF_CACHE`` turns the cache off."""
    env = os.environ.get(ENV, "").strip()
    if env.lower() in _OFF:
        return None
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    base = Path(xdg) if os.path.isabs(xdg) else Path.home() / ".cache"
    return base / "warpnerf"


def _key_json(name: str, key: Mapping) -> str:
    return json.dumps({"entry": name, "format": _FORMAT, "key": key}, sort_keys=True)


def entry_path(folder: Path, name: str, key: Mapping) -> Path:
    """The file of the entry ``name`` with ``key`` (a JSON-able mapping) in ``folder``."""
    digest = hashlib.sha256(_key_json(name, key).encode()).hexdigest()
    return Path(folder) / f"{name}-{digest[:40]}.npz"


def _nbytes(spec: Spec) -> int:
    return sum(math.prod(s) * np.dtype(dt).itemsize for s, dt, *_ in spec.values())


def _read_bounded(path: Path, limit: int) -> bytes | None:
    """The bytes of ``path`` when it is a regular file (not a symlink, FIFO, device, folder) of at
    most ``limit`` bytes; None otherwise or when it cannot be read
    (:func:`~warpnerf.safe_writes.read_input`)."""
    from ..errors import UserError
    from ..safe_writes import read_input

    try:
        return read_input(path, "cache entry", limit)
    except (UserError, OSError):  # absent, a symlink, a special file, too large, unreadable
        return None


def _parse(data: bytes, name: str, key: Mapping, spec: Spec) -> dict | None:
    """The arrays of an entry file's bytes when everything checks out, else None."""
    expected = {f"{k}.npy" for k in spec} | {"meta.npy"}
    limits = {f"{k}.npy": _nbytes({k: v}) + _SLACK for k, v in spec.items()}
    limits["meta.npy"] = _META_MAX + _SLACK
    buf = io.BytesIO(data)
    with zipfile.ZipFile(buf) as zf:
        infos = zf.infolist()
        if len(infos) != len(expected) or {i.filename for i in infos} != expected:
            return None
        for i in infos:  # stored members only (no decompression bomb), of bounded size
            if i.compress_type != zipfile.ZIP_STORED or i.file_size > limits[i.filename]:
                return None
    with np.load(io.BytesIO(data), allow_pickle=False) as npz:
        raw = npz["meta"]
        if raw.dtype != np.uint8 or raw.ndim != 1 or raw.size > _META_MAX:
            return None
        meta = json.loads(raw.tobytes().decode("utf-8"))
        if not isinstance(meta, dict) or meta.get("key") != json.loads(_key_json(name, key)):
            return None
        sums = meta.get("sha256")
        if not isinstance(sums, dict):
            return None
        out = {}
        for k, (shape, dtype, lo, hi) in spec.items():
            a = npz[k]
            if a.dtype != np.dtype(dtype) or a.shape != tuple(shape):
                return None
            if a.dtype.kind == "f" and a.size and not np.isfinite(a).all():
                return None
            if a.size and (lo is not None and a.min() < lo or hi is not None and a.max() > hi):
                return None
            if sums.get(k) != hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest():
                return None
            out[k] = a
    return out


def read_entry(folder: Path, name: str, key: Mapping, spec: Spec) -> dict | None:
    """The arrays of the entry ``name``/``key`` in ``folder`` when present and valid against
    ``spec``; None on a miss (absent, unreadable, not a regular file, too large, malformed,
    tampered with)."""
    limit = _nbytes(spec) + len(spec) * _SLACK + _META_MAX + 2 * _SLACK
    data = _read_bounded(entry_path(folder, name, key), limit)
    if data is None:
        return None
    try:
        return _parse(data, name, key, spec)
    except Exception:  # noqa: BLE001  (untrusted bytes: any failure to parse them is a miss)
        return None


def write_entry(folder: Path, name: str, key: Mapping, arrays: Mapping) -> Path:
    """Writes the entry atomically (temporary file in ``folder``, fsync, rename; a symlink or
    special file in its place is replaced, never written through). Raises OSError when the
    folder cannot be written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = entry_path(folder, name, key)
    arrays = {k: np.ascontiguousarray(a) for k, a in arrays.items()}
    meta = {
        "key": json.loads(_key_json(name, key)),
        "sha256": {k: hashlib.sha256(a.tobytes()).hexdigest() for k, a in arrays.items()},
    }
    raw = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, meta=raw, **arrays)  # uncompressed members
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)  # (mode 0600 from mkstemp: a per-user cache)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise
    with contextlib.suppress(OSError):  # the rename survives a power cut (best effort)
        dfd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    return path


def _note(folder: Path, err: OSError) -> None:
    if str(folder) not in _noted:
        _noted.add(str(folder))
        why = err.strerror or type(err).__name__
        print(f"warpnerf: note: cache {folder} not writable ({why}); made in memory",
              file=sys.stderr)  # fmt: skip


def cached_arrays(
    name: str, key: Mapping, spec: Spec, make: Callable[[], Mapping]
) -> dict[str, np.ndarray]:
    """The arrays of ``make()``, from the cache when a valid entry for ``key`` is there, else
    made and stored (when the cache is on and its folder writable).

    Args:
        name: the entry's kind (a plain file-name prefix, e.g. "builtin").
        key: a JSON-able mapping of everything that determines the arrays.
        spec: {array name: (shape, dtype, lowest, highest)} the entry must match.
        make: makes the arrays ({name: array}, the names and shapes of ``spec``).

    Returns:
        {name: np.ndarray} (fresh, writable arrays).
    """
    folder = cache_dir()
    if folder is not None:
        hit = read_entry(folder, name, key, spec)
        if hit is not None:
            return hit
    arrays = {k: np.asarray(a) for k, a in make().items()}
    if folder is not None:
        try:
            write_entry(folder, name, key, arrays)
        except OSError as e:
            _note(folder, e)
    return arrays
