"""Rendering with proposal sampling (:func:`render_proposal`, ``--sampler proposal``): each ray's
samples placed by nerfacto's proposal networks (:class:`warpnerf.fields.proposal.ProposalSampler`)
instead of marching an occupancy grid. Every ray has the same number of samples at every level,
so all shapes are fixed by the number of rays."""

from __future__ import annotations

import torch

from .field_protocol import density as field_density
from .ops import render_packed
from .ops.distortion import distortion_loss
from .ops.proposal import interlevel_loss, proposal_resample
from .render_marched import weight_before

__all__ = ["render_proposal", "uniform_edges"]


def uniform_edges(n_rays: int, n: int, jitter, device, dtype) -> torch.Tensor:
    """``n + 1`` edges in [0, 1] per ray ``[n_rays, n + 1]``: ``linspace(0, 1, n + 1)``, or with
    ``jitter`` [n_rays] each edge moved to ``lower + (upper - lower) U`` between the midpoints
    of its neighbouring bins (nerfacto's ``UniformSampler`` with a single jitter: sorted, first
    edge in [0, 1/(2n)], last in [1 - 1/(2n), 1])."""
    grid = torch.linspace(0, 1, n + 1, device=device, dtype=dtype)
    if jitter is None:
        return grid.expand(n_rays, n + 1)
    mid = 0.5 * (grid[1:] + grid[:-1])
    lower, upper = torch.cat([grid[:1], mid]), torch.cat([mid, grid[-1:]])
    return lower + (upper - lower) * jitter.to(dtype).unsqueeze(-1)


def _intervals(sampler, s, origins, directions):
    """(t_starts [n], t_ends [n], ray_indices [n], packed_info, positions [n, 3]) of the
    intervals between consecutive edges ``s`` [n_rays, k + 1], row by row."""
    n_rays, k = s.shape[0], s.shape[1] - 1
    t = sampler.t_of_s(s)
    t0, t1 = t[:, :-1].reshape(-1), t[:, 1:].reshape(-1)
    ri = torch.arange(n_rays, device=s.device).repeat_interleave(k)
    starts = torch.arange(n_rays, device=s.device, dtype=torch.int32) * k
    info = torch.stack([starts, torch.full_like(starts, k)], -1)
    pos = origins[ri] + directions[ri] * (0.5 * (t0 + t1)).unsqueeze(-1)
    return t0, t1, ri, info, pos


def render_proposal(
    sampler,
    field,
    origins: torch.Tensor,  # [n_rays, 3]
    directions: torch.Tensor,  # [n_rays, 3] unit length
    near,  # float or [n_rays]
    far,  # float or [n_rays]
    *,
    perturb: bool = False,
    generator: torch.Generator | None = None,
    jitter: torch.Tensor | None = None,  # [n_rays, sampler.n_draws] in [0, 1)
    background=1.0,
    t_threshold: float = 1e-4,
    ray_images: torch.Tensor | None = None,
    distortion=False,
    near_t=None,
    on_weights=None,
) -> dict:
    """Volume rendering of rays with proposal sampling.

    Level 0's edges are uniform in the sampler's coordinate s between near and far (jittered
    when ``perturb``: draws from ``generator`` on the rays' device, or given as ``jitter``, one
    column per level and one for the field's samples); each proposal network composites its
    densities at its intervals' midpoints into weights, which :func:`proposal_resample` turns
    into the next level's edges (deterministic midpoints without jitter), the last level's into
    the field's ``sampler.final`` intervals. The field (``density``/``color``, as for
    :func:`warpnerf.render.render_marched`) is composited onto ``background``.

    Returns a dict of rgb [n_rays, 3], depth, opacity [n_rays]; with gradients also
    ``interlevel`` [n_rays] (each ray's interlevel loss summed over the proposal levels, divided
    by the field's samples: nerfacto's mean over intervals) and, with ``distortion``,
    ``distortion`` [n_rays] (:func:`warpnerf.ops.distortion_loss` of the field's weights in s,
    the sampler's coordinate; ``distortion`` may instead be a map of ray distances t to another
    normalised coordinate, as :func:`~warpnerf.render.render_marched`'s ``distortion_s``) and,
    with ``near_t`` (a float or [n_rays]), ``near_weight`` [n_rays]: each ray's weight before
    that distance (:func:`~warpnerf.render_marched.weight_before`). ``on_weights``: called once
    with ``(ray_indices, t_starts, t_ends, weights)`` of the field's samples (as
    :func:`~warpnerf.render.render_marched`'s).
    """
    n_rays, dev, dt = origins.shape[0], origins.device, origins.dtype
    near = torch.as_tensor(near, device=dev, dtype=dt).expand(n_rays)
    far = torch.as_tensor(far, device=dev, dtype=dt).expand(n_rays)
    if jitter is None and perturb:
        jitter = torch.rand(n_rays, sampler.n_draws, device=dev, generator=generator)
    s_near, s_far = sampler.s_of_t(near), sampler.s_of_t(far)
    unit = uniform_edges(n_rays, sampler.samples[0], None if jitter is None else jitter[:, 0],
                         dev, dt)  # fmt: skip
    s = s_near.unsqueeze(-1) + (s_far - s_near).unsqueeze(-1) * unit
    levels = []
    counts = (*sampler.samples[1:], sampler.final)
    for i, (net, n_next) in enumerate(zip(sampler.nets, counts)):
        t0, t1, ri, info, pos = _intervals(sampler, s, origins, directions)
        sig = net(pos)
        *_, w = render_packed(t0, t1, ri, sig, sig.new_zeros(1, 3).expand(sig.shape[0], 3),
                              n_rays, packed_info=info, t_threshold=t_threshold, check=False,
                              return_weights=True)  # fmt: skip
        w = w.reshape(n_rays, -1)
        levels.append((s, w))
        u = None if jitter is None else jitter[:, i + 1]
        s = proposal_resample(s, w, n_next, jitter=u, anneal=sampler.anneal.to(dt), check=False)
    t0, t1, ri, info, pos = _intervals(sampler, s, origins, directions)
    sig, feats = field_density(field, pos, lambda: directions[ri])
    kw = {} if ray_images is None else {"image_ids": ray_images[ri]}
    rgbs = field.color(feats, directions[ri], **kw)
    rgb, depth, opacity, w = render_packed(
        t0, t1, ri, sig, rgbs, n_rays, background=background, packed_info=info,
        t_threshold=t_threshold, check=False, return_weights=True,
    )  # fmt: skip
    out = {"rgb": rgb, "depth": depth, "opacity": opacity}
    if on_weights is not None:
        on_weights(ri, t0, t1, w)
    if torch.is_grad_enabled():
        w_fine = w.detach().reshape(n_rays, -1)
        loss = sum(interlevel_loss(s, w_fine, sp, wp, check=False) for sp, wp in levels)
        out["interlevel"] = loss / sampler.final
        if distortion:  # True: the sampler's own coordinate s
            s0, s1 = ((s[:, :-1].reshape(-1), s[:, 1:].reshape(-1)) if distortion is True
                      else (distortion(t0), distortion(t1)))  # fmt: skip
            out["distortion"] = distortion_loss(s0, s1, ri, w, n_rays, packed_info=info,
                                                check=False)  # fmt: skip
        if near_t is not None:
            out["near_weight"] = weight_before(t0, t1, ri, w, info, near_t)
    return out
