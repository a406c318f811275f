"""Importance (coarse-to-fine) sampling (kernels/sampling.py via warpnerf.ops.sampling): evaluation
mode against the float64 twin, exact partitions of [near, far] that keep every coarse edge, the
piecewise-constant PDF (counts per interval, uniform inside one), padding and degenerate weights,
the packed layout with empty rays, seeds, and input validation."""

from __future__ import annotations

import math

import pytest
import torch

import warpnerf as W
from warpnerf.ops.sampling import PDF_PADDING, Samples, importance_samples
from warpnerf.reference.sampling import importance_samples as ref_importance_samples

from ._twin import assert_matches_twin

F32, F64 = torch.float32, torch.float64


def _coarse(n_rays, n_c, dtype, device, *, perturb=True, packed=False, n_miss=0, seed=3):
    """Stratified coarse intervals: near in [0.1, 2), far = near + [0.5, 4); n_miss rays miss."""
    near = torch.rand(n_rays, dtype=F64) * 1.9 + 0.1
    far = near + torch.rand(n_rays, dtype=F64) * 3.5 + 0.5
    if n_miss:
        far[-n_miss:] = near[-n_miss:]
    near, far = near.to(device, dtype), far.to(device, dtype)
    s = W.stratified_samples(near, far, n_c, perturb=perturb, seed=seed, packed=packed)
    return s, near, far


def _weights(shape, dtype, device):
    """Compositing-like weights: mostly small, a few peaks, some exact zeros; sum about 1."""
    w = torch.rand(shape, dtype=F64) ** 6
    w[torch.rand(shape) < 0.3] = 0.0
    w = w / w.sum(-1, keepdim=True).clamp_min(1e-12) * 0.9 if len(shape) == 2 else w
    return w.to(device, dtype)


def _edges(s: Samples) -> torch.Tensor:
    """Dense samples [n_rays, n] -> their edges [n_rays, n + 1]."""
    return torch.cat([s.t_starts[:, :1], s.t_ends], -1)


def _new_positions(coarse: Samples, fine: Samples) -> torch.Tensor:
    """The fine edges minus one copy of each coarse edge (dense, no repeated coarse edge)."""
    e, big = _edges(coarse), _edges(fine)
    keep = torch.ones_like(big, dtype=torch.bool)
    keep.scatter_(1, torch.searchsorted(big, e), False)
    return big[keep].reshape(big.shape[0], -1)


def _assert_partition(s: Samples, near, far):
    """Dense samples: sorted, contiguous, from near to far exactly."""
    assert torch.equal(s.t_starts[:, 0], near) and torch.equal(s.t_ends[:, -1], far)
    assert torch.equal(s.t_ends[:, :-1], s.t_starts[:, 1:])
    assert bool((s.t_ends >= s.t_starts).all())


def _match(s: Samples, w, n_fine, tol) -> Samples:
    """importance_samples against its twin (tests/_twin.py): t_starts and t_ends within tol,
    ray_indices and packed_info exact (None for dense samples, both)."""
    run = assert_matches_twin(
        lambda s, w: importance_samples(s, w, n_fine),
        lambda s, w: ref_importance_samples(s, w, n_fine),
        {"s": s, "w": w},
        tol=tol,
    )
    return Samples(**run.out)


def _tol(device, dtype):
    """float64: exact on the CPU, ~1e-12 on CUDA (FMA contraction, torch's parallel cumsum)."""
    if dtype == F32:
        return {"rtol": 0.0, "atol": 2e-4}
    if device.type == "cpu":
        return {"rtol": 0.0, "atol": 0.0}
    return {"rtol": 0.0, "atol": 1e-12}


