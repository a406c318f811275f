"""Torch bridge for stratified and importance sampling (kernels/sampling.py). No gradients."""

from __future__ import annotations

from typing import NamedTuple

import torch

from . import bridge

__all__ = ["stratified_samples", "importance_samples", "Samples"]

# Padding of the importance PDF: a constant density worth this much mass per interval on equal
# bins (NeRF's ``weights + 1e-5``); see kernels/sampling.py.
PDF_PADDING = 1e-5
# XORed into importance_samples' seed so that the seed given to stratified_samples for the same
# rays gives an unrelated random stream (with one stream, on uniform weights, every new position
# would sit exactly half a bin before a jittered coarse edge).
_IMPORTANCE_SALT = 0x5BD1E995


class Samples(NamedTuple):
    """Intervals along rays. Dense: t_starts/t_ends [n_rays, n_samples], ray_indices and
    packed_info None. Packed: t_starts/t_ends/ray_indices [n], packed_info [n_rays, 2] int32."""

    t_starts: torch.Tensor
    t_ends: torch.Tensor
    ray_indices: torch.Tensor | None = None
    packed_info: torch.Tensor | None = None

    def midpoints(self) -> torch.Tensor:
        return 0.5 * (self.t_starts + self.t_ends)


def stratified_samples(
    near: torch.Tensor,  # [n_rays]
    far: torch.Tensor,  # [n_rays]
    n_samples: int,
    *,
    perturb: bool = False,
    seed: int = 0,
    packed: bool = False,
    ray_offset: int = 0,
) -> Samples:
    """Stratified intervals partitioning [near, far] on every ray.

    Evaluation (perturb=False): n equal bins, fields evaluated at bin midpoints. Training
    (perturb=True): interior bin edges jittered uniformly by up to half a bin (Warp RNG keyed by
    ``seed`` and ray index ``ray_offset + i``: rays i.. of a slice starting at ``ray_offset`` get
    the draws of the whole batch's rays; pass a new seed every step). Packed: rays with far <=
    near get no samples.
    Non-finite near/far raise ValueError (they would otherwise yield plausible-looking samples);
    so does an ``n_samples`` that is not an int or whose n_rays * n_samples overflows int32
    offsets.
    """
    from warpnerf.kernels import sampling as K

    bridge.check_float("near", near, (None,))
    n_rays, dev, dt = near.shape[0], near.device, near.dtype
    bridge.check_float("far", far, (n_rays,), dt, dev)
    n_samples = bridge.check_int("n_samples", n_samples, lo=1)
    ray_offset = bridge.check_int("ray_offset", ray_offset, lo=0, hi=bridge.INT32_MAX - n_rays)
    if n_rays * n_samples > bridge.INT32_MAX:
        raise ValueError(
            f"n_rays * n_samples = {n_rays * n_samples} exceeds int32 offsets: sample fewer rays"
        )
    if n_rays and not bool(torch.isfinite(near).all() & torch.isfinite(far).all()):
        raise ValueError("near and far must be finite (a NaN/Inf bound would hide a bad ray)")
    counts = torch.where(far > near, n_samples, 0).to(torch.int64) if packed else None
    n = int(counts.sum()) if packed else n_rays * n_samples
    packed_info, t_starts, t_ends, ray_indices = _outputs(n, counts, near)
    a = bridge.arr
    bridge.launch(
        K.stratified_fwd,
        n_rays,
        [
            a(near),
            a(far),
            int(n_samples),
            a(packed_info),
            int(perturb),
            int(seed) & 0x7FFFFFFF,
            ray_offset,
            *map(a, (t_starts, t_ends, ray_indices)),
        ],
        dev,
    )
    return _samples(packed_info, t_starts, t_ends, ray_indices, None if packed else n_samples)


