"""The distortion loss (mip-NeRF 360) on packed samples: the Warp kernel against its O(n^2) twin
in float64 (loss and weight gradients), gradcheck, known values, hard cases (empty rays,
zero-length intervals, many samples, NaN/Inf inputs) and the input checks."""

from __future__ import annotations

import math

import pytest
import torch

from warpnerf.ops import distortion_loss, packed_info_from_ray_indices
from warpnerf.reference import distortion_loss as twin

from ._twin import assert_matches_twin, gradcheck_op

TOL = {torch.float64: {"rtol": 1e-10, "atol": 1e-12}, torch.float32: {"rtol": 1e-4, "atol": 1e-6}}


def packed(counts, dtype=torch.float64, device="cpu", seed=0):
    """Samples of rays with the given counts: increasing, non-overlapping intervals in [0, 1]
    (some of zero length), weights in [0, 1) summing below 1 per ray."""
    g = torch.Generator().manual_seed(seed)
    counts = torch.as_tensor(counts, dtype=torch.int64)
    ri = torch.repeat_interleave(torch.arange(len(counts)), counts)
    n = int(counts.sum())
    edges, weights = [], []
    for r, c in enumerate(counts.tolist()):
        e = torch.sort(torch.rand(2 * c, generator=g, dtype=torch.float64))[0].reshape(-1, 2)
        if r % 2:  # touching intervals, as marched samples are
            cuts = torch.sort(torch.rand(c + 1, generator=g, dtype=torch.float64))[0]
            e = torch.stack([cuts[:-1], cuts[1:]], -1)
        edges.append(e)
        w = torch.rand(c, generator=g, dtype=torch.float64)
        weights.append(w / max(1.0, float(w.sum()) * 1.25))
    e = torch.cat(edges) if n else torch.zeros(0, 2, dtype=torch.float64)
    if n > 2:
        e[1, 1] = e[1, 0]  # a zero-length interval
    kw = dict(dtype=dtype, device=device)
    return {
        "s_starts": e[:, 0].to(**kw),
        "s_ends": e[:, 1].to(**kw),
        "ray_indices": ri.to(device),
        "weights": torch.cat(weights).to(**kw) if n else torch.zeros(0, **kw),
        "n_rays": len(counts),
    }


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_matches_the_pairwise_definition(device, dtype):
    inputs = packed([0, 1, 2, 7, 33, 3, 0, 64], dtype=dtype, device=device)
    assert_matches_twin(distortion_loss, twin, inputs, tol=TOL, grad=("weights",),
                        twin_dtype=torch.float64)  # fmt: skip


def test_gradcheck(device):
    inputs = packed([3, 0, 5, 1], device=device)
    gradcheck_op(distortion_loss, inputs, ("weights",))


def test_known_values(device):
    """One sample: w^2 d / 3. Two zero-length samples: 2 w1 w2 |m1 - m2|. All weight in one
    place beats the same weight spread out."""
    kw = dict(dtype=torch.float64, device=device)
    ray0 = torch.tensor([0], device=device)
    one = distortion_loss(torch.tensor([0.2], **kw), torch.tensor([0.5], **kw), ray0,
                          torch.tensor([0.6], **kw), 1)  # fmt: skip
    assert float(one[0]) == pytest.approx(0.36 * 0.3 / 3, rel=1e-12)
    ends = torch.tensor([0.1, 0.7], **kw)  # (zero-length intervals)
    two = distortion_loss(ends, ends, torch.tensor([0, 0], device=device),
                          torch.tensor([0.3, 0.5], **kw), 1)  # fmt: skip
    assert float(two[0]) == pytest.approx(2 * 0.3 * 0.5 * 0.6, rel=1e-12)
    s = torch.linspace(0, 1, 11, **kw)
    ri = torch.zeros(10, dtype=torch.int64, device=device)
    spread = distortion_loss(s[:-1], s[1:], ri, torch.full((10,), 0.09, **kw), 1)
    peak = torch.zeros(10, **kw)
    peak[4] = 0.9
    assert float(distortion_loss(s[:-1], s[1:], ri, peak, 1)[0]) < float(spread[0]) / 5


