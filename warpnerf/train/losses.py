"""Every loss term of a NeRF/VolSDF step, written once: the eager step
(:meth:`warpnerf.train.nerf.NeRFTask.loss`) and the static-shape step captured in a CUDA graph
(:mod:`warpnerf.train.graph_step`) both call these, so a term added here is in both.

Each term is a mean over the step's rays. The captured step works on a fixed number of ray
slots of which ``n`` are used: it passes ``mask`` (1 for a used slot, 0 for an unused one) and
``n`` (a 0-dim tensor, so that no host sync is needed); the eager step passes neither.
"""

from __future__ import annotations

import torch

from .recipe import HUBER_DELTA

__all__ = [
    "ray_mean", "photometric", "huber", "composite_target", "opacity_term", "eikonal_term",
    "TERMS",
]  # fmt: skip

# the terms a step may record besides the loss, by name (history keys)
TERMS = ("psnr", "distortion", "near", "depth", "beta", "mask")

OPACITY_EPS = 1e-3  # the opacity is clamped to [eps, 1 - eps] in the cross-entropy (finite log)


def ray_mean(x: torch.Tensor, mask: torch.Tensor | None = None, n=None) -> torch.Tensor:
    """The mean of per-ray values ``x`` [n_rays] over the used rays: ``x.mean()`` without
    ``mask``, else ``sum(x * mask) / n``."""
    if mask is None:
        return x.mean()
    return (x * mask).sum() / n


def huber(pred: torch.Tensor, target: torch.Tensor, delta: float = HUBER_DELTA) -> torch.Tensor:
    """instant-ngp's Huber loss per element: ``x^2 / (2 delta)`` for ``|x| < delta``, else
    ``|x| - delta / 2`` (x = pred - target; the gradient is x / delta, clipped to +-1). This is
    torch's ``smooth_l1_loss`` with ``beta = delta``, i.e. ``huber_loss / delta``."""
    x = pred - target
    a = x.abs()
    return torch.where(a < delta, (0.5 / delta) * x * x, a - 0.5 * delta)


def photometric(rgb, target, kind: str = "mse", mask=None, n=None) -> tuple:
    """(loss, mse) of rendered colours ``rgb`` [n_rays, 3] against ``target`` [n_rays, 3]: the
    rays' mean of the channels' mean squared error (``kind`` "mse") or Huber loss ("huber");
    ``mse`` (detached: the PSNR the history shows) is the squared error either way."""
    se = ((rgb - target) ** 2).mean(-1)
    mse = ray_mean(se, mask, n)
    if kind == "huber":
        return ray_mean(huber(rgb, target).mean(-1), mask, n), mse.detach()
    if kind != "mse":
        raise ValueError(f"photometric loss must be mse or huber, got {kind!r}")
    return mse, mse.detach()


def composite_target(pixels, alpha, background, dataset_background: float):
    """The training target of pixels ``pixels`` [n, 3] (composited onto the dataset's
    background, a grey level ``dataset_background``) whose alpha is ``alpha`` [n] (None: opaque)
    seen over ``background`` [n, 3] instead: ``pixels + (1 - alpha) (background - b)``; exact
    (compositing, ``rgb a + b (1 - a)``, is linear in the background)."""
    if alpha is None:
        return pixels
    return pixels + (1.0 - alpha).unsqueeze(-1) * (background - dataset_background)


def opacity_term(opacity, alpha, mask=None, n=None, pixels: str = "all") -> torch.Tensor:
    """The rays' mean binary cross-entropy of the rendered opacity ``opacity`` [n] against the
    pixels' alpha ``alpha`` [n] (instant-nsr-pl's mask loss): ``-(a log o + (1 - a) log(1 - o))``
    with ``o`` clamped to [eps, 1 - eps] (:data:`OPACITY_EPS`), so a ray that is fully opaque or
    empty where its alpha says otherwise has a finite loss and gradient (none once clamped).
    ``pixels="background"``: only the rays of pixels with alpha below 0.5 count (the others add
    0; the mean stays over all rays)."""
    o = opacity.clamp(OPACITY_EPS, 1.0 - OPACITY_EPS)
    a = alpha.to(o.dtype)
    bce = -(a * torch.log(o) + (1.0 - a) * torch.log1p(-o))
    if pixels == "background":
        bce = bce * (a < 0.5).to(bce.dtype)
    elif pixels != "all":
        raise ValueError(f"pixels must be 'all' or 'background', got {pixels!r}")
    return ray_mean(bce, mask, n)


def eikonal_term(field, box_points, aux=None, aux_count=None) -> torch.Tensor:
    """VolSDF's eikonal term: the mean of ``field.eikonal`` at the step's rendered samples
    (``aux``, from the field's auxiliary losses; None when no sample was coloured) and at random
    points of the box ``box_points`` [m, 3], averaged; the box points' term alone when there is
    no rendered sample. ``aux_count`` (a 0-dim tensor, the captured step): the number of
    rendered samples, compared on the device instead of testing ``aux`` on the host."""
    box_term = field.eikonal(box_points)
    if aux is None:
        return box_term
    if aux_count is None:
        return 0.5 * (aux + box_term)
    return torch.where(aux_count > 0, 0.5 * (aux + box_term), box_term)