def importance_samples(
    samples: Samples,
    weights: torch.Tensor,  # [n_rays, n_c] dense or [n] packed, >= 0
    n_fine: int,
    *,
    perturb: bool = False,
    seed: int = 0,
    ray_offset: int = 0,
) -> Samples:
    """Hierarchical (coarse-to-fine) sampling: the coarse intervals merged with n_fine new edges.

    The coarse intervals must partition each ray's [near, far] (as :func:`stratified_samples`
    makes them); ``weights`` are their compositing weights (detached here). New edge positions
    are drawn by the inverse CDF of the piecewise-constant PDF p_i ~ w_i + eps * n_c * len_i / L
    (eps = ``PDF_PADDING``, L = far - near; all-zero weights sample uniformly by length) at
    u_j = (j + 1/2) / n_fine, or u_j = (j + U_j) / n_fine with U_j from Warp's RNG keyed by
    ``seed`` and ray (``ray_offset`` + its index, as in :func:`stratified_samples`) when
    ``perturb``. The n_c + 1 coarse edges and the n_fine new ones, merged in
    order, give n_c + n_fine intervals that still partition [near, far] (zero-length ones allowed):
    evaluate the fine field at their midpoints. Same layout out as in: dense
    [n_rays, n_c + n_fine], or packed with ``packed_info`` counts n_c + n_fine (0 stays 0).

    Raises ValueError for bad shapes/dtypes/devices, n_fine < 1, weights that are negative or not
    finite (a NaN weight would silently skew every sample of its ray) or whose sum is within a
    factor 8 of the dtype's overflow (an infinite total would put every new position at far),
    and samples that are not finite, ordered and contiguous along each ray.
    """
    from warpnerf.kernels import sampling as K

    if not isinstance(samples, Samples):
        raise ValueError(f"samples must be a Samples tuple, got {type(samples).__name__}")
    n_fine = bridge.check_int("n_fine", n_fine, lo=1)
    ray_offset = bridge.check_int("ray_offset", ray_offset, lo=0, hi=bridge.INT32_MAX // 2)
    ts, te, packed_info = samples.t_starts, samples.t_ends, samples.packed_info
    packed = packed_info is not None
    bridge.check_float("samples.t_starts", ts, (None,) if packed else (None, None))
    dev, dt = ts.device, ts.dtype
    bridge.check_float("samples.t_ends", te, tuple(ts.shape), dt, dev)
    bridge.check_float("weights", weights, tuple(ts.shape), dt, dev)
    if ts.numel() > bridge.INT32_MAX:
        raise ValueError(f"{ts.numel()} samples exceed int32 offsets: sample fewer rays at once")
    ts, te, w = ts.detach().contiguous(), te.detach().contiguous(), weights.detach().contiguous()
    if packed:
        n_rays, n_c = _check_packed(samples, ts.shape[0], dev), 0
        counts = packed_info[:, 1].long()
        first = torch.zeros(ts.shape[0] + 1, dtype=torch.bool, device=dev)
        first[packed_info[:, 0].long().clamp(0, ts.shape[0])[counts > 0]] = True  # ray starts
        joined = (te[:-1] == ts[1:]) | first[1:-1]
        out_counts = torch.where(counts > 0, counts + n_fine, 0)
        n_out = out_counts.sum()
        in_range = (packed_info[:, 0] >= 0) & (counts >= 0)
        in_range &= packed_info[:, 0].long() + counts <= ts.shape[0]
    else:
        n_rays, n_c = ts.shape
        if n_rays * (n_c + n_fine) > bridge.INT32_MAX:
            raise ValueError("n_rays * (n_coarse + n_fine) exceeds int32 offsets: use fewer rays")
        if samples.ray_indices is not None:
            raise ValueError("samples: dense samples (no packed_info) must have ray_indices None")
        if n_c < 1:
            raise ValueError("samples: dense samples need at least one interval per ray")
        joined = te[:, :-1] == ts[:, 1:]
        n_out = torch.tensor(n_rays * (n_c + n_fine), device=dev)
        in_range = torch.ones((), dtype=torch.bool, device=dev)
    flags = torch.stack(
        [
            in_range.all(),
            torch.isfinite(w).all(),
            (w >= 0).all(),
            # the kernel sums each ray's masses: a total within 8x of overflow is refused (the
            # inverse CDF of an infinite total puts every new position at far)
            torch.isfinite(w.sum() * 8),
            torch.isfinite(ts).all() & torch.isfinite(te).all(),
            (te >= ts).all(),
            joined.all(),
        ]
    )
    ok_range, finite_w, pos_w, small_w, finite_t, ordered, contiguous, n_out = [
        int(x) for x in torch.cat([flags.long(), n_out.reshape(1).long()]).tolist()
    ]  # one device sync for all the checks
    if not ok_range:
        raise ValueError("samples.packed_info has a (start, count) outside the samples")
    if n_out > bridge.INT32_MAX:
        raise ValueError(f"{n_out} output samples exceed int32 offsets: use fewer rays or n_fine")
    if not finite_w:
        raise ValueError("weights must be finite (a NaN/Inf weight would skew its ray's PDF)")
    if not pos_w:
        raise ValueError("weights must be >= 0")
    if not small_w:
        raise ValueError(
            f"weights are too large: their sum overflows {dt} (compositing weights sum to <= 1"
            " per ray; rescale them)"
        )
    if not finite_t:
        raise ValueError("samples must have finite t_starts and t_ends")
    if not ordered:
        raise ValueError("samples must have t_ends >= t_starts")
    if not contiguous:
        raise ValueError("samples must partition each ray: t_ends[k] == t_starts[k + 1] within it")

    in_info = (
        packed_info.contiguous() if packed else torch.empty(0, 2, device=dev, dtype=torch.int32)
    )
    out_info, out_starts, out_ends, out_ray_indices = _outputs(
        n_out, out_counts if packed else None, ts
    )
    a = bridge.arr
    bridge.launch(
        K.importance_fwd,
        n_rays,
        [
            a(ts.reshape(-1)),
            a(te.reshape(-1)),
            a(w.reshape(-1)),
            int(n_c),
            a(in_info),
            int(n_fine),
            bridge.scalar(PDF_PADDING, dt),
            int(perturb),
            (int(seed) ^ _IMPORTANCE_SALT) & 0x7FFFFFFF,
            ray_offset,
            *map(a, (out_info, out_starts, out_ends, out_ray_indices)),
        ],
        dev,
    )
    return _samples(
        out_info, out_starts, out_ends, out_ray_indices, None if packed else n_c + n_fine
    )


def _outputs(n: int, counts: torch.Tensor | None, like: torch.Tensor) -> tuple:
    """A sampler's outputs for ``n`` samples: (packed_info [n_rays, 2] int32 of the rays' sample
    ``counts`` [n_rays] int64, or [0, 2] in the dense layout (``counts`` None); t_starts and
    t_ends [n] of ``like``'s dtype and device; ray_indices [n] int64, or [0] dense)."""
    dev = like.device
    if counts is None:
        info = torch.empty(0, 2, device=dev, dtype=torch.int32)
        ray_indices = torch.empty(0, device=dev, dtype=torch.int64)
    else:
        info = torch.stack([torch.cumsum(counts, 0) - counts, counts], -1).to(torch.int32)
        ray_indices = torch.empty(n, device=dev, dtype=torch.int64)
    t_starts = torch.empty(n, device=dev, dtype=like.dtype)
    return info, t_starts, torch.empty_like(t_starts), ray_indices


def _samples(packed_info, t_starts, t_ends, ray_indices, per_ray: int | None) -> Samples:
    """The Samples of a sampler's outputs: packed, or dense with ``per_ray`` samples per ray."""
    if per_ray is None:
        return Samples(t_starts, t_ends, ray_indices, packed_info)
    return Samples(t_starts.reshape(-1, per_ray), t_ends.reshape(-1, per_ray))


def _check_packed(samples: Samples, n: int, dev: torch.device) -> int:
    """Checks a packed Samples' packed_info [n_rays, 2] int32 and ray_indices [n] int64; n_rays."""
    info, ray_indices = samples.packed_info, samples.ray_indices
    if isinstance(info, torch.Tensor) and (info.dtype.is_floating_point or info.dtype.is_complex):
        raise bridge.IndexDtypeError(
            f"samples.packed_info must be an int32 tensor [n_rays, 2], got {info.dtype}"
        )
    if isinstance(ray_indices, torch.Tensor) and ray_indices.dtype.is_floating_point:
        raise bridge.IndexDtypeError(
            f"samples.ray_indices must be an int64 tensor [n], got {ray_indices.dtype}"
        )
    if not isinstance(info, torch.Tensor) or info.dtype != torch.int32 or info.dim() != 2:
        raise ValueError("samples.packed_info must be an int32 tensor [n_rays, 2]")
    if info.shape[1] != 2 or info.device != dev:
        raise ValueError(f"samples.packed_info must be [n_rays, 2] on {dev}, got {info.shape}")
    if not isinstance(ray_indices, torch.Tensor) or ray_indices.dtype != torch.int64:
        raise ValueError("samples.ray_indices must be an int64 tensor [n] in the packed layout")
    if tuple(ray_indices.shape) != (n,) or ray_indices.device != dev:
        raise ValueError(f"samples.ray_indices must have shape [{n}] on {dev}")
    return info.shape[0]
