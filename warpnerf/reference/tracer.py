"""Pure-PyTorch twin of warpnerf.ops.tracer (same names and signatures): every ray's samples
marched at once by the brute-force marcher twin, the field evaluated once, compositing in closed
form (exclusive cumulative sums in log space) with the tracer's early-termination and
colour-skip rules. No rounds: the kernel's rounds must not change the image."""

from __future__ import annotations

import torch

from warpnerf.ops.tracer import COLOR_WEIGHT_EPS, MAX_STEPS, MIN_STEPS, steps_per_round

from .occupancy import march_rays, march_rays_contracted

__all__ = ["trace_rays", "steps_per_round", "COLOR_WEIGHT_EPS", "MIN_STEPS", "MAX_STEPS"]


def trace_rays(
    origins, directions, near, far, bits, res, aabb, dt, density_fn, color_fn, *, contract=0.0,
    cone=0.0, color_all=False, background=1.0, t_threshold=1e-4, color_eps=COLOR_WEIGHT_EPS,
    min_steps=MIN_STEPS, max_steps=MAX_STEPS,
):  # fmt: skip
    """Reference for :func:`warpnerf.ops.tracer.trace_rays`, in the dtype of the rays and of
    what ``density_fn`` returns (``min_steps`` / ``max_steps`` only shape the kernel's rounds:
    unused here). ``n_rounds`` is 1."""
    n_rays, dev = origins.shape[0], origins.device
    big = 1 << 30
    if contract:
        smp, _ = march_rays_contracted(origins, directions, near, far, bits, res, contract, dt,
                                       cone, max_samples=big)  # fmt: skip
    else:
        smp, _ = march_rays(origins, directions, near, far, bits, res, aabb, dt, max_samples=big)
    ri = smp.ray_indices.long()
    mid = 0.5 * (smp.t_starts + smp.t_ends)
    pos = origins[ri] + directions[ri] * mid.unsqueeze(-1)
    sig, ctx = density_fn(pos, directions[ri])
    dt_ = sig.dtype
    tau = sig * (smp.t_ends - smp.t_starts).to(dt_)
    csum = torch.cumsum(tau, 0)
    start = smp.packed_info[:, 0].long()
    first = torch.zeros(n_rays, device=dev, dtype=dt_)
    has = smp.packed_info[:, 1] > 0
    first[has] = (csum - tau)[start[has]]
    log_t = -(csum - tau - first[ri])  # exclusive: sum over the ray's earlier samples
    trans = torch.exp(log_t)
    live = trans >= t_threshold  # T only falls: the samples before the first one below
    w = torch.where(live, trans * -torch.expm1(-tau), torch.zeros_like(tau))
    if color_all:
        rgbs = color_fn(ctx, None).to(dt_)
        seen = torch.arange(w.shape[0], device=dev)
    else:
        seen = torch.nonzero(w >= color_eps).squeeze(1)
        rgbs = color_fn(ctx, seen).to(dt_)
    rgb = torch.zeros(n_rays, 3, device=dev, dtype=dt_)
    rgb.index_add_(0, ri[seen], w[seen].unsqueeze(-1) * rgbs)
    depth = torch.zeros(n_rays, device=dev, dtype=dt_).index_add_(0, ri, w * mid.to(dt_))
    kept_tau = torch.zeros(n_rays, device=dev, dtype=dt_).index_add_(0, ri, tau * live)
    t_end = torch.exp(-kept_tau)
    bg = torch.as_tensor(background, device=dev, dtype=dt_)
    rgb = rgb + t_end.unsqueeze(-1) * (bg.expand(3) if bg.dim() == 0 else bg)
    return {"rgb": rgb, "depth": depth, "opacity": 1.0 - t_end,
            "n_marched": int(smp.t_starts.shape[0]), "n_rounds": 1}  # fmt: skip
