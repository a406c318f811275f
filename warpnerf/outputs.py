"""Output writers and checkpoint loaders. Every output (image, video, mesh, checkpoint, JSON) is
written through :func:`~warpnerf.safe_writes.atomic_path`: to a temporary name in its folder,
flushed to disk, then renamed onto its target, so an interrupted run (an exception, a signal, a
killed process, a full disk) never leaves a half-written file: the target is the previous
complete file or the new complete one. A process killed outright in the middle of a write
(SIGKILL, or a signal without a Python handler) can leave the hidden temporary file
(``.NAME.XXXXXXXX.SUFFIX``) behind, never a partial target. How warpnerf writes into folders it
does not own exclusively (no links followed, special files refused, manifests, the folder lock)
is in :mod:`warpnerf.safe_writes`."""

from __future__ import annotations

import contextlib
import json
import math
import os
from pathlib import Path

import numpy as np

# The files warpnerf writes into run and output folders (atomic outputs, manifests, the folder
# lock, no links followed, special files refused): warpnerf/safe_writes.py, re-exported here.
from . import safe_writes as _safe_writes
from .safe_writes import *  # noqa: F403 (re-exported: the names of warpnerf/safe_writes.py)
from .safe_writes import atomic_path

__all__ = [
    *_safe_writes.__all__,
    "json_safe",
    "json_dumps",
    "write_json",
    "save_checkpoint",
    "load_checkpoint",
    "watch_checkpoint_reads",
    "load_weights",
    "load_tensors",
    "build_for_weights",
    "zip_directory",
    "check_overlap",
    "write_image",
    "write_video",
    "to_uint8",
    "depth_to_uint8",
    "contact_sheet",
]


def json_safe(obj):
    """``obj`` with every float that is not finite (an infinite PSNR of identical images, a
    Chamfer distance without a mesh) replaced by ``None``: JSON has no NaN or Infinity, and
    files with them are not valid JSON for other tools. Training stops before a non-finite
    loss could reach its history (see ``train.divergence.nonfinite_flags``)."""
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
        with _safe_writes.open_input(path, "checkpoint") as fh:  # (no link, no FIFO: never blocks)
            _check_checkpoint_zip(path, fh)
            fh.seek(0)
            ckpt = torch.load(fh, map_location=map_location, weights_only=True)
    except UserError:
        raise
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
    for k in keys:  # the entries every run kind shares, of the form the loop writes
        if k in _ENTRIES and not _ENTRIES[k][0](ckpt[k]):
            raise UserError(f"{path}: entry {k!r} must be {_ENTRIES[k][1]}, got {_show(ckpt[k])}")
    problem = _history_problem(ckpt["history"]) if "history" in keys else None
    if problem:
        raise UserError(f"{path}: entry 'history' is not a training history: {problem}")
    for watcher in tuple(_READ_WATCHERS):
        watcher(path, ckpt)
    return ckpt


_READ_WATCHERS: list = []


@contextlib.contextmanager
def watch_checkpoint_reads(fn):
    """Calls ``fn(path, checkpoint)`` after each checkpoint :func:`load_checkpoint` reads in the
    block (the CLI's note that a run it reads is still training, with the step it read)."""
    _READ_WATCHERS.append(fn)
    try:
        yield
    finally:
        _READ_WATCHERS.remove(fn)


def load_weights(module, state, path, what: str = "weights") -> None:
    """``module.load_state_dict(state)`` (a torch module, optimiser or scheduler) with a
    :class:`UserError` naming checkpoint ``path`` when the saved tensors do not fit: the run's
    config.json and its checkpoint disagree (a resized model, another run's checkpoint). A
    module's load is strict (every parameter and buffer present, of its shape); an optimiser's
    per-parameter state (Adam's moments) must have its parameter's shape."""
    from .errors import UserError

    try:
        module.load_state_dict(state)
        if hasattr(module, "param_groups"):
            _check_optimizer_state(module)
    except (RuntimeError, ValueError, KeyError, TypeError, AttributeError) as e:
        detail = " ".join(str(e).split())
        detail = detail if len(detail) <= 300 else detail[:297] + "..."
        raise UserError(
            f"{path}: its {what} do not match the run's config.json (was the config edited, or "
            f"the checkpoint copied from another run?): {detail}"
        ) from None


