"""Atomic output writers: every file is written to a temporary name in its folder, flushed to disk,
then renamed onto its target, so an interrupted run (an exception, a signal, a killed process, a
full disk) never leaves a half-written image, video, mesh, checkpoint or metrics file: the target
is the previous complete file or the new complete one. A process killed outright in the middle of
a write (SIGKILL, or a signal without a Python handler) can leave the hidden temporary file
(``.NAME.XXXXXXXX.SUFFIX``) behind, never a partial target."""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
import threading
from pathlib import Path

import numpy as np

__all__ = [
    "atomic_path",
    "MANIFEST",
    "LOCK",
    "owned_files",
    "adopt",
    "check_foreign",
    "remove_own",
    "output_lock",
    "json_safe",
    "json_dumps",
    "write_json",
    "save_checkpoint",
    "load_checkpoint",
    "load_weights",
    "write_image",
    "write_video",
    "to_uint8",
    "depth_to_uint8",
]


MANIFEST = ".warpnerf-files.json"  # per folder: the names of the files warpnerf wrote there
LOCK = ".warpnerf.lock"  # per output folder: held (flock) by the process writing into it
_MANIFEST_MAX_BYTES = 1 << 20


def _stamp(path: Path):
    st = path.stat()
    return [st.st_size, st.st_mtime_ns]


def _read_manifest(folder) -> dict:
    """{name: [size, mtime_ns]} of a folder's manifest; {} when absent or malformed."""
    p = Path(folder) / MANIFEST
    try:
        if p.stat().st_size > _MANIFEST_MAX_BYTES:
            return {}
        data = json.loads(p.read_text())
    except (OSError, ValueError, RecursionError):
        return {}
    if not isinstance(data, dict):
        return {}
    return {
        n: v
        for n, v in data.items()
        if isinstance(n, str) and _plain_name(n) and isinstance(v, list) and len(v) == 2
        and all(type(x) is int for x in v)
    }  # fmt: skip


def owned_files(folder) -> set:
    """Names of the files warpnerf wrote in ``folder`` and nobody changed since: its
    :data:`MANIFEST` records each file's size and modification time at the write, and a file
    replaced or edited afterwards no longer counts as warpnerf's. The manifest is untrusted like
    the rest of a run folder: anything but a JSON object of plain file names (no separators, no
    ``..``) of bounded size reads as empty, so it can never widen what is deleted or replaced
    beyond files of that folder."""
    folder = Path(folder)
    owned = set()
    for name, stamp in _read_manifest(folder).items():
        p = folder / name
        try:
            if not p.is_symlink() and p.is_file() and _stamp(p) == stamp:
                owned.add(name)
        except OSError:
            continue
    return owned


def _plain_name(name: str) -> bool:
    return name not in ("", ".", "..") and "/" not in name and "\\" not in name and "\0" not in name


_MANIFEST_LOCK = threading.Lock()  # (a checkpoint written by a thread, a viewer's path file)


def _record(path: Path) -> None:
    """Records ``path`` (size and modification time) in its folder's manifest, atomically (and
    one thread at a time: the read-modify-write would lose another thread's entry)."""
    if path.name == MANIFEST:
        return
    with _MANIFEST_LOCK:
        _record_locked(path)


