"""Debug: float32 Warp compositing vs float64 twin on one device (prints errors and samples)."""

import sys

import torch

import warpnerf as wn
from warpnerf import reference as R

dev = torch.device(sys.argv[1] if len(sys.argv) > 1 else "cpu")
n_rays, ns = 4096, 128
near = torch.full((n_rays,), 2.0, device=dev)
far = torch.full((n_rays,), 6.0, device=dev)
smp = wn.stratified_samples(near, far, ns, perturb=True, seed=1, packed=True)
n = smp.t_starts.shape[0]
g = torch.Generator().manual_seed(0)
sig = (torch.exp(torch.empty(n).uniform_(-4, 4, generator=g)) * 0.3).to(dev)
rgbs = torch.rand(n, 3, generator=g).to(dev)
args = (smp.t_starts, smp.t_ends, smp.ray_indices)
rgb, depth, op = wn.render_packed(
    *args, sig, rgbs, n_rays, background=1.0, packed_info=smp.packed_info
)
r64, d64, o64 = R.render_packed(
    *(a.double() if a.is_floating_point() else a for a in args),
    sig.double(),
    rgbs.double(),
    n_rays,
    background=1.0,
    packed_info=smp.packed_info,
)
r32, _, _ = R.render_packed(*args, sig, rgbs, n_rays, background=1.0, packed_info=smp.packed_info)
print(dev, "rgb dtype", rgb.dtype, r64.dtype)
print("warp32 vs ref64", (rgb.double() - r64).abs().max().item())
print("ref32 vs ref64", (r32.double() - r64).abs().max().item())
print("warp32 - ref32", (rgb - r32).abs().max().item())
print("samples", rgb[:2].tolist(), r64[:2].tolist())
print(
    "t_starts dtype",
    smp.t_starts.dtype,
    "sig sum",
    sig.sum().item(),
    "opacity mean",
    op.mean().item(),
)
