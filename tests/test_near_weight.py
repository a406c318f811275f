"""Fog measures and losses (issue 48): each ray's weight before a distance (``weight_before``,
the ``--near-loss`` penalty's and scripts/fog_report.py's) and its weighted median
(``weight_median``) against pure-PyTorch twins, forward and gradient through the compositing
kernel; the fixed-shape step's unused slots ignored; the penalty in training (the loss's term,
eager and static steps alike: tests/test_step_loss.py), its refusals; the distortion loss's ray
coordinate in a contracted scene against the twin on the kept samples, and mip-NeRF 360's
(``--distortion-space mipnerf360``)."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from warpnerf.ops import packed_info_from_ray_indices, render_packed
from warpnerf.reference import distortion_loss as distortion_twin
from warpnerf.reference.composite import render_packed as composite_twin
from warpnerf.render import weight_before, weight_median

from ._twin import assert_matches_twin, gradcheck_op

TOL = {torch.float64: {"rtol": 1e-10, "atol": 1e-12}, torch.float32: {"rtol": 1e-5, "atol": 1e-6}}


def marched(counts, dtype=torch.float64, device="cpu", seed=0):
    """Packed samples of rays with the given counts: touching intervals from t = 1 on (some
    rays dense enough to be opaque), densities in [0, 3), per-ray cuts inside their spans."""
    g = torch.Generator().manual_seed(seed)
    counts = torch.as_tensor(counts, dtype=torch.int64)
    ri = torch.repeat_interleave(torch.arange(len(counts)), counts)
    steps = 0.05 + torch.rand(int(counts.sum()), generator=g, dtype=torch.float64) * 0.2
    t_ends = torch.zeros_like(steps)
    for r in range(len(counts)):
        sl = ri == r
        t_ends[sl] = 1.0 + torch.cumsum(steps[sl], 0)
    kw = dict(dtype=dtype, device=device)
    cut = 1.0 + torch.rand(len(counts), generator=g, dtype=torch.float64) * counts.double() * 0.1
    return {
        "t_starts": (t_ends - steps).to(**kw),
        "t_ends": t_ends.to(**kw),
        "ray_indices": ri.to(device),
        "sigmas": (torch.rand(len(steps), generator=g, dtype=torch.float64) * 3).to(**kw),
        "n_rays": len(counts),
        "t_cut": cut.to(**kw),
    }


def near_op(t_starts, t_ends, ray_indices, sigmas, n_rays, t_cut):
    """The penalty's per-ray term as training computes it: the compositing kernel's weights,
    then :func:`weight_before`."""
    info = packed_info_from_ray_indices(ray_indices, n_rays)
    rgbs = sigmas.new_zeros(sigmas.shape[0], 3)
    *_, w = render_packed(t_starts, t_ends, ray_indices, sigmas, rgbs, n_rays, packed_info=info,
                          t_threshold=1e-4, return_weights=True)  # fmt: skip
    return weight_before(t_starts, t_ends, ray_indices, w, info, t_cut)


def near_twin(t_starts, t_ends, ray_indices, sigmas, n_rays, t_cut):
    """Its definition: the twin compositing's weights, summed ray by ray over the samples whose
    midpoint lies before the ray's cut."""
    rgbs = sigmas.new_zeros(sigmas.shape[0], 3)
    *_, w = composite_twin(t_starts, t_ends, ray_indices, sigmas, rgbs, n_rays,
                           t_threshold=1e-4, return_weights=True)  # fmt: skip
    mid = 0.5 * (t_starts + t_ends)
    return torch.stack([w[(ray_indices == r) & (mid < t_cut[r])].sum() for r in range(n_rays)])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_weight_before_matches_the_twin_with_its_gradient(device, dtype):
    inputs = marched([0, 1, 2, 7, 33, 3, 0, 64, 120], dtype=dtype, device=device)
    assert_matches_twin(near_op, near_twin, inputs, tol=TOL, grad=("sigmas",),
                        twin_dtype=torch.float64)  # fmt: skip
    out = near_op(**inputs)
    assert float(out[0]) == 0.0 and float(out[6]) == 0.0  # empty rays
    assert bool(((out >= 0) & (out <= 1 + 1e-6)).all())


def test_weight_before_gradcheck(device):
    inputs = marched([3, 0, 5, 2], device=device, seed=1)
    gradcheck_op(near_op, inputs, ("sigmas",))