def load_tensors(targets: dict, saved, path, what: str) -> None:
    """Copies a checkpoint's dict of tensors ``saved`` (untrusted) into ``targets`` (name ->
    tensor, in place), all or nothing: a :class:`UserError` naming ``path`` and ``what`` unless
    ``saved`` is a dict of exactly the names of ``targets``, each a tensor of its target's shape
    and dtype whose values are all finite."""
    import torch

    from .errors import UserError

    def fail(detail: str):
        return UserError(f"{path}: its {what} do not match the run's config.json ({detail})")

    if not isinstance(saved, dict):
        raise fail(f"expected a dict of tensors, got {_show(saved)}")
    names = [k for k in saved if not isinstance(k, str)]
    if names:
        raise fail(f"a key that is not a name: {_show(names[0])}")
    missing, extra = sorted(set(targets) - set(saved)), sorted(set(saved) - set(targets))
    if missing or extra:
        show = lambda ks: ", ".join(ks[:3]) + (" ..." if len(ks) > 3 else "")  # noqa: E731
        raise fail("; ".join(([f"missing {show(missing)}"] if missing else [])
                             + ([f"unexpected {show(extra)}"] if extra else [])))  # fmt: skip
    for k, t in targets.items():
        v = saved[k]
        if not isinstance(v, torch.Tensor) or v.dtype != t.dtype or v.shape != t.shape:
            raise fail(f"{k!r} must be a {t.dtype} tensor of shape {list(t.shape)}, got {_show(v)}")
        if v.is_floating_point() and not bool(torch.isfinite(v).all()):
            raise fail(f"{k!r} holds values that are not finite")
    with torch.no_grad():
        for k, t in targets.items():
            t.copy_(saved[k])


def build_for_weights(build, saved, path, config_path):
    """``build()`` (the model a run's ``config_path``, its config.json, describes) allowed to
    allocate no more than about what checkpoint ``path`` holds for it (``saved``: the model's
    entry, tensors in dicts and lists): every tensor the build makes through torch's factories
    (empty, zeros, ones, full, rand, randn, randint, new_*) is counted before it is allocated,
    and past twice those bytes + 1 MiB (buffers a checkpoint leaves out, the occupancy grid's
    mask) the build stops with a :class:`UserError` naming both files. A config.json edited to
    sizes its checkpoint cannot fill (2^31 layers, a 2^20-wide MLP, a 2^24-row hash table, 10^6
    appearance codes) is refused at once, before growing until the OOM killer; the strict load
    after the build checks every shape."""
    from torch.overrides import TorchFunctionMode

    from .errors import UserError, human_bytes

    held = _tensor_bytes(saved)

    class Budget(TorchFunctionMode):  # (this thread's torch calls, while the build runs)
        left = 2 * held + (1 << 20)

        def __torch_function__(self, func, types, args=(), kwargs=None):
            kwargs = kwargs or {}
            self.left -= _factory_bytes(func, args, kwargs)
            if self.left < 0:
                raise _OverBudget  # (before the allocation)
            return func(*args, **kwargs)

    try:
        with Budget():
            return build()
    except _OverBudget:
        raise UserError(
            f"{config_path}: describes a model larger than the weights {path} holds "
            f"({human_bytes(held)}): its network sizes (layers, widths, hash table, appearance "
            "codes, cameras) do not match the checkpoint; was config.json edited, or copied from "
            "another run?"
        ) from None