@pytest.mark.parametrize("packed", [False, True])
@pytest.mark.parametrize("dtype", [F64, F32])
def test_eval_matches_reference(device, dtype, packed):
    s, _, _ = _coarse(60, 24, dtype, device, packed=packed, n_miss=4)
    w = _weights(s.t_starts.shape, dtype, device)
    out = _match(s, w, 40, _tol(device, dtype))
    assert out.t_starts.dtype == out.t_ends.dtype == dtype
    if not packed:
        assert out.t_starts.shape == (60, 64)
        assert out.ray_indices is None and out.packed_info is None


@pytest.mark.parametrize("perturb", [False, True])
@pytest.mark.parametrize("dtype", [F64, F32])
def test_output_partitions_near_far_and_keeps_coarse_edges(device, dtype, perturb):
    s, near, far = _coarse(300, 32, dtype, device, n_miss=3)
    w = _weights(s.t_starts.shape, dtype, device)
    out = importance_samples(s, w, 48, perturb=perturb, seed=9)
    assert out.t_starts.shape == out.t_ends.shape == (300, 80)
    _assert_partition(out, near, far)
    big, e = _edges(out), _edges(s)
    assert torch.equal(big.gather(1, torch.searchsorted(big, e)), e)  # every coarse edge kept
    hit = far > near
    assert bool((out.t_starts[~hit] == near[~hit, None]).all())  # misses: all at near
    assert bool((out.t_ends[~hit] == near[~hit, None]).all())
    # Midpoints are where the fine field is evaluated: inside [near, far], non-decreasing.
    mid = out.midpoints()
    assert bool((mid.diff(dim=1) >= 0).all()) and bool((mid[hit] <= far[hit, None]).all())


def test_positions_follow_piecewise_constant_pdf(device):
    """Many rays share near/far, coarse bins and weights: counts per coarse interval match p_i
    (chi-square), each ray's counts are stratified (within 2 of n_f p_i), and positions are
    uniform inside their interval (Kolmogorov-Smirnov)."""
    n_rays, n_c, n_f = 4000, 16, 32
    near = torch.full((n_rays,), 1.0, dtype=F64, device=device)
    s = W.stratified_samples(near, near + 3.0, n_c)  # equal bins, identical on every ray
    w0 = [0, 0, 0.02, 0.05, 0.1, 0.2, 0.3, 0.15, 0.08, 0.05, 0.03, 0.02, 0, 0, 0, 0]
    w = torch.tensor(w0, dtype=F64, device=device).expand(n_rays, n_c).contiguous()
    out = importance_samples(s, w, n_f, perturb=True, seed=2024)
    t = _new_positions(s, out).cpu()
    e = _edges(s)[0].cpu()
    p = torch.tensor(w0, dtype=F64) + PDF_PADDING  # equal bins: padding eps per interval
    p = p / p.sum()
    idx = (torch.searchsorted(e, t, right=True) - 1).clamp(0, n_c - 1)  # [n_rays, n_f]
    per_ray = torch.zeros(n_rays, n_c, dtype=F64).scatter_add_(1, idx, torch.ones_like(t))
    # Stratified u: a ray's count in interval i is n_f p_i up to the two partly covered strata.
    assert bool(((per_ray - n_f * p).abs() <= 2.0 + 1e-9).all())
    counts, expected = per_ray.sum(0), n_rays * n_f * p
    big = expected >= 5
    chi2 = float(((counts[big] - expected[big]) ** 2 / expected[big]).sum())
    assert chi2 < 27.9, (chi2, counts, expected)  # df = 9: the 0.999 quantile is 27.9
    assert float(counts[~big].sum()) <= 25  # padding only: ~1.3 expected per zero-weight bin
    # Inside an interval the CDF is linear: offsets uniform on [0, 1).
    frac = ((t - e[idx]) / (e[idx + 1] - e[idx]))[big[idx]].sort().values
    n = frac.numel()
    cdf_hi, cdf_lo = torch.arange(1, n + 1, dtype=F64) / n, torch.arange(n, dtype=F64) / n
    ks = float(torch.maximum(cdf_hi - frac, frac - cdf_lo).max())
    assert ks < 1.95 / math.sqrt(n), ks  # 0.999 quantile of the KS statistic


