"""``--train-spp S``: each training pixel rendered as the mean of ``S`` rays through fixed points
of it (:func:`~warpnerf.train.nerf_run.pixel_points`: a k x k grid of cell centres for S = k^2),
compared with the pixel's colour. A dataset downsampled by area averaging (lego 400x400: the mean
of 2x2 pixels of an 800x800 render) holds exactly that mean, which one ray through the pixel's
centre does not render; ``eval --spp S`` scores the same image. The eager step
(:meth:`~warpnerf.train.nerf.NeRFTask.loss`) and the static-shape step
(:mod:`~warpnerf.train.graph_step`) both expand their pixels with :func:`sub_rays` and average
the renders with :func:`pixel_means`; the sub-rays of pixel i are rays i*S .. i*S + S - 1."""

from __future__ import annotations

import torch

from .nerf_run import pixel_points

__all__ = ["PER_RAY", "sub_offsets", "sub_rays", "expand_rows", "pixel_means"]

# the renderers' per-ray outputs that a pixel averages over its sub-rays (every other entry,
# sample counts and statistics, is left as it is)
PER_RAY = ("rgb", "rgb_coarse", "depth", "opacity", "distortion", "near_weight", "interlevel")


def sub_offsets(spp: int, device) -> torch.Tensor:
    """[S, 2] float32 offsets of the sub-rays from the pixel's centre (points - 1/2), made once
    on the run's device (a captured step cannot copy from the host)."""
    pts = torch.tensor(pixel_points(spp), dtype=torch.float32)
    return (pts - 0.5).to(device)


def expand_rows(x: torch.Tensor, s: int) -> torch.Tensor:
    """[n, ...] -> [n * s, ...], each row repeated ``s`` times in a row (no host sync)."""
    return x[:, None].expand(x.shape[0], s, *x.shape[1:]).reshape(x.shape[0] * s, *x.shape[1:])


def sub_rays(cam, px, py, offsets: torch.Tensor) -> tuple:
    """(cam, px, py) [n * S] of the sub-rays of the pixels whose centres are ``px``, ``py`` [n]
    (float32) of cameras ``cam`` [n]."""
    s = offsets.shape[0]
    pxs = (px[:, None] + offsets[None, :, 0]).reshape(-1)
    pys = (py[:, None] + offsets[None, :, 1]).reshape(-1)
    return expand_rows(cam, s), pxs, pys


def pixel_means(out: dict, n: int, s: int) -> dict:
    """The renderer's ``out`` for ``n * s`` sub-rays as ``n`` pixels: each :data:`PER_RAY` entry
    averaged over a pixel's ``s`` sub-rays (differentiable), the rest unchanged."""
    res = dict(out)
    for k in PER_RAY:
        v = out.get(k)
        if torch.is_tensor(v) and v.dim() >= 1 and v.shape[0] == n * s:
            res[k] = v.reshape(n, s, *v.shape[1:]).mean(1)
    return res