def _tensor_bytes(obj) -> int:
    """Bytes of the tensors in ``obj`` (a tensor, or dicts and lists of them)."""
    import torch

    if isinstance(obj, torch.Tensor):
        return obj.numel() * obj.element_size()
    if isinstance(obj, dict):
        return sum(_tensor_bytes(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(_tensor_bytes(v) for v in obj)
    return 0


class _OverBudget(Exception):
    pass


def _factory_bytes(func, args, kwargs) -> int:
    """Bytes a call of one of torch's tensor factories will allocate (0 for anything else)."""
    import torch

    sized = (torch.empty, torch.zeros, torch.ones, torch.rand, torch.randn)
    methods = (torch.Tensor.new_empty, torch.Tensor.new_zeros, torch.Tensor.new_ones)
    if func in methods or func is torch.Tensor.new_full:
        args = args[1:]  # (self)
    if func in sized or func in methods:  # f(*size) or f(size)
        size = args[0] if len(args) == 1 and not isinstance(args[0], int) else args
    elif func in (torch.full, torch.empty_strided, torch.Tensor.new_full):
        size = args[0] if args else ()
    elif func is torch.randint:
        size = args[-1] if args else ()
    else:
        return 0
    size = kwargs.get("size", size)
    try:
        numel = math.prod(max(int(v), 0) for v in size)
    except (TypeError, ValueError):  # (not a size: torch's own error follows)
        return 0
    dtype = kwargs.get("dtype") or torch.get_default_dtype()
    return numel * dtype.itemsize


def _check_optimizer_state(opt) -> None:
    """ValueError naming the first parameter whose saved state tensor (not a 0-dim counter) has
    another shape than the parameter: ``load_state_dict`` does not check them, and the first
    step would fail on them (or broadcast)."""
    for g, group in enumerate(opt.param_groups):
        for j, p in enumerate(group["params"]):
            for key, v in opt.state.get(p, {}).items():
                if hasattr(v, "shape") and v.dim() > 0 and v.shape != p.shape:
                    raise ValueError(
                        f"group {g} parameter {j}: state {key!r} has shape {list(v.shape)}, "
                        f"the parameter {list(p.shape)}"
                    )


def _is_step(v) -> bool:
    return type(v) is int and 0 <= v < 2**31


def _is_generator_state(v) -> bool:
    import torch

    size = torch.Generator().get_state().numel()
    return isinstance(v, torch.Tensor) and v.dtype == torch.uint8 and v.shape == (size,)


def _is_history(v) -> bool:
    return isinstance(v, dict) and all(isinstance(x, list) for x in v.values())


_PER_STEP = ("step", "loss", "seconds")  # the lists the loop appends to at every step


def _history_problem(h: dict) -> str | None:
    """What is wrong with a checkpoint's history (a dict of lists, :func:`_is_history`) for the
    training loop and the tools that read it, or None: names are strings; ``step``, ``loss``
    and ``seconds`` present and of one length; every value a number (not a bool), steps
    (``step``, ``val_step``) integers in [0, 2^31), ``loss`` and ``seconds`` finite, no NaN
    anywhere (a PSNR may be infinite); ``val_step`` and each ``val_*`` list of one length."""
    names = [k for k in h if not isinstance(k, str)]
    if names:
        return f"a key that is not a name ({_show(names[0])})"
    missing = [k for k in _PER_STEP if k not in h]
    if missing:
        return f"no {missing[0]!r} list"
    for k, values in h.items():
        for i, v in enumerate(values):
            if type(v) not in (int, float) or v != v:
                return f"{k!r}[{i}] must be a number, got {_show(v)}"
            if k in ("step", "val_step") and not _is_step(v):
                return f"{k!r}[{i}] must be an integer step in [0, 2^31), got {_show(v)}"
            if k in ("loss", "seconds") and not math.isfinite(v):
                return f"{k!r}[{i}] must be finite, got {v!r}"
    validation = ["val_step", *(k for k in h if k.startswith("val_") and k != "val_step")]
    for group in (_PER_STEP, validation):
        lengths = [f"{k} {len(h[k])}" for k in group if k in h]
        if len({len(h[k]) for k in group if k in h}) > 1:
            return f"lists of different lengths ({', '.join(lengths)})"
    return None


_ENTRIES = {  # name: (test, what it must be)
    "step": (_is_step, "an integer step in [0, 2^31)"),
    "generator": (_is_generator_state, "a CPU generator's state (uint8)"),
    "history": (_is_history, "a dict of lists"),
    "optimizer": (lambda v: isinstance(v, dict), "an optimiser's state (a dict)"),
}


def _show(v) -> str:
    import torch

    if isinstance(v, torch.Tensor):
        return f"a {v.dtype} tensor of shape {list(v.shape)}"
    text = repr(v)
    return f"a {type(v).__name__}" if len(text) > 40 else text


def _check_checkpoint_zip(path: Path, fh) -> None:
    """A checkpoint's zip directory, read before torch unpacks anything: torch's zip format with
    every member stored (``torch.save`` never compresses), each member's declared size its
    stored size, and the members together no larger than the file (no overlapping members, the
    zip bomb that reads one stored block many times). So loading allocates at most the file's
    size for tensors. Anything else (a compressed member, torch's legacy pickle format) is
    refused with a :class:`UserError`."""
    import zipfile

    from .errors import UserError

    size = os.fstat(fh.fileno()).st_size
    if not zipfile.is_zipfile(fh):
        raise UserError(
            f"{path}: not a readable checkpoint (not torch's zip format: corrupt, truncated, or "
            "torch's legacy format, which warpnerf never writes)"
        )
    infos = zip_directory(path, "checkpoint", fh)
    for info in infos:
        if info.compress_type != zipfile.ZIP_STORED:
            raise UserError(
                f"{path}: refused: member {info.filename!r} is compressed (torch never "
                "compresses a checkpoint; a compressed one can inflate far beyond its size)"
            )
        if info.file_size != info.compress_size:
            raise UserError(
                f"{path}: refused: member {info.filename!r} declares {info.file_size} bytes but "
                f"stores {info.compress_size} (corrupt or crafted)"
            )
    check_overlap(path, infos, size)


def zip_directory(path: Path, what: str, fh=None) -> list:
    """The members (ZipInfo) of a zip file's central directory (read from the open file ``fh``
    when given, else from ``path``); UserError naming ``path`` when unreadable."""
    import zipfile

    from .errors import UserError

    try:
        with zipfile.ZipFile(fh if fh is not None else path) as z:
            return z.infolist()
    except (zipfile.BadZipFile, zipfile.LargeZipFile, ValueError, EOFError) as e:
        raise UserError(f"{path}: unreadable {what} (a corrupt zip file: {e})") from None


def check_overlap(path: Path, infos: list, size: int) -> None:
    """UserError unless the members' stored bytes fit in the file (no overlapping members)."""
    from .errors import UserError

    stored = sum(i.compress_size for i in infos)
    if stored > size:
        raise UserError(
            f"{path}: refused: its zip members declare {stored} stored bytes in a file of "
            f"{size} (overlapping members: a zip bomb)"
        )


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


def contact_sheet(frames, cols: int = 4, every: int = 1, skipped=None) -> np.ndarray:
    """One uint8 image [rows * h, cols * w, 3] of ``frames`` (uint8 or float in [0, 1], [H, W]
    or [H, W, C]) tiled row-major, ``cols`` a row, each decimated by ``every`` pixels (nearest);
    blank tiles white. Frames of another size than the first are left out, their indices
    appended to ``skipped`` (a list) when given (device runs return few files: one sheet
    instead of many frames)."""
    tiles = []
    for i, f in enumerate(frames):
        img = f if getattr(f, "dtype", None) == np.uint8 else to_uint8(f)
        img = img[..., None].repeat(3, -1) if img.ndim == 2 else img[..., :3]
        img = img[::every, ::every]
        if tiles and img.shape != tiles[0].shape:
            if skipped is not None:
                skipped.append(i)
            continue
        tiles.append(img)
    if not tiles:
        raise ValueError("contact_sheet: no frames")
    cols = max(1, min(int(cols), len(tiles)))
    rows = -(-len(tiles) // cols)
    h, w = tiles[0].shape[:2]
    sheet = np.full((rows * h, cols * w, 3), 255, np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, cols)
        sheet[r * h : (r + 1) * h, c * w : (c + 1) * w] = t
    return sheet


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
