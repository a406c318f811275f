"""Rendering with an occupancy grid by instant-ngp's tracer (:func:`render_traced`): the
no-gradient path of :func:`warpnerf.render.render_marched`. Per-ray state on the device, a
compacted list of live rays, each round marching every live ray a few samples into fixed slots,
one field call on the round's slots and one compositing kernel with early termination
(kernels/tracer.py, bridged by :func:`warpnerf.ops.tracer.trace_rays`)."""

from __future__ import annotations

import torch

from .field_protocol import density as field_density
from .ops.tracer import COLOR_WEIGHT_EPS, MAX_STEPS, MIN_STEPS, trace_rays

__all__ = ["render_traced", "TRACE_COLORS", "SAMPLE_BUDGET"]

SAMPLE_BUDGET = 1 << 23  # rendering: most samples the field sees in one call (memory bound)

TRACE_COLORS = ("weighted", "all")  # colours of the samples that weigh, or of every sample


def render_traced(
    grid,
    field,
    origins: torch.Tensor,  # [n_rays, 3] float32
    directions: torch.Tensor,  # [n_rays, 3] unit length
    near,  # float or [n_rays]
    far,  # float or [n_rays]
    *,
    background=1.0,  # float, [3] or [n_rays, 3]
    t_threshold: float = 1e-4,
    half: bool = False,
    sample_budget: int = SAMPLE_BUDGET,
    colors: str = "weighted",
    min_steps: int = MIN_STEPS,
    max_steps: int = MAX_STEPS,
) -> dict:
    """Renders rays through ``grid`` (:class:`warpnerf.OccupancyGrid`, bounded or contracted)
    with ``field`` (``density(positions) -> (sigmas, features)``, ``color(features,
    directions) -> rgbs``), without gradients.

    The samples are the grid's lattice intervals in occupied cells (``grid.march``'s, no
    jitter). Rays march in rounds over a compacted list of live rays: each live ray gets
    ``clamp(n_rays // n_live, min_steps, max_steps)`` slots (instant-ngp's rule: a round holds
    about ``n_rays`` samples), the field's density runs once on the round's slots, each ray's
    samples are composited in order onto its transmittance, stopping at the first one with
    T < ``t_threshold`` (the compositing kernels' rule), and rays that are done or opaque leave
    the list. ``colors="weighted"`` (the default) runs the colour MLP only on samples whose
    weight in the image reaches ``COLOR_WEIGHT_EPS`` (1e-5; the others count as black, as in the
    rounds path with ``color_eps=COLOR_WEIGHT_EPS, color_fill="black"``, its rule before
    2026-12-03), at the cost of a gather and a scatter of those samples; ``"all"`` runs it on
    every slot of the round with the densities (no gather; more MLP work: every slot, unused ones
    included). ``half`` (CUDA only) runs the MLPs under float16 autocast; compositing stays
    float32. ``sample_budget``: most samples the field sees in one call (larger rounds are
    evaluated in slices; with ``colors="weighted"`` the features are then recomputed for the
    samples to colour).

    Host syncs: one after priming (live count and refused rays), one per round (next live count,
    slots to colour, samples marched). The image equals the rounds path's with that colour
    rule (``render_marched(..., tracer="rounds", color_eps=COLOR_WEIGHT_EPS,
    color_fill="black")``) up to float error, the samples behind the point
    where T < ``t_threshold`` (which the rounds path composites: at most T < t_threshold of
    weight) and the colour-skip rule (``tests/test_tracer.py``).

    Returns a dict of rgb [n_rays, 3], depth, opacity [n_rays] and the ints ``n_marched``
    (samples marched), ``n_kept`` (the same) and ``n_rounds``.
    """
    if colors not in TRACE_COLORS:
        raise ValueError(f"colors must be one of {TRACE_COLORS}, got {colors!r}")
    use_half = half and origins.device.type == "cuda"
    color_all = colors == "all"

    def autocast():
        return torch.autocast("cuda", dtype=torch.float16, enabled=use_half)

    def density_fn(pos, dirs):
        n = pos.shape[0]
        with torch.no_grad(), autocast():
            if n <= sample_budget:  # one call; the colour head reuses its features
                sig, feats = field_density(field, pos, dirs)
                rgbs = field.color(feats, dirs) if color_all else None
                return sig, (pos, dirs, feats, rgbs)
            sigs, rgbs = [], []
            for s in range(0, n, sample_budget):  # bounded memory
                sl = slice(s, s + sample_budget)
                sig, feats = field_density(field, pos[sl], dirs[sl])
                sigs.append(sig)
                if color_all:
                    rgbs.append(field.color(feats, dirs[sl]))
        return torch.cat(sigs), (pos, dirs, None, torch.cat(rgbs) if color_all else None)

    def color_fn(ctx, idx):
        pos, dirs, feats, rgbs = ctx
        if idx is None:
            return rgbs
        with torch.no_grad(), autocast():
            if feats is not None:
                return field.color(feats[idx], dirs[idx])
            return torch.cat([field.color(field_density(field, pos[sl], dirs[sl])[1], dirs[sl])
                              for sl in idx.split(sample_budget)])  # fmt: skip

    out = trace_rays(
        origins, directions, near, far, grid.bits, grid.res, grid.box, grid.dt, density_fn,
        color_fn, contract=grid.contract, cone=grid.cone, color_all=color_all,
        background=background, t_threshold=t_threshold, color_eps=COLOR_WEIGHT_EPS,
        min_steps=min_steps, max_steps=max_steps,
    )  # fmt: skip
    out["n_kept"] = out["n_marched"]
    return out