@pytest.mark.parametrize("dtype", [F64, F32])
def test_zero_weights_sample_uniformly_by_length(device, dtype):
    """All-zero weights on jittered (unequal) coarse bins: p_i = len_i / L, so evaluation puts
    new position j at near + (j + 1/2) / n_f * L and training keeps it in that stratum."""
    n_f = 24
    s, near, far = _coarse(200, 16, dtype, device)
    w = torch.zeros_like(s.t_starts)
    j = torch.arange(n_f, dtype=dtype, device=device)
    length = (far - near)[:, None]
    tol = 1e-12 if dtype == F64 else 2e-5
    t = _new_positions(s, importance_samples(s, w, n_f))
    torch.testing.assert_close(t, near[:, None] + (j + 0.5) / n_f * length, rtol=0.0, atol=tol)
    t = _new_positions(s, importance_samples(s, w, n_f, perturb=True, seed=4))
    stratum = (t - near[:, None]) / length * n_f - j  # in [0, 1)
    assert bool((stratum > -tol * n_f).all()) and bool((stratum < 1 + tol * n_f).all())
    assert float(stratum.std()) > 0.25  # jittered over the stratum (uniform: 0.29)


def test_single_nonzero_weight_concentrates_samples(device):
    n_rays, n_c, n_f = 500, 64, 64
    s, _, _ = _coarse(n_rays, n_c, F64, device)
    k = torch.randint(0, n_c, (n_rays,), device=device)
    w = torch.zeros(n_rays, n_c, dtype=F64, device=device)
    w[torch.arange(n_rays, device=device), k] = 1.0
    lo, hi = s.t_starts.gather(1, k[:, None]), s.t_ends.gather(1, k[:, None])
    # Evaluation: the padding outside interval k (< n_c eps = 6.4e-4) is below u_0 = 1 / 128.
    t = _new_positions(s, importance_samples(s, w, n_f))
    assert bool(((t >= lo) & (t <= hi)).all())
    # Training: a position leaves interval k only with the padding's probability (~6.4e-4).
    t = _new_positions(s, importance_samples(s, w, n_f, perturb=True, seed=8))
    outside = float(((t < lo) | (t > hi)).double().mean())
    assert outside < 3e-3
    assert abs(float(((t - lo) / (hi - lo)).clamp(0, 1).mean()) - 0.5) < 0.01  # uniform inside


@pytest.mark.parametrize("perturb", [False, True])
def test_packed_matches_dense_rows_with_empty_rays(device, perturb):
    n_rays, n_c, n_f = 40, 8, 12
    d, near, far = _coarse(n_rays, n_c, F64, device, n_miss=5)
    p = W.stratified_samples(near, far, n_c, perturb=True, seed=3, packed=True)
    hit = far > near
    wd = _weights((n_rays, n_c), F64, device)
    out_p = importance_samples(p, wd[hit].reshape(-1), n_f, perturb=perturb, seed=5)
    out_d = importance_samples(d, wd, n_f, perturb=perturb, seed=5)
    counts = out_p.packed_info[:, 1]
    assert out_p.packed_info.dtype == torch.int32 and out_p.ray_indices.dtype == torch.int64
    assert bool((counts[~hit] == 0).all()) and bool((counts[hit] == n_c + n_f).all())
    assert torch.equal(out_p.packed_info, W.packed_info_from_ray_indices(out_p.ray_indices, n_rays))
    # Same RNG key (seed and ray index) as the dense layout: bit-identical rows.
    assert torch.equal(out_p.t_starts, out_d.t_starts[hit].reshape(-1))
    assert torch.equal(out_p.t_ends, out_d.t_ends[hit].reshape(-1))