def test_many_samples_and_float32(device):
    """2,048 samples on one ray and 300 rays of 40, and a contracted-like ray (s = t / (t + 1)
    on a cone lattice, crowded towards s = 1, its weight in one sharp surface): float32 losses
    within 1e-4 (relative) of the float64 twin, weight gradients within 2e-5 of the loss's
    scale."""
    inputs = packed([2048] + [40] * 300, device=device, seed=3)
    t = torch.cumsum(torch.full((1024,), 1.0 / 64, dtype=torch.float64), 0) * torch.exp(
        torch.linspace(0, 6, 1025, dtype=torch.float64)[:-1]
    )  # steps growing with distance
    s_of_t = torch.cat([torch.zeros(1, dtype=torch.float64), t / (t + 1)])
    w = torch.exp(-(((torch.arange(1024) - 300.0) / 4) ** 2)).double() * 0.9
    n0 = inputs["weights"].shape[0]
    big = {
        "s_starts": torch.cat([inputs["s_starts"].cpu(), s_of_t[:-1]]),
        "s_ends": torch.cat([inputs["s_ends"].cpu(), s_of_t[1:]]),
        "ray_indices": torch.cat([inputs["ray_indices"].cpu(), torch.full((1024,), 301)]),
        "weights": torch.cat([inputs["weights"].cpu(), w]),
        "n_rays": 302,
    }
    assert big["weights"].shape[0] == n0 + 1024
    exact_w = big["weights"].clone().requires_grad_(True)
    exact = twin(**{**big, "weights": exact_w})
    exact.sum().backward()
    f32 = {k: v.float().to(device) if torch.is_tensor(v) and v.is_floating_point() else v
           for k, v in big.items()}  # fmt: skip
    f32["ray_indices"] = big["ray_indices"].to(device)
    w32 = f32["weights"].clone().requires_grad_(True)
    got = distortion_loss(**{**f32, "weights": w32})
    got.sum().backward()
    assert torch.allclose(got.double().cpu(), exact.detach(), rtol=1e-4, atol=1e-7)
    # (the gradient m_k (2 W_k - W) + S - 2 S_k cancels terms of the loss's scale: its float32
    # error is ~1e-5 of that scale, here about 1, whatever the gradient's own size)
    assert torch.allclose(w32.grad.double().cpu(), exact_w.grad, rtol=1e-4, atol=2e-5)


def test_empty_rays_and_no_samples(device):
    inputs = packed([0, 0, 0], device=device)
    out = distortion_loss(**inputs)
    assert out.shape == (3,) and float(out.abs().sum()) == 0.0
    nothing = packed([], device=device)
    assert distortion_loss(**nothing).shape == (0,)


def test_nan_and_inf_inputs_stay_in_their_ray(device):
    inputs = packed([4, 5, 6], device=device)
    w = inputs["weights"].clone()
    w[5] = float("nan")  # ray 1
    out = distortion_loss(**{**inputs, "weights": w})
    assert math.isnan(float(out[1])) and torch.isfinite(out[[0, 2]]).all()
    s1 = inputs["s_ends"].clone()
    s1[-1] = float("inf")  # ray 2's last interval
    out = distortion_loss(**{**inputs, "s_ends": s1})
    assert not math.isfinite(float(out[2])) and torch.isfinite(out[:2]).all()