def test_weight_before_ignores_slots_outside_the_rays():
    """The fixed-shape step's unused slots repeat a ray index but lie outside its range, and
    their weights are never written (here NaN): they count for nothing, in value and gradient."""
    inputs = marched([4, 6], seed=2)
    info = packed_info_from_ray_indices(inputs["ray_indices"], 2)
    w = torch.rand(10, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 0.1
    pad = torch.full((5,), float("nan"), dtype=torch.float64)
    wp = torch.cat([w, pad]).requires_grad_(True)
    t0 = torch.cat([inputs["t_starts"], torch.zeros(5, dtype=torch.float64)])
    t1 = torch.cat([inputs["t_ends"], torch.zeros(5, dtype=torch.float64)])
    ri = torch.cat([inputs["ray_indices"], torch.zeros(5, dtype=torch.int64)])
    got = weight_before(t0, t1, ri, wp, info, torch.tensor([1e9, 1e9], dtype=torch.float64))
    assert torch.allclose(got, torch.stack([w[:4].sum(), w[4:].sum()]))
    got.sum().backward()
    assert torch.isfinite(wp.grad).all() and float(wp.grad[10:].abs().sum()) == 0.0
    assert float(weight_before(t0, t1, ri, wp.detach(), info, 0.0).abs().sum()) == 0  # a float


def test_weight_median_matches_the_twin():
    """The midpoint of the first sample whose running weight reaches half the ray's total;
    NaN without weight; one sample holding most of the weight is the median."""
    g = torch.Generator().manual_seed(4)
    inputs = marched([0, 1, 5, 40, 17], seed=4)
    t0, t1, ri = inputs["t_starts"], inputs["t_ends"], inputs["ray_indices"]
    w = torch.rand(t0.shape[0], generator=g, dtype=torch.float64)
    w[ri == 2] = torch.tensor([0.0, 0.01, 0.9, 0.01, 0.0], dtype=torch.float64)
    w[ri == 4] = 0.0
    info = packed_info_from_ray_indices(ri, 5)
    got = weight_median(t0, t1, ri, w, info)
    mid = 0.5 * (t0 + t1)
    for r in range(5):
        wr, mr = w[ri == r], mid[ri == r]
        if float(wr.sum()) == 0:
            assert math.isnan(float(got[r]))
            continue
        run = torch.cumsum(wr, 0)
        want = mr[int(torch.nonzero(run >= 0.5 * run[-1])[0])]
        assert float(got[r]) == float(want), r
    assert float(got[2]) == float(mid[ri == 2][2])
    assert weight_median(t0[:0], t1[:0], ri[:0], w[:0], info[:0]).shape == (0,)


def test_near_loss_in_training(tmp_path):
    """--near-loss W: the step's loss is the colour term plus W x the rays' mean near weight
    (the first step renders the same batch with and without it), logged as "near", in [0, 1];
    in a contracted scene and with proposal sampling too; the flags' refusals."""
    from warpnerf.errors import UserError
    from warpnerf.train import train_nerf

    from .test_nerf import GRID, tiny
    from .test_proposal_sampling import PROPOSAL

    quiet = dict(progress=False, log=lambda *a: 0)
    plain = train_nerf(tiny(iters=2, **GRID), tmp_path / "a", **quiet)
    near = train_nerf(tiny(iters=2, near_loss=0.5, **GRID), tmp_path / "b", **quiet)
    assert "near" not in plain and len(near["near"]) == 2
    assert near["psnr"][0] == plain["psnr"][0]
    assert 0 < near["near"][0] < 1
    assert near["loss"][0] == pytest.approx(plain["loss"][0] + 0.5 * near["near"][0], rel=1e-5)
    assert near["loss"][1] != plain["loss"][1]
    # the stretch grows with --near-loss-frac: more weight inside it
    wide = train_nerf(tiny(iters=1, near_loss=0.5, near_loss_frac=0.9, **GRID), tmp_path / "w",
                      **quiet)  # fmt: skip
    assert wide["near"][0] > near["near"][0]
    contracted = dict(GRID, contract="on", max_samples=256)
    run = train_nerf(tiny(iters=2, near_loss=0.1, **contracted), tmp_path / "c", **quiet)
    assert all(0 <= v <= 1 for v in run["near"])
    prop = train_nerf(tiny(iters=2, near_loss=0.1, **dict(PROPOSAL, target_samples=500)),
                      tmp_path / "p", **quiet)  # fmt: skip
    assert len(prop["near"]) == 2 and all(0 <= v <= 1 for v in prop["near"])
    bads = (
        dict(near_loss=0.1),  # no grid
        dict(GRID, near_loss=-1.0),
        dict(GRID, near_loss=float("nan")),
        dict(GRID, near_loss=0.1, near_loss_frac=0.0),
        dict(GRID, near_loss=0.1, near_loss_frac=1.5),
    )
    for bad in bads:
        with pytest.raises(UserError, match="near.loss"):
            train_nerf(tiny(**bad), tmp_path / "bad", **quiet)


def test_distortion_in_the_contracted_coordinate():
    """A contracted run's distortion term is the twin's loss of the kept samples' weights at
    s = t / (t + a), not at raw t (the weights and samples read back through the renderer's
    hook, without gradients: the same samples, every one composited); mip-NeRF 360's
    coordinate is its (1/near - 1/t) / (1/near - 1/far), 0 at near and 1 at far."""
    from warpnerf.render import render_marched
    from warpnerf.train.nerf import distortion_coordinate

    from .test_graph_step import _task

    task = _task("cpu", contract="on")
    cfg, model = task.cfg, task.model
    o, d = task.batch_rays(torch.zeros(8, dtype=torch.int64),
                           torch.arange(8.0) * 2 + 0.5, torch.arange(8.0) + 4.5)  # fmt: skip
    s_of_t = distortion_coordinate(cfg)
    kw = dict(background=1.0, t_threshold=0.0, max_samples=8192)  # (every sample of a ray)
    out = render_marched(model.grid, model.coarse, o, d, cfg.near, cfg.far, distortion_s=s_of_t,
                         **kw)  # fmt: skip
    seen = []
    with torch.no_grad():
        again = render_marched(model.grid, model.coarse, o, d, cfg.near, cfg.far,
                               on_weights=lambda *x: seen.append(x), **kw)  # fmt: skip
    ri, t0, t1, w = (torch.cat(x) for x in zip(*seen))
    order = torch.argsort(ri, stable=True)  # (rounds: each ray's samples in order)
    ri, t0, t1, w = ri[order], t0[order], t1[order], w[order]
    assert torch.allclose(again["opacity"], out["opacity"].detach(), atol=1e-6)
    a = float(cfg.aabb)
    want = distortion_twin(t0 / (t0 + a), t1 / (t1 + a), ri, w, 8).float()
    assert torch.allclose(out["distortion"].detach(), want, rtol=1e-4, atol=1e-6)
    raw = distortion_twin(t0, t1, ri, w, 8).float()
    assert not torch.allclose(out["distortion"].detach(), raw, rtol=1e-2)

    mip = distortion_coordinate(dataclasses.replace(cfg, distortion_space="mipnerf360"))
    near, far = float(cfg.near), float(cfg.far)
    t = torch.tensor([near, 2 * near, 10 * near, far], dtype=torch.float64)
    want = (1 / near - 1 / t) / (1 / near - 1 / far)
    assert torch.allclose(mip(t), want) and float(mip(t[:1])) == 0.0
    assert float(mip(t[-1:])) == pytest.approx(1.0)


def test_mipnerf360_distortion_space_in_training(tmp_path):
    from warpnerf.errors import UserError
    from warpnerf.train import train_nerf

    from .test_nerf import GRID, tiny
    from .test_proposal_sampling import PROPOSAL

    quiet = dict(progress=False, log=lambda *a: 0)
    flags = dict(distortion_loss=0.1, distortion_space="mipnerf360")
    run = train_nerf(tiny(iters=2, **flags, **dict(GRID, contract="on", max_samples=256)),
                     tmp_path / "c", **quiet)  # fmt: skip
    assert len(run["distortion"]) == 2 and all(0 < v < 1 for v in run["distortion"])
    prop = train_nerf(tiny(iters=1, **flags, **dict(PROPOSAL, target_samples=500)),
                      tmp_path / "p", **quiet)  # fmt: skip
    scene = train_nerf(tiny(iters=1, distortion_loss=0.1, **dict(PROPOSAL, target_samples=500)),
                       tmp_path / "q", **quiet)  # fmt: skip
    assert prop["distortion"][0] > 0 and prop["distortion"][0] != scene["distortion"][0]
    with pytest.raises(UserError, match="distortion.space"):
        train_nerf(tiny(**GRID, distortion_space="sideways"), tmp_path / "bad", **quiet)
    with pytest.raises(UserError, match="near > 0"):
        train_nerf(tiny(iters=1, **flags, **GRID, near=0.0), tmp_path / "bad2", **quiet)