def test_packed_variable_counts(device):
    """Rays with 0, 1, 2, ... coarse intervals (prefixes of stratified rays) against the twin."""
    n_rays = 12
    d, _, _ = _coarse(n_rays, 10, F64, device)
    counts = torch.tensor([3, 0, 1, 10, 0, 7, 2, 10, 5, 0, 1, 4])
    keep = torch.arange(10)[None, :] < counts[:, None]
    ray_indices = torch.arange(n_rays).repeat_interleave(counts).to(device)
    info = torch.stack([torch.cumsum(counts, 0) - counts, counts], -1).to(torch.int32).to(device)
    keep = keep.to(device)
    s = Samples(d.t_starts[keep], d.t_ends[keep], ray_indices, info)
    w = _weights((n_rays, 10), F64, device)[keep]
    out = _match(s, w, 6, _tol(device, F64))
    assert out.packed_info[:, 1].tolist() == torch.where(counts > 0, counts + 6, 0).tolist()


def test_packed_all_rays_empty(device):
    info = torch.zeros(3, 2, dtype=torch.int32, device=device)
    empty = torch.empty(0, dtype=F64, device=device)
    s = Samples(empty, empty, torch.empty(0, dtype=torch.int64, device=device), info)
    out = importance_samples(s, empty, 8, perturb=True)
    assert out.t_starts.numel() == 0 and out.ray_indices.numel() == 0
    assert out.packed_info.tolist() == [[0, 0]] * 3


def test_point_mass_on_zero_length_interval(device):
    """A weight on a zero-length coarse interval is a point mass: new positions land on it."""
    edges = torch.tensor([[0.0, 1.0, 2.0, 2.0, 3.0, 4.0]], dtype=F64, device=device)
    s = Samples(edges[:, :-1].contiguous(), edges[:, 1:].contiguous())
    w = torch.tensor([[0.0, 0.0, 1.0, 0.0, 0.0]], dtype=F64, device=device)
    out = importance_samples(s, w, 10, perturb=True, seed=1)
    _assert_partition(out, edges[:, 0], edges[:, -1])
    big = _edges(out)
    assert int((big == 2.0).sum()) >= 2 + 9  # both coarse copies and (almost) all new positions
    # Degenerate ray (near == far) with non-zero weights: everything stays at near.
    fives = torch.full((1, 3), 5.0, dtype=F64, device=device)
    s0 = Samples(fives, fives.clone())
    out0 = importance_samples(s0, torch.ones(1, 3, dtype=F64, device=device), 4, perturb=True)
    assert bool((out0.t_starts == 5.0).all()) and bool((out0.t_ends == 5.0).all())


def test_long_rays_match_reference(device):
    s, near, far = _coarse(4, 2048, F64, device)
    w = torch.zeros(4, 2048, dtype=F64, device=device)
    w[:, 1000:1010] = 0.1  # a thin surface
    w[:, 1500] = 0.05
    out = _match(s, w, 1024, _tol(device, F64))
    _assert_partition(out, near, far)
    in_surface = (out.midpoints() > s.t_starts[:, 1000:1001]) & (
        out.midpoints() < s.t_ends[:, 1009:1010]
    )
    assert bool((in_surface.sum(1) > 600).all())  # 10/15 of the mass: ~680 of 1024


def test_seeds(device):
    s, _, _ = _coarse(64, 16, F64, device)
    w = _weights((64, 16), F64, device)
    a = importance_samples(s, w, 16, perturb=True, seed=1)
    b = importance_samples(s, w, 16, perturb=True, seed=1)
    c = importance_samples(s, w, 16, perturb=True, seed=2)
    e = importance_samples(s, w, 16)
    assert torch.equal(a.t_starts, b.t_starts) and torch.equal(a.t_ends, b.t_ends)
    ta, tc, te = (_new_positions(s, x) for x in (a, c, e))
    assert bool((ta != tc).all()) and bool((ta != te).all())
    assert torch.equal(importance_samples(s, w, 16, seed=3).t_starts, e.t_starts)


