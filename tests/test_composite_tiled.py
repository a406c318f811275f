"""The cooperative float32 kernels (composite_fwd_tiled / composite_bwd_tiled, one block per ray)
against the one-thread-per-ray kernels and the float64 twin: ray lengths around the block width,
early termination, weights, extreme optical depths, zero-length intervals and NaN."""

from __future__ import annotations

import pytest
import torch

import warpnerf as W
from warpnerf import reference as R
from warpnerf.ops import composite as C

F32, F64 = torch.float32, torch.float64


def impl(kind, block_dim=32):
    return C.composite_kernels(kind, block_dim)


def _case(device, counts, *, tau_values=None, zero_len=False, nan_ray=None, seed=0):
    g = torch.Generator().manual_seed(seed)
    counts = torch.tensor(counts)
    n_rays = counts.shape[0]
    ray_indices = torch.repeat_interleave(torch.arange(n_rays), counts)
    n = ray_indices.shape[0]
    starts = torch.cumsum(counts, 0) - counts
    k = torch.arange(n) - starts[ray_indices]
    delta = (0.02 + 0.05 * torch.rand(n, generator=g)).double()
    t_starts = 2.0 + 0.07 * k.double()
    sig = torch.exp(torch.empty(n).uniform_(-6, 4, generator=g)).double()
    if tau_values is not None:
        pick = torch.randint(0, len(tau_values), (n,), generator=g)
        sig = torch.tensor(tau_values, dtype=F64)[pick] / delta
    if zero_len:
        delta[::3] = 0.0  # zero-length intervals with finite densities
    if nan_ray is not None:
        sig[ray_indices == nan_ray] = float("nan")
    rgbs = torch.rand(n, 3, generator=g, dtype=F64)
    bg = torch.rand(n_rays, 3, generator=g, dtype=F64)
    up = [
        torch.randn(n_rays, 3, generator=g),
        torch.randn(n_rays, generator=g),
        torch.randn(n_rays, generator=g),
        torch.randn(n, generator=g),
    ]
    to = {"device": device}
    return dict(
        t_starts=t_starts.to(**to),
        t_ends=(t_starts + delta).to(**to),
        ray_indices=ray_indices.to(**to),
        sigmas=sig.to(**to),
        rgbs=rgbs.to(**to),
        bg=bg.to(**to),
        up=[u.to(**to) for u in up],
        n_rays=n_rays,
    )


def _run(lib, c, dtype, t_threshold):
    sig = c["sigmas"].to(dtype).requires_grad_()
    rgbs = c["rgbs"].to(dtype).requires_grad_()
    bg = c["bg"].to(dtype).requires_grad_()
    out = lib.render_packed(
        c["t_starts"].to(dtype),
        c["t_ends"].to(dtype),
        c["ray_indices"],
        sig,
        rgbs,
        c["n_rays"],
        bg,
        t_threshold=t_threshold,
        return_weights=True,
    )
    up = [u.to(dtype) for u in c["up"]]
    live = [(o, u) for o, u in zip(out, up) if o.requires_grad]
    grads = torch.autograd.grad(
        [o for o, _ in live], (sig, rgbs, bg), [u for _, u in live], allow_unused=True
    )
    return [x.detach() for x in out], list(grads)


COUNTS = [0, 1, 2, 31, 32, 33, 64, 65, 100, 5]


@pytest.mark.parametrize("block_dim", [4, 32])
@pytest.mark.parametrize("t_threshold", [0.0, 1e-2, 0.4])
def test_tiled_matches_sequential_and_float64(device, block_dim, t_threshold):
    c = _case(device, COUNTS)
    with impl("tiled", block_dim):
        out_t, g_t = _run(W, c, F32, t_threshold)
    with impl("sequential"):
        out_s, g_s = _run(W, c, F32, t_threshold)
    out_r, g_r = _run(R, c, F64, t_threshold)
    names = ["rgb", "depth", "opacity", "weights", "v_sigmas", "v_rgbs", "v_bg"]
    for name, t, s, r in zip(names, out_t + g_t, out_s + g_s, out_r + g_r):
        scale = max(float(r.abs().max()), 1.0)
        assert float((t.double() - s.double()).abs().max()) <= 2e-6 * scale, name
        assert float((t.double() - r).abs().max()) <= 5e-6 * scale, name


@pytest.mark.parametrize(
    "taus", [[0.0, 1e-12, 1.0], [1e3, 1e8, float("inf")], [0.0, 1e-6, 1.0, 1e8, float("inf")]]
)
def test_tiled_extreme_optical_depths(device, taus):
    c = _case(device, COUNTS, tau_values=taus, zero_len=float("inf") not in taus)
    with impl("tiled"):
        out_t, g_t = _run(W, c, F32, 0.0)
    with impl("sequential"):
        out_s, g_s = _run(W, c, F32, 0.0)
    for t, s in zip(out_t + g_t, out_s + g_s):
        assert bool(torch.isfinite(t).all())
        torch.testing.assert_close(t, s, rtol=1e-5, atol=2e-6)
    opacity = out_t[2]
    assert bool(((opacity >= 0) & (opacity <= 1 + 1e-6)).all())


def test_tiled_huge_tau_does_not_swallow_what_is_in_front(device):
    """A tau of 1e8 behind small ones: the exclusive prefix must keep the small sum exactly
    (inclusive - tau would round 0.5 + 1e8 - 1e8 to 0 in float32)."""
    c = _case(device, [3], seed=1)
    c["sigmas"] = torch.tensor([5.0, 5.0, 1e8], dtype=F64, device=device) / (
        c["t_ends"] - c["t_starts"]
    )
    c["sigmas"][:2] *= 0.05  # taus 0.25, 0.25, 1e8
    with impl("tiled"):
        (rgb, depth, opacity, weights), _ = _run(W, c, F32, 0.0)
    w = weights.double().cpu()
    expect_t2 = torch.exp(torch.tensor(-0.5, dtype=F64))
    assert abs(float(w[2]) - float(expect_t2)) < 1e-6


def test_tiled_nan_stays_in_its_ray(device):
    c = _case(device, COUNTS, nan_ray=6)
    clean = _case(device, COUNTS)
    with impl("tiled"):
        out, _ = _run(W, c, F32, 1e-2)
        ref, _ = _run(W, clean, F32, 1e-2)
    for o, r in zip(out[:3], ref[:3]):
        assert bool(torch.isnan(o[6]).all())
        keep = torch.arange(len(COUNTS), device=device) != 6
        assert torch.equal(o[keep], r[keep])


def test_default_float32_path_is_tiled():
    assert C._IMPL["float32_sigma"] == "tiled"
    assert C._use_tiled(torch.zeros(1), 0) and not C._use_tiled(torch.zeros(1, dtype=F64), 0)
    assert not C._use_tiled(torch.zeros(1), 1)
