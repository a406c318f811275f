"""Stratified sampling kernel (kernels/sampling.py via warpnerf.ops.sampling): evaluation mode
against the reference, exact partitions of [near, far], the packed layout and the training jitter's
range, reproducibility and distribution."""

from __future__ import annotations

import pytest
import torch

import warpnerf as W
from warpnerf import reference as R

from ._twin import assert_matches_twin

F32, F64 = torch.float32, torch.float64


def _bounds(n_rays, dtype, device, n_miss=0):
    """near in [0.1, 2), far = near + [0.5, 4); the last n_miss rays have far <= near."""
    near = torch.rand(n_rays, dtype=F64) * 1.9 + 0.1
    far = near + torch.rand(n_rays, dtype=F64) * 3.5 + 0.5
    if n_miss:
        far[-n_miss:] = near[-n_miss:] - torch.rand(n_miss, dtype=F64)
        far[-1] = near[-1]  # far == near is a miss too
    return near.to(device, dtype), far.to(device, dtype)


def _tol(device, dtype):
    """Exact on the CPU; a few ulps on CUDA, where NVRTC may contract a + k * step into an FMA."""
    if device.type == "cpu":
        return {"rtol": 0.0, "atol": 0.0}
    return {"rtol": 4 * torch.finfo(dtype).eps, "atol": 0.0}


@pytest.mark.parametrize("packed", [False, True])
@pytest.mark.parametrize("dtype", [F64, F32])
def test_eval_matches_reference(device, dtype, packed):
    near, far = _bounds(50, dtype, device, n_miss=5)
    # t_starts, t_ends within _tol; ray_indices, packed_info exact (None when dense, both).
    run = assert_matches_twin(
        lambda near, far: W.stratified_samples(near, far, 16, packed=packed),
        lambda near, far: R.stratified_samples(near, far, 16, packed=packed),
        {"near": near, "far": far},
        tol=_tol(device, dtype),
    )
    s = W.Samples(**run.out)
    assert s.t_starts.dtype == s.t_ends.dtype == dtype
    if not packed:
        assert s.ray_indices is None and s.packed_info is None
    # Evaluation bins are equal: midpoints at near + (k + 1/2) D.
    if not packed:
        d = ((far - near).clamp_min(0) / 16)[:, None]
        k = torch.arange(16, dtype=dtype, device=device)
        torch.testing.assert_close(s.midpoints(), near[:, None] + (k + 0.5) * d)


@pytest.mark.parametrize("perturb", [False, True])
@pytest.mark.parametrize("dtype", [F64, F32])
def test_dense_intervals_partition_near_far(device, dtype, perturb):
    near, far = _bounds(200, dtype, device, n_miss=4)
    s = W.stratified_samples(near, far, 32, perturb=perturb, seed=7)
    hit = far > near
    assert s.t_starts.shape == s.t_ends.shape == (200, 32)
    assert torch.equal(s.t_starts[:, 0], near)
    assert torch.equal(s.t_ends[hit, -1], far[hit])
    assert torch.equal(s.t_ends[:, :-1], s.t_starts[:, 1:])
    assert bool((s.t_ends[hit] > s.t_starts[hit]).all())  # ordered, no empty bin
    # Misses (far <= near): zero-length intervals at near, which composite to nothing.
    assert bool((s.t_starts[~hit] == near[~hit, None]).all())
    assert bool((s.t_ends[~hit] == near[~hit, None]).all())


@pytest.mark.parametrize("perturb", [False, True])
def test_packed_layout(device, perturb):
    n_rays, n_s = 40, 8
    near, far = _bounds(n_rays, F64, device)
    miss = torch.tensor([0, 3, 4, 17, 39], device=device)
    far[miss] = near[miss] - 0.25
    far[4] = near[4]
    p = W.stratified_samples(near, far, n_s, perturb=perturb, seed=11, packed=True)
    d = W.stratified_samples(near, far, n_s, perturb=perturb, seed=11)
    hit = far > near
    counts = p.packed_info[:, 1]
    assert p.packed_info.dtype == torch.int32 and p.ray_indices.dtype == torch.int64
    assert bool((counts[~hit] == 0).all()) and bool((counts[hit] == n_s).all())
    assert p.t_starts.shape == p.t_ends.shape == p.ray_indices.shape == (int(hit.sum()) * n_s,)
    assert bool((p.ray_indices[1:] >= p.ray_indices[:-1]).all())
    assert not bool(torch.isin(p.ray_indices, miss).any())
    assert torch.equal(p.packed_info, W.packed_info_from_ray_indices(p.ray_indices, n_rays))
    starts = p.packed_info[:, 0].long()
    assert torch.equal(starts, torch.cumsum(counts.long(), 0) - counts.long())
    # Same samples as the dense layout's hit rows (same RNG key: seed and ray index).
    assert torch.equal(p.t_starts, d.t_starts[hit].reshape(-1))
    assert torch.equal(p.t_ends, d.t_ends[hit].reshape(-1))


def test_packed_all_rays_miss(device):
    near = torch.ones(3, dtype=F64, device=device)
    p = W.stratified_samples(near, near - 1, 4, packed=True)
    assert p.t_starts.numel() == 0 and p.ray_indices.numel() == 0
    assert p.packed_info.tolist() == [[0, 0]] * 3


def test_single_sample_is_the_whole_interval(device):
    near, far = _bounds(10, F64, device)
    for perturb in (False, True):
        s = W.stratified_samples(near, far, 1, perturb=perturb, seed=1)
        assert torch.equal(s.t_starts[:, 0], near) and torch.equal(s.t_ends[:, 0], far)


