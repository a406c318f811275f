"""The bridge between torch tensors and Warp launches: array views, launches, shape, dtype and
index checks shared by every op module (no compilation at import)."""

from __future__ import annotations

import operator
import os

import torch
import warp as _warp

# Silence Warp's banner and per-module compile lines unless asked for (no init, no compile here).
if not os.environ.get("WARPNERF_VERBOSE"):
    _warp.config.log_level = _warp.LOG_WARNING

_READY = False
_HELD_BACK = ""  # what Warp's native init printed that :func:`load_warp` kept off stderr
_DRIVER_NOTE = "Could not find or load the NVIDIA CUDA driver"
FLOATS = (torch.float32, torch.float64)
INTS = (torch.int32, torch.int64)
INT32_MAX = 2**31 - 1  # kernels index with 32-bit ints: sizes and offsets must stay below this


def load_warp():
    """Imports and initialises Warp on first use (quietly unless WARPNERF_VERBOSE is set)."""
    global _READY
    import warp as wp

    if not _READY:
        if os.environ.get("WARPNERF_VERBOSE"):
            wp.init()
        else:
            _quiet_init(wp)
        _READY = True
    return wp


def _quiet_init(wp) -> None:
    """``wp.init()`` without its CUDA driver warning on machines without the driver.

    Warp's native ``wp_init`` always probes the CUDA driver and, when ``libcuda`` is missing,
    writes "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver..." straight to the
    process's stderr (C ``fprintf``; no config option skips the probe or the line). A CPU run does
    not need CUDA, so the line is noise there: native stderr (fd 2) is sent to a temporary file
    for the duration of the init, that line is held back (:func:`wp_device` repeats it if CUDA is
    then asked of Warp; the CLI's ``--device cuda`` already fails with its own error when PyTorch
    has no CUDA) and anything else Warp printed is written back to stderr."""
    global _HELD_BACK
    import sys
    import tempfile

    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no usable fd 2 (embedded interpreters): init as it is
        wp.init()
        return
    try:
        with tempfile.TemporaryFile() as tmp:
            os.dup2(tmp.fileno(), 2)
            try:
                wp.init()
            finally:
                os.dup2(saved, 2)
            tmp.seek(0)
            text = tmp.read().decode("utf-8", "replace")
    finally:
        os.close(saved)
    lines = text.splitlines(keepends=True)
    _HELD_BACK = "".join(ln for ln in lines if _DRIVER_NOTE in ln).strip()
    rest = "".join(ln for ln in lines if _DRIVER_NOTE not in ln)
    if rest:
        os.write(2, rest.encode())


def wp_device(device: torch.device) -> str:
    if device.type == "cuda":
        if _HELD_BACK and not load_warp().is_cuda_available():
            raise RuntimeError(f"a CUDA tensor, but Warp has no CUDA here: {_HELD_BACK}")
        return f"cuda:{device.index if device.index is not None else torch.cuda.current_device()}"
    if device.type == "cpu":
        return "cpu"
    raise ValueError(f"warpnerf kernels run on cpu or cuda tensors, got device {device}")


_ARRAY_TYPES: dict = {}  # (dtype, ndim) -> the Warp array type of a descriptor
_OVERLOADS: dict = {}  # (generic kernel, argument signature) -> its concrete overload


def _array_type(dtype, ndim: int):
    key = (dtype, ndim)
    t = _ARRAY_TYPES.get(key)
    if t is None:
        t = _ARRAY_TYPES[key] = load_warp().array(dtype=dtype, ndim=ndim)
    return t


def arr(t: torch.Tensor, dtype=None):
    """Zero-copy Warp view of a contiguous tensor (no gradient tracking on the Warp side) as
    Warp's low-level array descriptor (``from_torch(..., return_ctype=True)``: 4 us of host time
    against 13 us for a ``wp.array``, and a training step makes about 85 of them). The descriptor
    holds the tensor (so a temporary such as ``arr(x.to(torch.int32))`` lives as long as the
    launch's argument list) and its Warp array type, which :func:`launch` uses to pick a generic
    kernel's overload: Warp takes descriptors verbatim, without type checks, so every op checks
    its tensors' dtypes and shapes before launching (``check_float``, ``check_index``)."""
    wp = load_warp()
    t = t.contiguous()
    a = wp.from_torch(t, dtype=dtype, requires_grad=False, return_ctype=True)
    dt = dtype if dtype is not None else wp.dtype_from_torch(t.dtype)
    a._tensor = t
    a._wptype = _array_type(dt, t.dim() - len(getattr(dt, "_shape_", ())))
    return a


def _overload(kernel, inputs: list):
    """The concrete overload of a generic kernel for these arguments (Warp cannot infer types
    from descriptors): inferred once per signature from the descriptors' array types."""
    if not kernel.is_generic:
        return kernel
    wp = load_warp()
    sig, proxies = [], []
    for x in inputs:
        t = getattr(x, "_wptype", None)
        if t is not None:
            sig.append(t)
            proxies.append(t)
        elif isinstance(x, wp.array):
            sig.append(("array", x.dtype, x.ndim))
            proxies.append(x)
        else:
            sig.append(type(x))
            proxies.append(x)
    key = (kernel, tuple(sig))
    k = _OVERLOADS.get(key)
    if k is None:
        types = kernel.infer_argument_types(proxies)
        k = kernel.get_overload(types) or kernel.add_overload(types)
        _OVERLOADS[key] = k
    return k