def test_same_seed_as_stratified_is_not_correlated(device):
    """stratified(seed) then importance(seed), zero weights, n_f = n_c: with one shared random
    stream new position j would sit exactly half a bin before coarse edge j + 1 on every ray
    (both are near + (j + U_j) D up to that half bin); the salted seed decorrelates them."""
    near = torch.zeros(256, dtype=F64, device=device)
    s = W.stratified_samples(near, near + 1.0, 16, perturb=True, seed=7)
    out = importance_samples(s, torch.zeros_like(s.t_starts), 16, perturb=True, seed=7)
    gap = (s.t_ends - _new_positions(s, out)) * 16  # coarse edge j + 1 minus position j, in bins
    assert float(gap.std()) > 0.3  # independent uniforms: 0.5 + U - U' has std 0.41


def test_detached_weights(device):
    s, _, _ = _coarse(8, 8, F64, device)
    w = _weights((8, 8), F64, device).requires_grad_()
    out = importance_samples(s, w, 4)
    assert not out.t_starts.requires_grad and not out.t_ends.requires_grad


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf"), -1e-3])
def test_bad_weights_raise(device, bad):
    for packed in (False, True):
        s, _, _ = _coarse(6, 8, F64, device, packed=packed)
        w = _weights(s.t_starts.shape, F64, device)
        w.view(-1)[5] = bad
        with pytest.raises(ValueError, match=r"\bweights\b"):
            importance_samples(s, w, 4)


def test_rejects_bad_arguments():
    s, _, _ = _coarse(4, 8, F64, torch.device("cpu"))
    w = torch.rand(4, 8, dtype=F64)
    for n_fine in (0, -2, 2.0, True):
        with pytest.raises(ValueError, match=r"\bn_fine\b"):
            importance_samples(s, w, n_fine)
    with pytest.raises(ValueError, match=r"\bweights\b"):
        importance_samples(s, w[:, :7], 4)
    with pytest.raises(ValueError, match=r"\bweights\b"):
        importance_samples(s, w.float(), 4)
    with pytest.raises(ValueError, match=r"\bsamples\b"):
        importance_samples((s.t_starts, s.t_ends), w, 4)
    with pytest.raises(ValueError, match=r"samples\.t_ends"):
        importance_samples(Samples(s.t_starts, s.t_ends[:, :7]), w, 4)
    gap = s.t_starts.clone()
    gap[1, 3] += 1e-3
    with pytest.raises(ValueError, match=r"samples must partition"):
        importance_samples(Samples(gap, s.t_ends), w, 4)
    flipped = Samples(s.t_ends.flip(1), s.t_starts.flip(1))
    with pytest.raises(ValueError, match=r"t_ends >= t_starts"):
        importance_samples(flipped, w, 4)
    nan_t = s.t_starts.clone()
    nan_t[0, 0] = float("nan")
    with pytest.raises(ValueError, match=r"finite t_starts"):
        importance_samples(Samples(nan_t, s.t_ends), w, 4)
    p, _, _ = _coarse(4, 8, F64, torch.device("cpu"), packed=True)
    wp_ = torch.rand(p.t_starts.shape[0], dtype=F64)
    bad_info = p.packed_info.clone()
    bad_info[-1, 1] += 1
    with pytest.raises(ValueError, match=r"packed_info"):
        importance_samples(p._replace(packed_info=bad_info), wp_, 4)
    with pytest.raises(ValueError, match=r"packed_info"):
        importance_samples(p._replace(packed_info=p.packed_info.long()), wp_, 4)
    with pytest.raises(ValueError, match=r"ray_indices"):
        importance_samples(p._replace(ray_indices=None), wp_, 4)
    with pytest.raises(ValueError, match=r"\bweights\b"):
        importance_samples(p, w, 4)  # dense weights for packed samples