def test_input_checks(device):
    """Refused with check=True: samples out of order, backwards intervals, bad indices and
    layouts. Accepted: touching and overlapping intervals and equal midpoints."""
    inputs = packed([3, 4], device=device)
    touching = {
        **inputs,
        "s_starts": inputs["s_starts"].clone(),
        "s_ends": inputs["s_ends"].clone(),
    }
    touching["s_starts"][1] = touching["s_ends"][0] - 1e-3  # overlaps its predecessor
    touching["s_starts"][2], touching["s_ends"][2] = touching["s_starts"][1], touching["s_ends"][1]
    assert torch.isfinite(distortion_loss(**touching)).all()
    flipped = {**inputs, "s_starts": inputs["s_ends"], "s_ends": inputs["s_starts"]}
    with pytest.raises(ValueError, match="s_end >= s_start"):
        distortion_loss(**flipped)
    backwards = {**inputs, "s_starts": inputs["s_starts"].flip(0),
                 "s_ends": inputs["s_ends"].flip(0)}  # fmt: skip
    with pytest.raises(ValueError, match="increasing"):
        distortion_loss(**backwards)
    with pytest.raises(ValueError, match="sorted"):
        distortion_loss(**{**inputs, "ray_indices": inputs["ray_indices"].flip(0)})
    with pytest.raises(ValueError, match="n_rays"):
        distortion_loss(**{**inputs, "n_rays": 1})
    with pytest.raises(ValueError, match="s_ends"):
        distortion_loss(**{**inputs, "s_ends": inputs["s_ends"][:-1]})
    with pytest.raises(TypeError):
        distortion_loss(**{**inputs, "ray_indices": inputs["ray_indices"].double()})
    bad = packed_info_from_ray_indices(inputs["ray_indices"], 2).clone()
    bad[1, 1] += 1
    with pytest.raises(ValueError, match="packed_info"):
        distortion_loss(**inputs, packed_info=bad)


def test_training_adds_the_weighted_distortion_term(tmp_path):
    """--distortion-loss W: the step's loss is the colour MSE plus W x the rays' mean distortion
    (the first step, before any update, renders the same batch with and without it), logged as
    the history's "distortion"; the ray coordinate is normalised in both kinds of scene; the flag
    is refused where there are no marched samples."""
    from warpnerf.errors import UserError
    from warpnerf.train import train_nerf
    from warpnerf.train.nerf import distortion_coordinate, resolve_data

    from .test_nerf import GRID, tiny

    quiet = dict(progress=False, log=lambda *a: 0)
    plain = train_nerf(tiny(iters=2, **GRID), tmp_path / "a", **quiet)
    reg = train_nerf(tiny(iters=2, distortion_loss=0.5, **GRID), tmp_path / "b", **quiet)
    assert "distortion" not in plain and len(reg["distortion"]) == 2
    assert reg["psnr"][0] == plain["psnr"][0]
    assert 0 < reg["distortion"][0] < 1 and math.isfinite(reg["distortion"][1])
    assert reg["loss"][0] == pytest.approx(plain["loss"][0] + 0.5 * reg["distortion"][0], rel=1e-5)
    assert reg["loss"][1] != plain["loss"][1]  # the gradient moved the field differently
    # the coordinate: in [0, 1] and increasing over the distances rays are marched at (from
    # near, or from 0 in a contracted scene, out to far)
    for cfg in (tiny(**GRID), tiny(**dict(GRID, contract="on"))):
        cfg = resolve_data(cfg)
        lo = 0.0 if cfg.contract == "on" else cfg.near
        s = distortion_coordinate(cfg)(torch.linspace(lo, min(cfg.far, 50.0), 200))
        s_far = float(distortion_coordinate(cfg)(torch.tensor(cfg.far)))
        assert (s[1:] > s[:-1]).all() and float(s[0]) == 0.0 and float(s[-1]) <= s_far <= 1
    # a contracted run logs a finite, positive term every step
    run = train_nerf(tiny(iters=3, distortion_loss=0.05, **dict(GRID, contract="on",
                                                                 max_samples=256)),
                     tmp_path / "c", **quiet)  # fmt: skip
    assert len(run["distortion"]) == 3 and all(0 < v < 1 for v in run["distortion"])
    bads = (
        dict(distortion_loss=0.1),
        dict(GRID, distortion_loss=-1.0),
        dict(GRID, distortion_loss=float("nan")),
        dict(HASH_ONLY, distortion_loss=0.1),
    )
    for bad in bads:
        with pytest.raises(UserError, match="distortion"):
            train_nerf(tiny(**bad), tmp_path / "bad", **quiet)


HASH_ONLY = dict(field="hash", grid_res=0, hash_levels=4, hash_log2_size=10)
