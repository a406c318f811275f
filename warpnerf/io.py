"""Atomic output writers: every file is written to a temporary name in its folder, flushed to disk,
then renamed onto its target, so an interrupted run (an exception, a signal, a killed process, a
full disk) never leaves a half-written image, video, mesh, checkpoint or metrics file: the target
is the previous complete file or the new complete one. A process killed outright in the middle of
a write (SIGKILL, or a signal without a Python handler) can leave the hidden temporary file
(``.NAME.XXXXXXXX.SUFFIX``) behind, never a partial target."""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path

import numpy as np

__all__ = [
    "atomic_path",
    "write_json",
    "save_checkpoint",
    "load_checkpoint",
    "load_weights",
    "write_image",
    "write_video",
    "to_uint8",
    "depth_to_uint8",
]


@contextlib.contextmanager
def atomic_path(path):
    """Yields a temporary path next to ``path`` (same suffix); when the block succeeds the file is
    fsynced and renamed onto ``path`` (then the folder is fsynced, so the rename survives a power
    cut); when it raises (any exception, KeyboardInterrupt included) the file is removed."""
    path = Path(path)
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


def write_json(path, obj) -> None:
    with atomic_path(path) as tmp, open(tmp, "w") as f:
        json.dump(obj, f, indent=2)
        f.write("\n")


def save_checkpoint(path, state: dict) -> None:
    """``torch.save(state)`` through :func:`atomic_path`: the previous checkpoint stays in place
    until the new one is completely on disk."""
    import torch

    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def load_checkpoint(path, map_location=None, keys=()) -> dict:
    """``torch.load`` of a checkpoint written by :func:`save_checkpoint`, with user errors instead
    of unpickling tracebacks: an unreadable, corrupt or truncated file, or one that is not a dict
    holding ``keys`` (another kind of run's checkpoint), raises a :class:`UserError` naming
    ``path``."""
    import pickle
    import zipfile

    import torch

    from .errors import UserError

    path = Path(path)
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=False)
    except (PermissionError, FileNotFoundError, IsADirectoryError) as e:
        raise UserError(f"{path}: cannot read the checkpoint ({e.strerror or e})") from None
    except (pickle.UnpicklingError, zipfile.BadZipFile, EOFError, OSError, RuntimeError,
            ValueError, AttributeError, ImportError, IndexError, KeyError,
            TypeError) as e:  # fmt: skip
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
    """frames: list of uint8 [H, W, 3] (or float in [0, 1]); .gif or .mp4 (needs imageio-ffmpeg)."""
    import imageio.v2 as imageio

    frames = [f if getattr(f, "dtype", None) == np.uint8 else to_uint8(f) for f in frames]
    frames = [np.repeat(f[..., None], 3, -1) if f.ndim == 2 else f for f in frames]
    path = Path(path)
    with atomic_path(path) as tmp:
        if path.suffix == ".gif":
            imageio.mimsave(tmp, frames, duration=1000.0 / fps, loop=0)
        else:
            # Even sizes for yuv420p; macro_block_size=1 keeps small frames unpadded otherwise.
            h, w = frames[0].shape[:2]
            frames = [f[: h - h % 2, : w - w % 2] for f in frames]
            wr = imageio.get_writer(
                tmp, fps=fps, codec="libx264", quality=8, macro_block_size=1, format="FFMPEG"
            )
            try:
                for f in frames:
                    wr.append_data(f)
            except BaseException:
                # imageio's writer skips close() when its block raises: ffmpeg would then finish
                # writing the temporary file after atomic_path removed it. Stop ffmpeg first.
                with contextlib.suppress(Exception):
                    wr.close()
                raise
            wr.close()