def _record_locked(path: Path) -> None:
    entries = _read_manifest(path.parent)
    entries = {n: v for n, v in entries.items() if (path.parent / n).exists()}  # prune
    entries[path.name] = _stamp(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{MANIFEST}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(entries, f)
        os.replace(tmp, path.parent / MANIFEST)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def adopt(folder, names) -> None:
    """Records ``names`` (those that exist) as warpnerf's in ``folder``'s manifest: the files of a
    run that the user resumes, written before manifests existed."""
    for name in names:
        p = Path(folder) / name
        if _plain_name(name) and p.is_file() and not p.is_symlink():
            _record(p)


def check_foreign(paths) -> None:
    """:class:`UserError` if any of ``paths`` exists and was not written by warpnerf (is not in
    its folder's manifest): commands replace only their own files. Called before the work starts
    so that a refusal costs nothing."""
    from .errors import UserError

    for p in map(Path, paths):
        if (p.exists() or p.is_symlink()) and p.name not in owned_files(p.parent):
            raise UserError(
                f"{p}: exists and was not written by warpnerf; refusing to replace it "
                "(move it away or choose another output)"
            )


def remove_own(folder, names) -> list:
    """Removes those of ``names`` in ``folder`` that warpnerf wrote there (listed in its
    manifest); any other file is left alone. Returns the names removed."""
    folder = Path(folder)
    owned, gone = owned_files(folder), []
    for name in names:
        if name in owned and _plain_name(name):
            p = folder / name
            if p.is_file() and not p.is_symlink():
                p.unlink()
                gone.append(name)
    return gone


@contextlib.contextmanager
def output_lock(folder, what: str = "output folder"):
    """Holds an exclusive lock on ``folder`` (its :data:`LOCK` file, created if needed) for the
    block: a second process writing into the same folder gets a :class:`UserError` naming the
    holder's pid instead of mixing two runs' files. The lock is the OS's (``flock``): it is
    released on every exit path, a crash or SIGKILL included, so a lock file left by a dead
    process is stale by construction and simply taken over. Re-entrant within one process."""
    from .errors import UserError

    folder = Path(folder)
    key = str(folder.resolve())
    if key in _HELD:
        _HELD[key] += 1
        try:
            yield
        finally:
            _HELD[key] -= 1
        return
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as e:
        raise UserError(f"{path}: cannot create the lock file ({e.strerror or e})") from None
    try:
        _try_lock(fd)
    except BlockingIOError:
        os.lseek(fd, 0, os.SEEK_SET)
        holder = os.read(fd, 64).decode(errors="replace").strip() or "?"
        os.close(fd)
        raise UserError(
            f"{folder}: this {what} is in use by another warpnerf process (pid {holder}); wait "
            "for it to finish or choose another output"
        ) from None
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        _HELD[key] = 1
        yield
    finally:
        _HELD.pop(key, None)
        os.close(fd)  # closing the descriptor releases the lock


_HELD: dict = {}


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


@contextlib.contextmanager
def atomic_path(path, replace_foreign: bool = False):
    """Yields a temporary path next to ``path`` (same suffix); when the block succeeds the file is
    fsynced and renamed onto ``path`` (then the folder is fsynced, so the rename survives a power
    cut) and its name is recorded in the folder's manifest; when it raises (any exception,
    KeyboardInterrupt included) the file is removed. An existing ``path`` that warpnerf did not
    write is never replaced (:class:`UserError`) unless ``replace_foreign`` (a file the user named
    explicitly, such as ``mesh --out FILE``)."""
    path = Path(path)
    if not replace_foreign:
        check_foreign([path])
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; outputs get the usual permissions
    try:
        yield tmp
        _fsync(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise
    _record(path)
    _fsync(path.parent)


def _fsync(path) -> None:
    """Flushes a file's data to disk (best effort: a folder cannot be opened on every OS)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def json_safe(obj):
    """``obj`` with every float that is not finite (an infinite PSNR of identical images, a
    Chamfer distance without a mesh) replaced by ``None``: JSON has no NaN or Infinity, and
    files with them are not valid JSON for other tools. Training stops before a non-finite
    loss could reach its history (see ``train._signals.nonfinite_flags``)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.generic):
        return json_safe(obj.item())
    return obj


def json_dumps(obj, **kw) -> str:
    """``json.dumps`` of :func:`json_safe` (obj) with ``allow_nan=False``: strict JSON."""
    return json.dumps(json_safe(obj), allow_nan=False, **kw)


def write_json(path, obj, replace_foreign: bool = False) -> None:
    text = json_dumps(obj, indent=2) + "\n"  # fails before anything is written
    with atomic_path(path, replace_foreign) as tmp, open(tmp, "w") as f:
        f.write(text)


def save_checkpoint(path, state: dict) -> None:
    """``torch.save(state)`` through :func:`atomic_path`: the previous checkpoint stays in place
    until the new one is completely on disk."""
    import torch

    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def load_checkpoint(path, map_location=None, keys=()) -> dict:
    """``torch.load(weights_only=True)`` of a checkpoint written by :func:`save_checkpoint`: only
    tensors and plain data (dict, list, tuple, str, numbers) are rebuilt, so a crafted pickle cannot
    run code (it is refused with a :class:`UserError`). User errors instead of unpickling
    tracebacks: an unreadable, corrupt or truncated file, or one that is not a dict
    holding ``keys`` (another kind of run's checkpoint), raises a :class:`UserError` naming
    ``path``."""
    import pickle

    import torch

    from .errors import UserError

    path = Path(path)
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except (PermissionError, FileNotFoundError, IsADirectoryError) as e:
        raise UserError(f"{path}: cannot read the checkpoint ({e.strerror or e})") from None
    except pickle.UnpicklingError as e:
        if "weights only" in str(e).lower() or "weights_only" in str(e).lower():
            # torch's restricted unpickler met a global other than tensors and plain data: a
            # crafted file (or another program's pickle). Nothing of it ran.
            raise UserError(
                f"{path}: refused: the checkpoint holds Python objects other than tensors and "
                "plain data (loading it could run code); warpnerf checkpoints never do"
            ) from None
        raise UserError(f"{path}: not a readable checkpoint, corrupt or truncated ({e})") from None
    except MemoryError:
        raise
    except Exception as e:  # any parse failure of an untrusted file (struct.error, zip, EOF...)
        raise UserError(
            f"{path}: not a readable checkpoint, corrupt or truncated ({type(e).__name__}: "
            f"{str(e).splitlines()[0] if str(e) else 'no detail'})"
        ) from None
    if not isinstance(ckpt, dict):
        raise UserError(f"{path}: not a warpnerf checkpoint (a {type(ckpt).__name__})")
    missing = [k for k in keys if k not in ckpt]
    if missing:
        raise UserError(
            f"{path}: not this kind of run's checkpoint (missing {', '.join(map(repr, missing))}; "
            "another model's run, or written by another version)"
        )
    return ckpt


def load_weights(module, state, path, what: str = "weights") -> None:
    """``module.load_state_dict(state)`` (a torch module, optimiser or scheduler) with a
    :class:`UserError` naming checkpoint ``path`` when the saved tensors do not fit: the run's
    config.json and its checkpoint disagree (a resized model, another run's checkpoint)."""
    from .errors import UserError

    try:
        module.load_state_dict(state)
    except (RuntimeError, ValueError, KeyError, TypeError, AttributeError) as e:
        detail = " ".join(str(e).split())
        detail = detail if len(detail) <= 300 else detail[:297] + "..."
        raise UserError(
            f"{path}: its {what} do not match the run's config.json (was the config edited, or "
            f"the checkpoint copied from another run?): {detail}"
        ) from None


def to_uint8(img) -> np.ndarray:
    """float image in [0, 1] (torch or numpy, [H, W] or [H, W, C]) -> uint8."""
    if hasattr(img, "detach"):
        img = img.detach().cpu().numpy()
    img = np.nan_to_num(np.asarray(img, dtype=np.float64), nan=0.0)
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def depth_to_uint8(depth, max_value: float | None = None) -> np.ndarray:
    """Depth [H, W] normalised by its maximum (or ``max_value``) to a grey uint8 image."""
    if hasattr(depth, "detach"):
        depth = depth.detach().cpu().numpy()
    depth = np.asarray(depth, dtype=np.float64)
    m = float(np.nanmax(depth)) if max_value is None else float(max_value)
    return to_uint8(depth / m if m > 0 else depth)


def write_image(path, img) -> None:
    import imageio.v3 as iio

    arr = img if getattr(img, "dtype", None) == np.uint8 else to_uint8(img)
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, arr)