def _offsets(s, near, far, n_s):
    """Interior edge k (1..n-1) minus its regular position near + k D, in units of D."""
    d = ((far - near) / n_s)[:, None]
    k = torch.arange(1, n_s, dtype=near.dtype, device=near.device)
    return (s.t_starts[:, 1:] - (near[:, None] + k * d)) / d


@pytest.mark.parametrize("dtype", [F64, F32])
def test_jitter_stays_within_half_a_bin(device, dtype):
    near, far = _bounds(300, dtype, device)
    s = W.stratified_samples(near, far, 24, perturb=True, seed=5)
    off = _offsets(s, near, far, 24)
    slack = 1e-12 if dtype == F64 else 1e-4  # rounding of the edge positions, in units of D
    assert bool((off >= -0.5 - slack).all()) and bool((off < 0.5 + slack).all())
    assert float(off.abs().max()) > 0.45  # the whole range is used
    # Midpoints stay inside their own regular bin's neighbourhood: ordered along each ray.
    assert bool((s.midpoints().diff(dim=1) > 0).all())


def test_seeds(device):
    near, far = _bounds(64, F64, device)
    a = W.stratified_samples(near, far, 16, perturb=True, seed=1)
    b = W.stratified_samples(near, far, 16, perturb=True, seed=1)
    c = W.stratified_samples(near, far, 16, perturb=True, seed=2)
    e = W.stratified_samples(near, far, 16)
    assert torch.equal(a.t_starts, b.t_starts) and torch.equal(a.t_ends, b.t_ends)
    # A new seed moves every interior edge of every ray; so does perturbing at all.
    assert bool((a.t_starts[:, 1:] != c.t_starts[:, 1:]).all())
    assert bool((a.t_starts[:, 1:] != e.t_starts[:, 1:]).all())
    # perturb=False ignores the seed.
    assert torch.equal(W.stratified_samples(near, far, 16, seed=3).t_starts, e.t_starts)


def test_ray_offset_gives_a_slice_the_whole_batch_draws(device):
    """``ray_offset``: the jitter of rays k.. of a slice starting at k is that of the same rays
    in the whole batch (a data-parallel rank's share), for stratified and importance samples."""
    near, far = _bounds(40, F64, device)
    whole = W.stratified_samples(near, far, 8, perturb=True, seed=5, packed=True)
    part = W.stratified_samples(near[17:], far[17:], 8, perturb=True, seed=5, packed=True,
                                ray_offset=17)  # fmt: skip
    torch.testing.assert_close(part.t_starts, whole.t_starts[17 * 8 :], rtol=0, atol=0)
    unshifted = W.stratified_samples(near[17:], far[17:], 8, perturb=True, seed=5, packed=True)
    assert not torch.equal(unshifted.t_starts, part.t_starts)
    w = torch.rand(whole.t_starts.shape, dtype=F64, generator=torch.Generator().manual_seed(2))
    w = w.to(device)
    fine = W.importance_samples(whole, w, 6, perturb=True, seed=9)
    part_fine = W.importance_samples(part, w[17 * 8 :], 6, perturb=True, seed=9, ray_offset=17)
    torch.testing.assert_close(part_fine.t_starts, fine.t_starts[17 * 14 :], rtol=0, atol=0)
    with pytest.raises(ValueError, match="ray_offset"):
        W.stratified_samples(near, far, 8, perturb=True, ray_offset=-1)


def test_jitter_is_uniform_and_independent(device):
    n_rays, n_s = 2000, 33
    near, far = _bounds(n_rays, F64, device)
    s = W.stratified_samples(near, far, n_s, perturb=True, seed=123)
    off = _offsets(s, near, far, n_s).cpu()  # uniform on [-1/2, 1/2): mean 0, variance 1/12
    flat = off.reshape(-1)
    assert abs(float(flat.mean())) < 0.05
    assert abs(float(flat.var()) - 1 / 12) < 0.005
    hist = torch.histc(flat, bins=10, min=-0.5, max=0.5) / flat.numel()
    assert bool(((hist > 0.09) & (hist < 0.11)).all()), hist
    # Independent along a ray (the RNG state advances) and across rays (keyed by ray index).
    along = torch.corrcoef(torch.stack([off[:, :-1].reshape(-1), off[:, 1:].reshape(-1)]))[0, 1]
    across = torch.corrcoef(torch.stack([off[:-1].reshape(-1), off[1:].reshape(-1)]))[0, 1]
    assert abs(float(along)) < 0.05 and abs(float(across)) < 0.05
    assert bool((off.std(dim=1) > 0.1).all())  # no ray with one shared offset


@pytest.mark.parametrize("bad", ["nan_near", "nan_far", "inf_far", "neg_inf_near"])
def test_non_finite_bounds_raise(device, bad):
    near, far = _bounds(5, F64, device)
    if bad == "nan_near":
        near[2] = float("nan")
    elif bad == "nan_far":
        far[0] = float("nan")
    elif bad == "inf_far":
        far[4] = float("inf")
    else:
        near[1] = -float("inf")
    for packed in (False, True):
        with pytest.raises(ValueError, match=r"near and far"):
            W.stratified_samples(near, far, 8, packed=packed)


def test_rejects_bad_arguments():
    near, far = torch.zeros(4, dtype=F64), torch.ones(4, dtype=F64)
    with pytest.raises(ValueError, match=r"\bn_samples\b"):
        W.stratified_samples(near, far, 0)
    with pytest.raises(ValueError, match=r"\bfar\b"):
        W.stratified_samples(near, far[:3], 8)
    with pytest.raises(ValueError, match=r"\bfar\b"):
        W.stratified_samples(near, far.float(), 8)
    with pytest.raises(ValueError, match=r"\bnear\b"):
        W.stratified_samples(near[:, None], far, 8)
    with pytest.raises(ValueError, match=r"\bnear\b"):
        W.stratified_samples(near.long(), far.long(), 8)
