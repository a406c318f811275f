"""The visibility grid of a NeRF/VolSDF run (issue 49): the cells of a box where its training
rays put weight, for culling the mesh it delivers (:func:`warpnerf.mesh.cull_unweighted`).

sdfstudio's ``extract_mesh --create-visibility-mask`` renders the training images (every 8th
pixel), splats each sample whose compositing weight passes 0.005 into a 512^3 grid, and keeps
the faces in its marked cells. Here the same, with the run's own eager rendering
(:func:`warpnerf.train.nerf_run.render_rays_of`'s samples, no colours):

- rays: the training split's pixel centres, every ``stride``-th pixel of every ``stride``-th
  row (the stride grows until at most ``max_rays`` are left), through the run's refined poses
  (``--pose-refine``) and its NDC map (the grid then lies in NDC, the mesh's own frame);
- samples: an occupancy-grid run's marched samples (in rounds, like rendering, each weight
  times the transmittance left by earlier rounds); an MLP run's stratified samples within its
  box and, with a fine network, the fine pass's samples (those of the final image);
- a cell is marked when the midpoint ``(t_start + t_end) / 2`` of a sample with weight >=
  ``threshold`` (default :data:`WEIGHT_THRESHOLD`, sdfstudio's 0.005: a surface puts most of a
  ray's weight on a few samples, a ray passing near-empty space puts less than that on each)
  lies in it; samples outside the box mark nothing (a contracted scene's grid is its inner
  cube, where its mesh is); then the marked cells are dilated by ``dilate`` cells;
- cells no smaller than the rays' spacing: the grid has ``resolution`` cells per axis at most,
  fewer where neighbouring rays of a camera lie further apart near the box's centre (the median
  over cameras), so a surface the cameras see has a ray in each of its cells (sparse rays
  through a fine grid would leave holes between them).

Weights need a model, so this lives here; :mod:`warpnerf.mesh` stays model-free.
"""

from __future__ import annotations

import math
import time
from typing import NamedTuple

import torch

__all__ = [
    "WeightGrid",
    "training_weight_grid",
    "weight_grid",
    "sample_weights",
    "WEIGHT_THRESHOLD",
    "WEIGHT_RESOLUTION",
    "WEIGHT_STRIDE",
    "WEIGHT_MAX_RAYS",
]

WEIGHT_THRESHOLD = 0.005  # a sample marks its cell at this compositing weight (sdfstudio's)
WEIGHT_RESOLUTION = 128  # cells per axis at most (fewer where the rays lie further apart)
WEIGHT_MIN_RESOLUTION = 8  # cells per axis at least
WEIGHT_STRIDE = 4  # every 4th pixel of every 4th row (more when there would be too many rays)
WEIGHT_MAX_RAYS = 1 << 21  # training rays rendered at most
WEIGHT_DILATE = 1  # marked cells grow by this many cells
SPACING_CAMERAS = 32  # cameras whose neighbouring rays measure the rays' spacing


class WeightGrid(NamedTuple):
    """Cells of the box [lower, upper] where training rays put weight: ``grid`` bool [R, R, R]
    (indexed x, y, z; on the CPU), ``info`` its figures."""

    grid: torch.Tensor
    lower: list
    upper: list
    info: dict


@torch.no_grad()
def sample_weights(model, cfg, origins, directions):
    """Yields (positions [m, 3], weights [m]) of the samples that rendering the rays (
    ``origins``, ``directions`` [n_rays, 3], one chunk) composites with the run's model, in
    parts: an occupancy-grid run's marched samples round by round (each weight times the
    transmittance earlier rounds left, as :func:`warpnerf.render.render_marched` renders),
    an MLP run's final pass (the fine samples with a fine network). Densities only, no
    colours; eager (never the CUDA-graph path)."""
    if model.grid is not None:
        yield from _marched(model, cfg, origins, directions)
    else:
        yield _stratified(model, cfg, origins, directions)


