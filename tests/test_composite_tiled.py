"""The cooperative float32 kernels (composite_fwd_tiled / composite_bwd_tiled, one block per ray)
against the one-thread-per-ray kernels and the float64 twin: ray lengths around the block width
and the chunk length, early termination, weights, extreme optical depths, zero-length intervals,
NaN, and samples no ray covers."""

from __future__ import annotations

import pytest
import torch

import warpnerf as W
from warpnerf import reference as R
from warpnerf.ops import composite as C

from ._twin import assert_finite, assert_outputs_close, run_with_grads

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


NAMES = ("rgb", "depth", "opacity", "weights")


def _run(lib, c, dtype, t_threshold):
    """Outputs and the gradients of the case's upstream gradients, by name (tests/_twin.py);
    called inside the composite_kernels context, which the backward reads too."""

    def render(t_starts, t_ends, sigmas, rgbs, bg):
        return lib.render_packed(
            t_starts,
            t_ends,
            c["ray_indices"],
            sigmas,
            rgbs,
            c["n_rays"],
            bg,
            t_threshold=t_threshold,
            return_weights=True,
        )

    inputs = {k: c[k] for k in ("t_starts", "t_ends", "sigmas", "rgbs", "bg")}
    grad = ("sigmas", "rgbs", "bg")
    return run_with_grads(render, inputs, grad, cotangents=c["up"], names=NAMES, dtype=dtype)


def _of_max(atol):
    """An absolute error in units of the output's largest magnitude (at least 1)."""
    return {"rtol": 0.0, "atol": atol, "relative_to_max": True}


COUNTS = [0, 1, 2, 31, 32, 33, 64, 65, 100, 5, 129, 300]  # chunks of 4 x block_dim samples


@pytest.mark.parametrize("block_dim", [4, 32])
@pytest.mark.parametrize("t_threshold", [0.0, 1e-2, 0.4])
def test_tiled_matches_sequential_and_float64(device, block_dim, t_threshold):
    c = _case(device, COUNTS)
    with impl("tiled", block_dim):
        t = _run(W, c, F32, t_threshold)
    with impl("sequential"):
        s = _run(W, c, F32, t_threshold)
    r = _run(R, c, F64, t_threshold)
    tiled = {**t.out, **t.grads}
    assert_outputs_close(tiled, {**s.out, **s.grads}, tol=_of_max(2e-6))
    assert_outputs_close(tiled, {**r.out, **r.grads}, tol=_of_max(5e-6), other_dtype=True)


@pytest.mark.parametrize(
    "taus", [[0.0, 1e-12, 1.0], [1e3, 1e8, float("inf")], [0.0, 1e-6, 1.0, 1e8, float("inf")]]
)
def test_tiled_extreme_optical_depths(device, taus):
    c = _case(device, COUNTS, tau_values=taus, zero_len=float("inf") not in taus)
    with impl("tiled"):
        t = _run(W, c, F32, 0.0)
    with impl("sequential"):
        s = _run(W, c, F32, 0.0)
    assert_finite(t)
    assert_outputs_close(
        {**t.out, **t.grads}, {**s.out, **s.grads}, tol={"rtol": 1e-5, "atol": 2e-6}
    )
    opacity = t.out["opacity"]
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
        w = _run(W, c, F32, 0.0).out["weights"].double().cpu()
    expect_t2 = torch.exp(torch.tensor(-0.5, dtype=F64))
    assert abs(float(w[2]) - float(expect_t2)) < 1e-6


def test_tiled_nan_stays_in_its_ray(device):
    c = _case(device, COUNTS, nan_ray=6)
    clean = _case(device, COUNTS)
    with impl("tiled"):
        out = list(_run(W, c, F32, 1e-2).out.values())
        ref = list(_run(W, clean, F32, 1e-2).out.values())
    for o, r in zip(out[:3], ref[:3]):
        assert bool(torch.isnan(o[6]).all())
        keep = torch.arange(len(COUNTS), device=device) != 6
        assert torch.equal(o[keep], r[keep])


def test_default_float32_path_is_tiled():
    assert C._IMPL["float32_sigma"] == "tiled"
    assert C._kernels(torch.zeros(1), 0) == "tiled"
    assert C._kernels(torch.zeros(1, dtype=F64), 0) == "sequential"
    assert C._kernels(torch.zeros(1), 1) == "sequential"


@pytest.mark.parametrize(
    "kind,block_dim,dtype",
    [("tiled", 4, F32), ("tiled", 32, F32), ("sequential", 32, F32), ("sequential", 32, F64)],
)
def test_samples_no_ray_covers_get_zero_gradients(device, kind, block_dim, dtype, monkeypatch):
    """A fixed-capacity layout (check=False): gaps before the first ray, between rays and after
    the last one. The backward allocates its gradients without zero-filling them (here they
    start as NaN), so the kernels must write those samples' zeros themselves."""
    info = torch.tensor([[2, 3], [5, 0], [7, 40], [50, 0], [50, 9]], dtype=torch.int32)
    n, n_rays = 70, info.shape[0]
    g = torch.Generator().manual_seed(3)
    t0 = (2.0 + 0.05 * torch.arange(n, dtype=F64)).to(device, dtype)
    sig = (3 * torch.rand(n, generator=g, dtype=F64)).to(device, dtype).requires_grad_()
    rgbs = torch.rand(n, 3, generator=g, dtype=F64).to(device, dtype).requires_grad_()
    ri = torch.zeros(n, dtype=torch.int64, device=device)
    covered = torch.zeros(n, dtype=torch.bool)
    for s0, cnt in info.tolist():
        covered[s0 : s0 + cnt] = True
    empty_like = torch.empty_like
    monkeypatch.setattr(
        torch, "empty_like", lambda x, **kw: empty_like(x, **kw).fill_(float("nan"))
    )
    with impl(kind, block_dim):
        rgb, depth, _ = W.render_packed(t0, t0 + 0.05, ri, sig, rgbs, n_rays, 1.0,
                                        packed_info=info.to(device), check=False)  # fmt: skip
        v_sig, v_rgb = torch.autograd.grad(rgb.sum() + depth.sum(), (sig, rgbs))
    assert bool(torch.isfinite(v_sig).all() and torch.isfinite(v_rgb).all())
    assert bool((v_sig.cpu()[~covered] == 0).all() and (v_rgb.cpu()[~covered] == 0).all())
    assert bool((v_rgb.cpu()[covered] != 0).all())


def test_backward_uses_the_forwards_kernels_and_block():
    """The tiled backward re-walks the forward's chunks, so it must run with the forward's
    block width even when the backward runs after the composite_kernels block has closed."""
    c = _case("cpu", COUNTS)
    sig = c["sigmas"].float().requires_grad_()
    args = (c["t_starts"].float(), c["t_ends"].float(), c["ray_indices"])
    with impl("tiled", 4):
        rgb, *_ = W.render_packed(*args, sig, c["rgbs"].float(), c["n_rays"], c["bg"].float())
    (late,) = torch.autograd.grad(rgb.sum(), sig)
    with impl("tiled", 4):
        rgb, *_ = W.render_packed(*args, sig, c["rgbs"].float(), c["n_rays"], c["bg"].float())
        (inside,) = torch.autograd.grad(rgb.sum(), sig)
    assert torch.equal(late, inside)
