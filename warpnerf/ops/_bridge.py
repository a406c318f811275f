"""Private helpers between torch tensors and Warp launches (no compilation at import)."""

from __future__ import annotations

import os

import torch
import warp as _warp

# Silence Warp's banner and per-module compile lines unless asked for (no init, no compile here).
if not os.environ.get("WARPNERF_VERBOSE"):
    _warp.config.log_level = _warp.LOG_WARNING

_READY = False
FLOATS = (torch.float32, torch.float64)


def _wp():
    """Imports and initialises Warp on first use (quietly unless WARPNERF_VERBOSE is set)."""
    global _READY
    import warp as wp

    if not _READY:
        wp.init()
        _READY = True
    return wp


def wp_device(device: torch.device) -> str:
    if device.type == "cuda":
        return f"cuda:{device.index if device.index is not None else torch.cuda.current_device()}"
    if device.type == "cpu":
        return "cpu"
    raise ValueError(f"warpnerf kernels run on cpu or cuda tensors, got device {device}")


def arr(t: torch.Tensor, dtype=None):
    """Zero-copy Warp view of a contiguous tensor (no gradient tracking on the Warp side)."""
    wp = _wp()
    return wp.from_torch(t.contiguous(), dtype=dtype, requires_grad=False)


def scalar(x: float, dtype: torch.dtype):
    """A Warp scalar of the tensors' float type (a bare Python float would pick float32)."""
    wp = _wp()
    return wp.float64(x) if dtype == torch.float64 else wp.float32(x)


def launch(kernel, dim: int, inputs: list, device: torch.device) -> None:
    """Launches on torch's current stream for CUDA tensors, so ordering with torch ops holds."""
    wp = _wp()
    if dim == 0:
        return
    dev = wp_device(device)
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
    if device is not None and t.device != device:
        raise ValueError(f"{name} is on {t.device}, expected {device} like the other inputs")
    if t.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, t.shape)):
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {want}, got {list(t.shape)}")


def launch_tiled(kernel, n_blocks: int, block_dim: int, inputs: list, device: torch.device) -> None:
    """One block of ``block_dim`` threads per item (Warp runs CPU blocks with one lane)."""
    wp = _wp()
    if n_blocks == 0:
        return
    dev = wp_device(device)
    stream = wp.stream_from_torch(device) if device.type == "cuda" else None
    wp.launch_tiled(
        kernel, dim=[n_blocks], inputs=inputs, device=dev, block_dim=block_dim, stream=stream
    )
