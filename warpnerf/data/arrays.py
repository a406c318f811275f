"""Arrays read from untrusted ``.npz`` / ``.npy`` files (point clouds, LLFF ``poses_bounds.npy``)
with bounded inflation and no pickles: zip directories and ``.npy`` headers are checked against
the file's size before anything is inflated or allocated."""

from __future__ import annotations

import math
import os
import zipfile
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..outputs import check_overlap, open_input, zip_directory

__all__ = ["load_npz", "load_npy", "inflate_limit", "INFLATE_ENV"]

INFLATE_ENV = "WARPNERF_MAX_INFLATE"  # bytes a compressed input may inflate to (overrides)
INFLATE_MIN = 256 << 20  # at least this much, whatever the file's size
INFLATE_RATIO = 32  # else this many times the file's size


def inflate_limit(file_size: int) -> int:
    """Bytes a compressed input file (an ``.npz``) may inflate to: ``$WARPNERF_MAX_INFLATE`` when
    set (an integer), else ``max(256 MiB, 32 x file_size)``. Real data compresses by a few times
    at most; a zip bomb of zeros by a thousand."""
    env = os.environ.get(INFLATE_ENV)
    if env:
        try:
            return int(env)
        except ValueError:
            raise UserError(f"{INFLATE_ENV}={env!r}: expected a number of bytes") from None
    return max(INFLATE_MIN, INFLATE_RATIO * file_size)


def load_npz(path, what: str = "file") -> dict:
    """Every array of an ``.npz`` file (``np.savez`` or ``np.savez_compressed``), with bounded
    inflation and no pickles: the zip directory is read first, and the members' declared sizes
    together must stay within :func:`inflate_limit` of the file's size (nothing is inflated
    beyond a member's declared size), no members may overlap, and each member's ``.npy`` header
    must declare no more data than the member holds, before its array is allocated. Object
    arrays (pickles) are refused. A :class:`UserError` naming ``path``, the member and the limit
    otherwise."""
    path = Path(path)
    try:
        fh = open_input(path, what, follow=True)  # (a FIFO or device: refused, never waited on)
    except OSError as e:
        raise UserError(f"{path}: unreadable {what} ({type(e).__name__}: {e})") from None
    with fh:
        return _load_npz(path, fh, what)


def _load_npz(path: Path, fh, what: str) -> dict:
    size = os.fstat(fh.fileno()).st_size
    if not zipfile.is_zipfile(fh):
        raise UserError(f"{path}: unreadable {what} (not an .npz zip file)")
    infos = zip_directory(path, what, fh)
    check_overlap(path, infos, size)
    limit, total = inflate_limit(size), sum(i.file_size for i in infos)
    if total > limit:
        big = max(infos, key=lambda i: i.file_size)
        raise UserError(
            f"{path}: refused: its members would inflate to {total} bytes ({big.filename!r}: "
            f"{big.file_size}), beyond the limit of {limit} for a file of {size} bytes (a "
            f"decompression bomb? set {INFLATE_ENV}=BYTES to raise the limit)"
        )
    out = {}
    try:
        with zipfile.ZipFile(fh) as z:
            for info in infos:
                if info.is_dir():
                    continue
                name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
                with z.open(info) as f:
                    out[name] = _read_npy(f, info.file_size, f"{path}: member {info.filename!r}")
    except UserError:
        raise
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as e:
        raise UserError(f"{path}: unreadable {what} ({type(e).__name__}: {e})") from None
    return out


def load_npy(path, what: str = "file") -> np.ndarray:
    """The array of an ``.npy`` file, its header checked before anything is allocated: the shape
    and dtype must declare no more bytes than the file holds; no pickles (object arrays)."""
    path = Path(path)
    try:
        with open_input(path, what, follow=True) as f:
            return _read_npy(f, os.fstat(f.fileno()).st_size, str(path))
    except UserError:
        raise
    except (OSError, ValueError, EOFError) as e:
        raise UserError(f"{path}: unreadable {what} ({type(e).__name__}: {e})") from None


def _read_npy(f, available: int, where: str) -> np.ndarray:
    """One ``.npy`` stream of at most ``available`` bytes (header included)."""
    from numpy.lib import format as npf

    try:
        version = npf.read_magic(f)
        header = {(1, 0): npf.read_array_header_1_0, (2, 0): npf.read_array_header_2_0}
        if version not in header:
            raise ValueError(f"npy format version {version} is not supported")
        shape, fortran, dtype = header[version](f)
    except (ValueError, SyntaxError) as e:
        raise UserError(f"{where}: not a readable .npy array ({e})") from None
    if dtype.hasobject:
        raise UserError(f"{where}: refused: an object array (a pickle); only plain arrays load")
    if any(type(n) is not int or n < 0 for n in shape):
        raise UserError(f"{where}: not a readable .npy array (shape {shape})")
    nbytes = math.prod(shape) * dtype.itemsize
    if nbytes > available:
        raise UserError(
            f"{where}: refused: its header declares shape {list(shape)} of {dtype} "
            f"({nbytes} bytes) but it holds at most {available} bytes"
        )
    buf = bytearray(nbytes)
    view, got = memoryview(buf), 0
    while got < nbytes:
        n = f.readinto(view[got:])
        if not n:
            raise UserError(f"{where}: truncated ({got} of {nbytes} bytes of array data)")
        got += n
    arr = np.frombuffer(buf, dtype=dtype)
    return arr.reshape(shape, order="F" if fortran else "C")
