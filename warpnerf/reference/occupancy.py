"""Pure-PyTorch twins of warpnerf.ops.occupancy (same names and signatures).

The marcher's twin is the brute force the kernel must equal: enumerate every lattice interval of
every ray and keep those whose midpoint cell is occupied (no cell skipping at all).
"""

from __future__ import annotations

import torch

from warpnerf.ops import occupancy as _op
from warpnerf.ops.occupancy import unpack_bits  # pure torch: shared, not twinned
from warpnerf.ops.sampling import Samples

from .rays import ray_aabb_intersect

# the twin of each public op, by the same name (the contraction is pure torch: shared)
__all__ = [n for n in _op.__all__ if n not in ("contract_points", "uncontract_points")]


def _geometry(aabb, res, dtype, device):
    box = torch.as_tensor(aabb, dtype=dtype, device=device).reshape(2, 3)
    return box[0], (box[1] - box[0]) / res


def grid_cell_points(cells, jitter, res, aabb):
    lo, size = _geometry(aabb, res, jitter.dtype, jitter.device)
    c = cells.long()
    ijk = torch.stack([c // (res * res), (c // res) % res, c % res], -1).to(jitter.dtype)
    return lo + (ijk + jitter) * size


def grid_ema_update(density, cells, values, decay):
    newmax = torch.full_like(density, -1.0)
    newmax.scatter_reduce_(0, cells.long(), values.clamp_min(0), reduce="amax")
    upd = newmax >= 0
    density[upd] = torch.maximum(density[upd] * decay, newmax[upd])
    return density


def grid_pack_bits(density, threshold):
    occ = (density > threshold).reshape(-1, 8).to(torch.int64)
    weights = 2 ** torch.arange(8, device=density.device)
    return (occ * weights).sum(-1).to(torch.uint8)


def march_rays(
    origins, directions, near, far, bits, res, aabb, dt, *, jitter=None, k_begin=None,
    max_samples=1024,
):  # fmt: skip
    """Reference for :func:`warpnerf.ops.occupancy.march_rays` (brute force over the lattice;
    k_next is the index after the last sample for rays stopped by the cap, else -1)."""
    n_rays, dev, dt_ = origins.shape[0], origins.device, origins.dtype
    near = torch.as_tensor(near, device=dev, dtype=dt_).expand(n_rays)
    far = torch.as_tensor(far, device=dev, dtype=dt_).expand(n_rays)
    t_in, t_out, hit = ray_aabb_intersect(origins, directions, aabb)
    t0 = torch.maximum(t_in, near)
    t1 = torch.where(hit, torch.minimum(t_out, far), t0)
    j = torch.zeros(n_rays, device=dev, dtype=dt_) if jitter is None else jitter.to(dt_)
    kb = torch.zeros(n_rays, device=dev, dtype=torch.long) if k_begin is None else k_begin.long()
    span = torch.where(t1 > t0, (t1 - t0) / dt, torch.zeros_like(t0))
    n_lat = int(torch.ceil(span.max()).item()) + 2 if n_rays else 0
    k = torch.arange(n_lat, device=dev, dtype=torch.long).expand(n_rays, n_lat)
    s = t0[:, None] + (k.to(dt_) + j[:, None]) * dt
    e = torch.minimum(s + dt, t1[:, None])
    mid = 0.5 * (s + e)
    p = origins[:, None, :] + directions[:, None, :] * mid[..., None]
    lo, size = _geometry(aabb, res, dt_, dev)
    ijk = torch.floor((p - lo) * (1.0 / size)).clamp(0, res - 1).long()
    cell = (ijk[..., 0] * res + ijk[..., 1]) * res + ijk[..., 2]
    valid = (s < t1[:, None]) & (k >= kb[:, None]) & (kb[:, None] >= 0)
    keep = valid & unpack_bits(bits)[cell]
    return _pack_kept(s, e, k, keep, max_samples)


def _pack_kept(s, e, k, keep, max_samples):
    """(Samples, k_next) of the lattice intervals [s, e] [n_rays, L] (lattice indices ``k``) kept
    by the mask ``keep``, the first ``max_samples`` of each ray; a ray stopped by the cap
    continues after its last sample (its next call may find none), else k_next is -1."""
    n_rays, dev = keep.shape[0], keep.device
    keep = keep & (torch.cumsum(keep.long(), 1) <= max_samples)
    counts = keep.sum(1)
    last = torch.where(keep, k, torch.full_like(k, -1)).amax(1) if s.shape[1] else counts - 1
    k_next = torch.where(counts == max_samples, last + 1, -1).to(torch.int32)
    starts = torch.cumsum(counts, 0) - counts
    ray_indices = torch.arange(n_rays, device=dev).repeat_interleave(counts).to(torch.int32)
    info = torch.stack([starts, counts], -1).to(torch.int32)
    return Samples(s[keep], e[keep], ray_indices, info), k_next


def _lattice_t(s, dt, cone):
    if cone <= 0:
        return s * dt
    return torch.where(s * cone <= 1, s * dt, dt / cone * torch.exp(cone * s - 1))


def contracted_lattice(origins, directions, near, far, res, a, dt, cone, jitter=None, n_lat=None):
    """Every lattice interval of every ray in the contracted scheme (kernels/occupancy.py), as
    dense [n_rays, n_lat] tensors: starts, ends, valid (before far) and the contracted
    midpoints' cell indices, plus the midpoints' distance to the nearest cell face in cells."""
    n_rays, dev, dt_ = origins.shape[0], origins.device, origins.dtype
    near = torch.as_tensor(near, device=dev, dtype=dt_).expand(n_rays)
    far = torch.as_tensor(far, device=dev, dtype=dt_).expand(n_rays)
    s0, s1 = _op.lattice_s(near, dt, cone), _op.lattice_s(far, dt, cone)
    j = torch.zeros(n_rays, device=dev, dtype=dt_) if jitter is None else jitter.to(dt_)
    if n_lat is None:
        n_lat = int(torch.ceil((s1 - s0).clamp_min(0).max()).item()) + 2 if n_rays else 0
    k = torch.arange(n_lat, device=dev, dtype=dt_).expand(n_rays, n_lat)
    sk = s0[:, None] + k + j[:, None]
    s = _lattice_t(sk, dt, cone)
    e = torch.minimum(_lattice_t(sk + 1, dt, cone), far[:, None])
    p = origins[:, None, :] + directions[:, None, :] * (0.5 * (s + e))[..., None]
    u = (_op.contract_points(p, a) + 2 * a) * (res / (4 * a))
    ijk = torch.floor(u).clamp(0, res - 1).long()
    cell = (ijk[..., 0] * res + ijk[..., 1]) * res + ijk[..., 2]
    face = (u - torch.round(u)).abs().amin(-1)
    return s, e, s < far[:, None], cell, face


def march_rays_contracted(
    origins, directions, near, far, bits, res, a, dt, cone, *, jitter=None, k_begin=None,
    max_samples=1024,
):  # fmt: skip
    """Reference for :func:`warpnerf.ops.occupancy.march_rays_contracted` (brute force over
    the lattice, every interval tested)."""
    n_rays, dev = origins.shape[0], origins.device
    s, e, valid, cell, _ = contracted_lattice(
        origins, directions, near, far, res, a, dt, cone, jitter
    )
    k = torch.arange(s.shape[1], device=dev).expand_as(s)
    kb = torch.zeros(n_rays, device=dev, dtype=torch.long) if k_begin is None else k_begin.long()
    keep = valid & (k >= kb[:, None]) & (kb[:, None] >= 0) & unpack_bits(bits)[cell]
    return _pack_kept(s, e, k, keep, max_samples)


def live_samples(samples, sigmas, t_threshold):
    """Reference for :func:`warpnerf.ops.occupancy.live_samples`."""
    info = samples.packed_info
    tau = sigmas * (samples.t_ends - samples.t_starts)
    n_rays = info.shape[0]
    n_live = torch.zeros(n_rays, dtype=torch.int32, device=tau.device)
    keep = torch.zeros(tau.shape[0], dtype=torch.bool, device=tau.device)
    for r in range(n_rays):
        s, c = int(info[r, 0]), int(info[r, 1])
        acc = torch.zeros((), dtype=tau.dtype, device=tau.device)
        for i in range(s, s + c):
            if torch.exp(-acc) < t_threshold:
                break
            keep[i] = True
            n_live[r] += 1
            acc = acc + tau[i]
    return keep, n_live


def sample_points(samples, origins, directions):
    """Reference for :func:`warpnerf.ops.occupancy.sample_points`."""
    ri = samples.ray_indices.long()
    return origins[ri] + directions[ri] * samples.midpoints().unsqueeze(-1)


def live_samples_fixed(samples, sigmas, t_threshold, capacity, positions=None, directions=None):
    """Reference for :func:`warpnerf.ops.occupancy.live_samples_fixed`: each live sample
    scattered to its slot (ray order), the other slots holding sample 0."""
    ts, te, info = samples.t_starts, samples.t_ends, samples.packed_info
    ri = samples.ray_indices.long()
    n, dev = ts.shape[0], ts.device
    live = live_samples(samples, sigmas, t_threshold)[1].long()
    start = info[:, 0].long()
    keep = (torch.arange(n, device=dev) - start[ri]) < live[ri]  # (unused slots: ray 0, past it)
    csum = torch.cumsum(live, 0)
    first = csum - live
    kept_n = torch.minimum((capacity - first).clamp_min(0), live)
    dest = first[ri] + torch.arange(n, device=dev) - start[ri]
    dest = torch.where(keep & (dest < capacity), dest, torch.full_like(dest, capacity))
    src = torch.zeros(capacity + 1, device=dev, dtype=torch.int64)
    src.scatter_(0, dest, torch.arange(n, device=dev))  # (the dump slot's winner is unused)
    src = src[:capacity]
    total = csum[-1] if live.numel() else torch.zeros((), device=dev, dtype=torch.int64)
    stats = torch.stack([total, (total - capacity).clamp_min(0)])
    packed = torch.stack([first.clamp_max(capacity), kept_n], -1).to(torch.int32)
    kept = Samples(ts[src], te[src], samples.ray_indices[src], packed)
    if positions is None:
        return kept, src, stats, None, None
    return kept, src, stats, positions[src], directions[samples.ray_indices[src].long()]