def write_video(path, frames, fps: int = 20) -> None:
    """frames: list of uint8 [H, W, 3] (or float in [0, 1]); .gif or .mp4 (needs imageio-ffmpeg).

    An mp4 is encoded by running the ffmpeg of imageio-ffmpeg on raw frames piped to it; the file
    is renamed onto ``path`` only when ffmpeg exits with status 0 and wrote an MP4 (a full disk or
    a broken encoder raise a :class:`UserError` with ffmpeg's last message and leave no file)."""
    import imageio.v2 as imageio

    frames = [f if getattr(f, "dtype", None) == np.uint8 else to_uint8(f) for f in frames]
    frames = [np.repeat(f[..., None], 3, -1) if f.ndim == 2 else f for f in frames]
    path = Path(path)
    if not frames:
        raise ValueError(f"{path}: no frames to write")
    bad = [f.shape for f in frames if f.shape != frames[0].shape or f.ndim != 3 or f.shape[2] != 3]
    if bad:
        raise ValueError(f"{path}: frames must all be [H, W, 3] of one size, got {bad[0]}")
    with atomic_path(path) as tmp:
        if path.suffix == ".gif":
            imageio.mimsave(tmp, frames, duration=1000.0 / fps, loop=0)
        else:
            _encode_mp4(tmp, frames, fps, path)


def _encode_mp4(tmp, frames, fps: int, path: Path) -> None:
    import subprocess

    import imageio_ffmpeg

    from .errors import UserError

    h, w = frames[0].shape[:2]
    h, w = h - h % 2, w - w % 2  # yuv420p needs even sizes
    if h < 2 or w < 2:
        raise ValueError(f"{path}: frames of {frames[0].shape[1]}x{frames[0].shape[0]} are too "
                         "small for an mp4")  # fmt: skip
    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-f", "rawvideo",
           "-pix_fmt", "rgb24", "-s", f"{w}x{h}", "-r", str(fps), "-i", "-", "-an",
           "-c:v", "libx264", "-qp", "10", "-pix_fmt", "yuv420p", "-f", "mp4",
           str(tmp)]  # fmt: skip
    proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)  # fmt: skip
    try:
        try:
            for f in frames:
                proc.stdin.write(np.ascontiguousarray(f[:h, :w, :3]).tobytes())
            proc.stdin.close()
        except BrokenPipeError:  # ffmpeg died; its status and message say why
            pass
        err = proc.stderr.read().decode(errors="replace")
        status = proc.wait()
    except BaseException:
        proc.kill()
        proc.wait()
        raise
    finally:
        for stream in (proc.stdin, proc.stderr):
            with contextlib.suppress(OSError):
                stream.close()
    with open(tmp, "rb") as fh:
        head = fh.read(12)
    if status != 0 or head[4:8] != b"ftyp":
        last = next((ln for ln in reversed(err.strip().splitlines()) if ln.strip()), "")
        why = f"exit status {status}" if status != 0 else "it wrote no MP4"
        raise UserError(
            f"{path}: the video encoder (ffmpeg) failed ({why}{': ' + last if last else ''}); "
            "no video was written"
        )
