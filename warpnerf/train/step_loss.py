"""The loss of a NeRF/VolSDF training step, assembled once (:func:`step_loss`): the eager step
(:meth:`warpnerf.train.nerf.NeRFTask.loss`) and the static-shape step a CUDA graph holds
(:mod:`warpnerf.train.graph_step`) both call it, with the terms of :mod:`~warpnerf.train.losses`.

The loss, in this order of sums (each a mean over the step's rays unless said):

- the photometric term (``--photometric-loss``), against the targets composited onto the rays'
  random backgrounds (``--random-background``);
- ``mask_w`` x the opacity's cross-entropy against the pixels' alpha (``--mask-loss``);
- ``distortion_w`` x mip-NeRF 360's distortion loss (when the renderer returned it);
- ``near_w`` x each ray's compositing weight nearer than ``--near-loss-frac`` x its camera's
  distance to the scene centre (``--near-loss``; when the renderer returned it);
- ``interlevel_w`` x mip-NeRF 360's interlevel loss of the proposal networks (``--sampler
  proposal``: when the renderer returned it);
- ``depth_w`` x the depth prior at sparse points (``--depth-loss``; computed by the caller);
- the coarse pass's photometric term (a run with a fine pass);
- ``eikonal_w`` x VolSDF's eikonal term at the rendered samples and random box points (an SDF
  field; not scaled: every rank computes the whole term).

A data-parallel rank passes ``scale`` (its share of the global batch times the ranks) and
``dist``; the captured step passes ``mask``/``n`` (its used ray slots, see losses.py). Terms the
captured step cannot compute are named by :func:`unsupported_terms` (which
:func:`warpnerf.train.graph_step.unsupported` reports) and refused here, never dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .losses import composite_target, eikonal_term, opacity_term, photometric, ray_mean

__all__ = ["LossSettings", "step_loss", "unsupported_terms", "dp_eikonal"]


@dataclass(frozen=True)
class LossSettings:
    """What of a run's config and model the step's loss reads (host values, fixed for a run)."""

    photometric: str = "mse"  # "mse" or "huber"
    mask_w: float = 0.0  # the opacity term's weight (0: none)
    mask_pixels: str = "all"  # the opacity term's pixels: "all" or "background" (alpha < 0.5)
    distortion_w: float = 0.0  # the distortion loss's weight (0: none)
    near_w: float = 0.0  # the near-camera weight penalty's weight (0: none)
    interlevel_w: float = 0.0  # the proposal networks' interlevel loss weight (--sampler proposal)
    depth_w: float = 0.0  # the depth prior's weight (0: none)
    eikonal_w: float = 0.0  # the eikonal term's weight (an SDF field)
    sdf: bool = False  # an SDF field: the eikonal term, and beta in the terms
    fine: bool = False  # a fine pass: the coarse pass's photometric term too
    background: float = 1.0  # the dataset's background grey level (its pixels' composite)
    aabb: float = 1.0  # the eikonal term's box points lie in [-aabb, aabb]^3

    @classmethod
    def of(cls, cfg, model, mask_w: float) -> LossSettings:
        """The settings of a run (``mask_w``: the task's, 0 when the images have no alpha)."""
        sdf = model.kind == "sdf"
        return cls(
            photometric=cfg.photometric_loss, mask_w=float(mask_w),
            mask_pixels=getattr(cfg, "mask_pixels", "all"),
            distortion_w=float(cfg.distortion_loss), depth_w=float(cfg.depth_loss),
            near_w=float(cfg.near_loss),
            interlevel_w=float(cfg.interlevel_loss) if cfg.sampler == "proposal" else 0.0,
            eikonal_w=float(cfg.eikonal_weight) if sdf else 0.0, sdf=sdf,
            fine=model.fine is not None, background=float(cfg.background), aabb=float(cfg.aabb),
        )  # fmt: skip


def unsupported_terms(s: LossSettings, model=None, dist=None) -> str | None:
    """Why the captured step (masked ray slots, no host sync) cannot compute this loss (None:
    it can)."""
    if s.fine:
        return "it needs one field without a fine pass (--field hash or hash_sdf)"
    if s.sdf and model is not None and not hasattr(model.coarse, "eikonal"):
        return "the SDF field has no eikonal term (--field hash_sdf)"
    if dist is not None:
        return "data-parallel training is not captured yet"
    if s.depth_w > 0:
        return "--depth-loss is not captured yet"
    return None


def step_loss(
    s: LossSettings,
    model,
    out: dict,
    target: torch.Tensor,  # [n_rays, 3] the pixels (composited onto the dataset's background)
    alpha: torch.Tensor | None,  # [n_rays] or None (opaque pixels)
    background: torch.Tensor | None = None,  # [n_rays, 3] random backgrounds, or None
    mask: torch.Tensor | None = None,  # [n_rays] 1 for a used ray slot (the captured step)
    n: torch.Tensor | None = None,  # 0-dim: the used slots' count (with ``mask``)
    scale: float = 1.0,
    box: torch.Tensor | None = None,  # [m, 3] in [0, 1)^3: the eikonal term's box points
    depth: torch.Tensor | None = None,  # 0-dim: the depth prior's term (with ``depth_w`` > 0)
    dist=None,  # data parallelism (:class:`~warpnerf.train.distributed.Dist`)
) -> tuple:
    """(loss, terms) of a step's render output ``out`` (rgb, opacity, optionally distortion,
    interlevel, near_weight and rgb_coarse) against its pixels. ``terms``: psnr (the MSE),
    mask, distortion, interlevel, near, depth, beta, as the step has them (detached)."""
    if mask is not None:
        why = unsupported_terms(s, model, dist)
        if why is not None:
            raise ValueError(f"the masked (captured) step's loss: {why}")

    def scaled(x):  # (a rank's share; no op on one process)
        return x if scale == 1.0 else x * scale

    if background is not None:
        target = composite_target(target, alpha, background, s.background)
    loss, mse = photometric(out["rgb"], target, s.photometric, mask, n)
    terms = {"psnr": scaled(mse)}
    loss = scaled(loss)
    if s.mask_w > 0:  # the rendered opacity against the pixels' alpha
        mask_term = scaled(opacity_term(out["opacity"], alpha, mask, n, s.mask_pixels))
        terms["mask"] = mask_term.detach()
        loss = loss + s.mask_w * mask_term
    if "distortion" in out:  # mip-NeRF 360's distortion loss, the rays' mean
        dist_loss = scaled(ray_mean(out["distortion"], mask, n))
        terms["distortion"] = dist_loss.detach()
        loss = loss + s.distortion_w * dist_loss
    if "near_weight" in out:  # --near-loss: weight in front of the cameras, the rays' mean
        near = scaled(ray_mean(out["near_weight"], mask, n))
        terms["near"] = near.detach()
        loss = loss + s.near_w * near
    if "interlevel" in out:  # --sampler proposal: the proposal networks' loss
        inter = scaled(ray_mean(out["interlevel"], mask, n))
        terms["interlevel"] = inter.detach()
        loss = loss + s.interlevel_w * inter
    if s.depth_w > 0:  # the depth prior at sparse points (the same on every rank)
        if depth is None:
            raise ValueError("--depth-loss: the step's loss needs its depth term")
        terms["depth"] = depth.detach()
        loss = loss + s.depth_w * depth
    coarse = out.get("rgb_coarse")
    if coarse is not None and coarse.requires_grad and s.fine:
        loss = loss + scaled(photometric(coarse, target, s.photometric, mask, n)[0])
    if s.sdf:  # eikonal on the rendered samples and on random box points
        if box is None:
            raise ValueError("an SDF field's step loss needs the eikonal term's box points")
        loss = loss + s.eikonal_w * _eikonal(model, (box * 2 - 1) * s.aabb, mask, dist)
        terms["beta"] = model.coarse.beta.detach()
    return loss, terms


def _eikonal(model, box_points, mask, dist):
    """The eikonal term: one process's (its rendered samples' mean, whose count the captured
    step compares on the device), or a data-parallel rank's share (:func:`dp_eikonal`)."""
    f = model.coarse
    if dist is not None:  # (every rank draws the same box points: their term needs no exchange)
        return dp_eikonal(dist, model.eikonal_parts(), f.eikonal(box_points))
    if mask is None:
        return eikonal_term(f, box_points, model.aux_losses().get("eikonal"))
    ((aux, count),) = model.eikonal_parts()  # (one field; the count a device tensor)
    return eikonal_term(f, box_points, aux, None if aux is None else count)


def dp_eikonal(dist, parts, box_term):
    """A data-parallel rank's eikonal term, such that the ranks' average is the one process's:
    each field's mean at the rendered samples (``parts``: (mean, count) per field) becomes this
    rank's sum over the samples of every rank (their counts summed on the device, no host
    wait), times the number of ranks; without any rendered sample anywhere, the box points'
    term ``box_term`` alone."""
    dev = box_term.device
    counts = torch.tensor([float(n) for _, n in parts], dtype=torch.float64)
    if dev.type == "cuda":  # (a pinned copy does not wait for the GPU)
        counts = counts.pin_memory().to(dev, non_blocking=True)
    total = dist.sum_(counts.to(dev))
    aux = box_term.new_zeros(())
    for k, (mean, n) in enumerate(parts):
        if mean is not None:
            share = (n * dist.world / total[k].clamp_min(1.0)).to(mean.dtype)
            aux = aux + mean * share
    return torch.where(total.sum() > 0, 0.5 * (aux + box_term), box_term)
