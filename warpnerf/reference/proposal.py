"""Pure-PyTorch twins of warpnerf.ops.proposal: inverse-CDF resampling as nerfstudio's
``PDFSampler`` writes it (``searchsorted`` on the cumulative masses) and the interlevel loss as
nerfstudio's ``outer`` / ``lossfun_outer`` (two ``searchsorted`` calls and a difference of
prefix sums), with autograd's backward."""

from __future__ import annotations

import torch

__all__ = ["proposal_resample", "interlevel_loss"]


def proposal_resample(s_edges, weights, n_samples, *, jitter=None, anneal=1.0, padding=0.01,
                      check=True):  # fmt: skip
    """Reference for :func:`warpnerf.ops.proposal.proposal_resample`."""
    e, w = s_edges.detach(), weights.detach()
    n_rays, n = w.shape
    n_out = n_samples + 1
    a = torch.as_tensor(anneal, dtype=w.dtype, device=w.device).reshape(())
    powered = torch.where(w == 0, (a == 0).to(w.dtype).expand_as(w), w.pow(a))
    m = powered + padding
    total = m.sum(-1, keepdim=True)
    uniform = ~(total > 0)
    m = torch.where(uniform, torch.ones_like(m), m)
    total = torch.where(uniform, torch.full_like(total, float(n)), total)
    cdf = torch.cat([torch.zeros_like(total), torch.cumsum(m, -1)], -1)  # [n_rays, n + 1]
    j = torch.arange(n_out, dtype=w.dtype, device=w.device)
    if jitter is None:
        u = (j + 0.5).expand(n_rays, n_out)
    else:
        jit = jitter.detach().to(w.dtype)
        u = j + (jit.unsqueeze(-1) if jit.dim() == 1 else jit)
    v = u / n_out * total
    idx = (torch.searchsorted(cdf.contiguous(), v.contiguous(), right=True) - 1).clamp(0, n - 1)
    c0 = cdf.gather(-1, idx)
    mi = m.gather(-1, idx)
    e0, e1 = e.gather(-1, idx), e.gather(-1, idx + 1)
    f = torch.where(mi > 0, ((v - c0) / mi.where(mi > 0, torch.ones_like(mi))).clamp(0, 1),
                    torch.zeros_like(v))  # fmt: skip
    out = torch.minimum(e0 + f * (e1 - e0), e1)
    bad = ~(torch.isfinite(e).all(-1) & torch.isfinite(powered.sum(-1) + padding))
    return torch.where(bad.unsqueeze(-1), torch.full_like(out, float("nan")), out)


def interlevel_loss(s_fine, w_fine, s_prop, w_prop, *, eps=1e-7, check=True):
    """Reference for :func:`warpnerf.ops.proposal.interlevel_loss`: per ray,
    ``sum_i max(0, w_i - outer_i)^2 / (w_i + eps)``."""
    w = w_fine.detach()
    n_p = w_prop.shape[-1]
    cy = torch.cat([torch.zeros_like(w_prop[..., :1]), torch.cumsum(w_prop, -1)], -1)
    starts, ends = s_prop[..., :-1].contiguous(), s_prop[..., 1:].contiguous()
    lo = torch.searchsorted(starts, s_fine[..., :-1].contiguous(), right=True) - 1
    hi = torch.searchsorted(ends, s_fine[..., 1:].contiguous(), right=True)
    lo, hi = lo.clamp(0, n_p - 1), hi.clamp(0, n_p - 1)
    outer = cy[..., 1:].gather(-1, hi) - cy[..., :-1].gather(-1, lo)
    return ((w - outer).clamp_min(0) ** 2 / (w + eps)).sum(-1)