def _marched(model, cfg, o, d):
    from ..field_protocol import density as field_density
    from ..field_protocol import needs_directions
    from ..ops import render_packed
    from ..render import SAMPLE_BUDGET

    grid, field = model.grid, model.coarse
    n, dev, dt = o.shape[0], o.device, o.dtype
    near = torch.full((n,), float(cfg.near), device=dev, dtype=dt)
    far = torch.full((n,), float(cfg.far), device=dev, dtype=dt)
    trans = torch.ones(n, device=dev, dtype=dt)
    k = torch.zeros(n, device=dev, dtype=torch.int32)
    alive = torch.arange(n, device=dev)
    cap = int(cfg.max_samples)
    per_round = int(cfg.round_samples) or cap
    budget = per_round * n
    while alive.numel():
        per_ray = min(max(per_round, budget // alive.numel()), cap)
        oa, da = o[alive], d[alive]
        smp, k_next = grid.march(oa, da, near[alive], far[alive], k_begin=k[alive],
                                 max_samples=per_ray)  # fmt: skip
        ri = smp.ray_indices
        pos = oa[ri] + da[ri] * smp.midpoints().unsqueeze(-1)
        sd = da[ri] if needs_directions(field) else None  # (NeuS: the samples' directions)
        sig = torch.cat([field_density(field, pos[s : s + SAMPLE_BUDGET],
                                       None if sd is None else sd[s : s + SAMPLE_BUDGET])[0].to(dt)
                         for s in range(0, max(pos.shape[0], 1), SAMPLE_BUDGET)])  # fmt: skip
        _, _, op, w = render_packed(
            smp.t_starts, smp.t_ends, ri, sig, sig.new_zeros(1, 3).expand(sig.shape[0], 3),
            alive.numel(), packed_info=smp.packed_info, return_weights=True, check=False,
        )  # fmt: skip
        t_a = trans[alive]
        yield pos, w * t_a[ri]
        t_a = t_a * (1.0 - op)
        trans[alive] = t_a
        k[alive] = k_next
        alive = alive[(k_next >= 0) & (t_a >= cfg.t_threshold)]


def _stratified(model, cfg, o, d):
    from ..ops import ray_aabb_intersect, stratified_samples
    from ..ops.sampling import importance_samples

    n, dev, dt = o.shape[0], o.device, o.dtype
    near = torch.full((n,), float(cfg.near), device=dev, dtype=dt)
    far = torch.full((n,), float(cfg.far), device=dev, dtype=dt)
    aabb = cfg.aabb_box()
    if aabb is not None:  # (render_nerf's rule: rays that miss the box get no samples)
        t0, t1, hit = ray_aabb_intersect(o, d, aabb)
        near = torch.maximum(near, t0)
        far = torch.where(hit, torch.minimum(far, t1), near)
    smp = stratified_samples(near, far, cfg.n_coarse, packed=True)
    pos, w = _shaded(model.coarse, o, d, smp, cfg)
    if model.fine is not None and cfg.n_fine > 0:  # (unperturbed: the seed draws nothing)
        smp = importance_samples(smp, w, cfg.n_fine, seed=7919)
        pos, w = _shaded(model.fine, o, d, smp, cfg)
    return pos, w


def _shaded(field, o, d, smp, cfg):
    """(positions, weights) of packed samples shaded by an MLP field (render_nerf's _shade)."""
    from ..ops import render_packed

    ri = smp.ray_indices
    pos = o[ri] + d[ri] * smp.midpoints().unsqueeze(-1)
    sigmas, rgbs = field(pos, d[ri])
    *_, w = render_packed(
        smp.t_starts, smp.t_ends, ri, sigmas, rgbs, o.shape[0], background=cfg.background,
        packed_info=smp.packed_info, t_threshold=cfg.t_threshold, return_weights=True,
        check=False,
    )  # fmt: skip
    return pos, w


@torch.no_grad()
def weight_grid(model, cfg, origins, directions, lower, upper, resolution: int,
                threshold: float = WEIGHT_THRESHOLD, dilate: int = WEIGHT_DILATE,
                chunk: int | None = None, progress=None) -> tuple:  # fmt: skip
    """(bool grid [R, R, R] on the CPU, cells marked before dilation) of the rays ``origins``,
    ``directions`` [n_rays, 3] rendered with the run's model (:func:`sample_weights`, ``chunk``
    rays at a time, default cfg.chunk): a cell of the box [lower, upper] (R = ``resolution``
    cells per axis) is marked when a sample with weight >= ``threshold`` has its midpoint in
    it; then marked cells grow by ``dilate`` cells (a max filter). ``progress``: called with
    each chunk's ray count."""
    res = int(resolution)
    if res < 1 or dilate < 0 or not 0.0 < threshold <= 1.0:
        raise ValueError(f"need resolution >= 1, dilate >= 0 and 0 < threshold <= 1, got "
                         f"{resolution}, {dilate}, {threshold}")  # fmt: skip
    dev = origins.device
    lo = torch.as_tensor(lower, dtype=torch.float32, device=dev).reshape(3)
    hi = torch.as_tensor(upper, dtype=torch.float32, device=dev).reshape(3)
    flat = torch.zeros(res**3, dtype=torch.bool, device=dev)
    n = origins.shape[0]
    chunk = int(chunk or cfg.chunk)
    for s in range(0, n, chunk):
        o, d = origins[s : s + chunk], directions[s : s + chunk]
        for pos, w in sample_weights(model, cfg, o, d):
            p = pos[w >= threshold]
            u = (p - lo) / (hi - lo)
            ok = ((u >= 0) & (u <= 1)).all(1)  # (False for NaN)
            idx = (u[ok] * res).floor().long().clamp_(0, res - 1)
            flat[(idx[:, 0] * res + idx[:, 1]) * res + idx[:, 2]] = True
        if progress is not None:
            progress(o.shape[0])
    grid = flat.reshape(res, res, res)
    marked = int(grid.sum())
    if dilate > 0 and marked:
        k = 2 * dilate + 1
        grid = torch.nn.functional.max_pool3d(grid[None, None].float(), k, stride=1,
                                              padding=dilate)[0, 0] > 0  # fmt: skip
    return grid.cpu(), marked


def _pixels(n_cams: int, width: int, height: int, stride: int, max_rays: int) -> tuple:
    """(stride, camera index, px, py [m]) of the strided pixel centres of every camera: the
    stride grows until at most ``max_rays`` are left."""
    while n_cams * math.ceil(width / stride) * math.ceil(height / stride) > max_rays:
        stride += 1
        if stride > max(width, height):  # one pixel a camera is still too many: spread cameras
            break
    xs = torch.arange(stride // 2, width, stride, dtype=torch.float32) + 0.5
    ys = torch.arange(stride // 2, height, stride, dtype=torch.float32) + 0.5
    cams = torch.arange(n_cams)
    if n_cams * len(xs) * len(ys) > max_rays:
        cams = torch.linspace(0, n_cams - 1, max(1, max_rays // (len(xs) * len(ys)))).round()
        cams = cams.long().unique()
    c, y, x = torch.meshgrid(cams, torch.arange(len(ys)), torch.arange(len(xs)), indexing="ij")
    return stride, c.reshape(-1), xs[x.reshape(-1)], ys[y.reshape(-1)]


def _ray_spacing(cfg, ds, stride: int, centre) -> float:
    """The median over cameras (up to :data:`SPACING_CAMERAS`) of the distance between two
    rays ``stride`` pixels apart through the image's centre, where they pass nearest to
    ``centre`` (inf where it is behind them)."""
    from .nerf_run import dataset_rays

    n = ds.c2w.shape[0]
    cams = torch.linspace(0, n - 1, min(n, SPACING_CAMERAS)).round().long().unique()
    k = ds.intrinsics[cams].cpu()
    cx, cy = k[:, 2], k[:, 3]
    cam = cams.repeat_interleave(2).to(ds.c2w.device)
    px = torch.stack([cx, cx + stride], 1).reshape(-1).to(ds.c2w.device)
    py = torch.stack([cy, cy], 1).reshape(-1).to(ds.c2w.device)
    o, d = dataset_rays(cfg, ds, cam_idx=cam, px=px, py=py)
    c = torch.as_tensor(centre, dtype=o.dtype, device=o.device)
    t = ((c - o) * d).sum(-1)
    p = (o + t.unsqueeze(-1) * d).reshape(-1, 2, 3)
    gap = (p[:, 1] - p[:, 0]).norm(dim=-1)
    gap = torch.where((t.reshape(-1, 2) > 0).all(1) & torch.isfinite(gap), gap, math.inf)
    return float(gap.median())


@torch.no_grad()
def training_weight_grid(model, cfg, ds, lower, upper, *, resolution: int = WEIGHT_RESOLUTION,
                         threshold: float = WEIGHT_THRESHOLD, stride: int = WEIGHT_STRIDE,
                         max_rays: int = WEIGHT_MAX_RAYS, dilate: int = WEIGHT_DILATE,
                         progress: bool = False) -> tuple:  # fmt: skip
    """The visibility grid of a run over the box [lower, upper] (the mesh's box, in the field's
    frame): (:class:`WeightGrid` or None, reason or None). ``model``, ``cfg``: the run
    (:func:`~warpnerf.train.nerf_run.load_run`: with ``--ema`` its averaged weights, what it
    renders); ``ds``: its training split (with the refined poses,
    :func:`~warpnerf.train.nerf_run.with_refined_poses`). The rule is the module's. None (and
    why) when there is nothing to judge by: no training rays, or no sample reaching
    ``threshold`` anywhere in the box (an untrained or empty field: culling by it would remove
    every face). ``info``: resolution, threshold, dilate, stride, rays, ray_spacing,
    cells_marked_fraction (before dilation) and seconds."""
    from .nerf_run import dataset_rays
    from .progress import Progress

    t0 = time.perf_counter()
    lo = [float(x) for x in lower]
    hi = [float(x) for x in upper]
    n_cams = int(ds.c2w.shape[0])
    if n_cams == 0 or ds.width < 1 or ds.height < 1:
        return None, "the training split has no rays"
    stride, cam, px, py = _pixels(n_cams, int(ds.width), int(ds.height), int(stride),
                                  int(max_rays))  # fmt: skip
    centre = [(a + b) / 2 for a, b in zip(lo, hi)]
    spacing = _ray_spacing(cfg, ds, stride, centre)
    extent = max(b - a for a, b in zip(lo, hi))
    res = int(resolution)
    if math.isfinite(spacing) and spacing > 0:
        res = min(res, max(WEIGHT_MIN_RESOLUTION, int(extent / spacing)))
    dev = ds.c2w.device
    o, d = dataset_rays(cfg, ds, cam_idx=cam.to(dev), px=px.to(dev), py=py.to(dev))
    with Progress(int(o.shape[0]), "mesh: training rays' weights", unit="ray",
                  enabled=progress) as bar:  # fmt: skip
        grid, marked = weight_grid(model, cfg, o, d, lo, hi, res, threshold, dilate,
                                   progress=bar.update)  # fmt: skip
    if marked == 0:
        return None, (f"no sample of the {o.shape[0]} training rays has weight >= {threshold} "
                      "inside the box (an untrained or empty field)")  # fmt: skip
    info = {"resolution": res, "threshold": float(threshold), "dilate": int(dilate),
            "stride": int(stride), "rays": int(o.shape[0]),
            "ray_spacing": spacing if math.isfinite(spacing) else None,
            "cells_marked_fraction": marked / res**3,
            "seconds": time.perf_counter() - t0}  # fmt: skip
    return WeightGrid(grid, lo, hi, info), None