def scalar(x: float, dtype: torch.dtype):
    """A Warp scalar of the tensors' float type (a bare Python float would pick float32)."""
    wp = load_warp()
    return wp.float64(x) if dtype == torch.float64 else wp.float32(x)


def launch(kernel, dim: int, inputs: list, device: torch.device) -> None:
    """Launches on torch's current stream for CUDA tensors, so ordering with torch ops holds."""
    wp = load_warp()
    if dim == 0:
        return
    dev = wp_device(device)
    kernel = _overload(kernel, inputs)
    if device.type == "cuda":
        stream = wp.stream_from_torch(device)
        wp.launch(kernel, dim=dim, inputs=inputs, device=dev, stream=stream)
    else:
        wp.launch(kernel, dim=dim, inputs=inputs, device=dev)


def check_float(name: str, t: torch.Tensor, shape: tuple, dtype=None, device=None) -> None:
    """Raises ValueError naming the argument when a tensor's shape/dtype/device is not as expected.

    ``shape`` entries of None match any size.
    """
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dtype not in FLOATS:
        raise ValueError(f"{name} must be float32 or float64, got {t.dtype}")
    if dtype is not None and t.dtype != dtype:
        raise ValueError(f"{name} has dtype {t.dtype}, expected {dtype} like the other inputs")
    _check_placement(name, t, shape, device)


def _check_placement(name: str, t: torch.Tensor, shape: tuple, device) -> None:
    """ValueError naming the argument when ``t`` is not on ``device`` (None: any) or its shape is
    not ``shape`` (None entries match any size)."""
    if device is not None and t.device != device:
        raise ValueError(f"{name} is on {t.device}, expected {device} like the other inputs")
    if t.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, t.shape)):
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {want}, got {list(t.shape)}")


def launch_tiled(kernel, n_blocks: int, block_dim: int, inputs: list, device: torch.device) -> None:
    """One block of ``block_dim`` threads per item (Warp runs CPU blocks with one lane)."""
    wp = load_warp()
    if n_blocks == 0:
        return
    dev = wp_device(device)
    kernel = _overload(kernel, inputs)
    stream = wp.stream_from_torch(device) if device.type == "cuda" else None
    wp.launch_tiled(
        kernel, dim=[n_blocks], inputs=inputs, device=dev, block_dim=block_dim, stream=stream
    )


class IndexDtypeError(TypeError, ValueError):
    """A float (or bool) tensor or number where integers are expected. A TypeError that is also a
    ValueError: the ops' other argument errors are ValueErrors, and callers catch either."""


def check_int(name: str, value, lo: int = 0, hi: int = INT32_MAX) -> int:
    """``value`` as a Python int in [lo, hi] (ints, NumPy ints and one-element integer tensors
    accepted; bools and floats refused: a float size or index would be truncated silently)."""
    if isinstance(value, bool) or (isinstance(value, torch.Tensor) and value.dtype == torch.bool):
        raise IndexDtypeError(f"{name} must be an int, got a bool")
    try:
        v = operator.index(value)
    except TypeError:
        raise IndexDtypeError(f"{name} must be an int, got {type(value).__name__}") from None
    if not lo <= v <= hi:
        raise ValueError(f"{name} must be an int in [{lo}, {hi}], got {v}")
    return v


def check_index(name: str, t, shape: tuple, device=None) -> None:
    """Raises naming the argument when an index tensor is not int32/int64 (IndexDtypeError: a
    float tensor would be truncated), or its shape or device is not as expected (ValueError).
    Host-side only: the values are checked by the op, in one device sync."""
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dtype not in INTS:
        raise IndexDtypeError(f"{name} must be an int32 or int64 tensor of indices, got {t.dtype}")
    _check_placement(name, t, shape, device)


_CONSTANTS: dict = {}  # (device, dtype, values) -> a small read-only device tensor


def constant(values, device, dtype) -> torch.Tensor:
    """A small tensor of Python numbers on ``device``, made once per (device, dtype, values) and
    reused: building it anew copies host memory to the GPU, and that copy synchronises the host
    with the GPU on every call (the training step's ray box, near/far and background did this).
    Callers must not write into it. Values that are not plain numbers (tensors) are copied as
    usual, uncached."""
    if isinstance(values, torch.Tensor):
        return values.to(device=device, dtype=dtype)
    flat = tuple(values) if isinstance(values, (list, tuple)) else (values,)
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in flat):
        return torch.as_tensor(values, device=device, dtype=dtype)
    dev = torch.device(device)
    key = (dev.type, dev.index, dtype, isinstance(values, (list, tuple)), tuple(map(float, flat)))
    t = _CONSTANTS.get(key)
    if t is None:
        if len(_CONSTANTS) > 256:  # (a long viewer session with many boxes)
            _CONSTANTS.clear()
        t = torch.tensor(values if isinstance(values, (list, tuple)) else flat[0], dtype=dtype)
        t = _CONSTANTS[key] = t.to(dev)
    return t


def host_flags(*flags: torch.Tensor) -> list:
    """Python ints of 0-dim bool/int device tensors, copied in one transfer (one host sync on
    CUDA however many checks ride on it)."""
    if not flags:
        return []
    return torch.stack([f.reshape(()).to(torch.int64) for f in flags]).tolist()


_wp = load_warp  # (the old private name, for code written against ops._bridge)
