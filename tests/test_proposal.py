"""Proposal sampling's kernels (kernels/proposal.py): inverse-CDF resampling and the interlevel
loss against their nerfstudio-style twins in float64 (loss and proposal-weight gradients),
gradcheck, known values, and hard cases (huge and zero weights, zero-length bins, many samples,
rays whose proposal misses the fine weight, NaN/Inf inputs, input checks)."""

from __future__ import annotations

import math

import pytest
import torch

from warpnerf.ops.proposal import interlevel_loss, proposal_resample
from warpnerf.reference import proposal as R

from ._twin import assert_matches_twin, gradcheck_op

TOL = {torch.float64: {"rtol": 1e-10, "atol": 1e-12}, torch.float32: {"rtol": 1e-4, "atol": 1e-6}}
F64 = torch.float64


def histogram(n_rays, n, seed=0, device="cpu", dtype=F64):
    """Edges in [0, 1] (sorted, some bins of zero length) and weights summing below 1."""
    g = torch.Generator().manual_seed(seed)
    e = torch.sort(torch.rand(n_rays, n + 1, generator=g, dtype=F64), -1)[0]
    if n > 2:
        e[0, 2] = e[0, 1]  # a zero-length bin
    w = torch.rand(n_rays, n, generator=g, dtype=F64)
    w = w / (w.sum(-1, keepdim=True) * 1.25)
    return e.to(device, dtype), w.to(device, dtype)


def interlevel_inputs(n_rays, n_f, n_p, seed=0, device="cpu", dtype=F64):
    s_prop, w_prop = histogram(n_rays, n_p, seed, device, dtype)
    s_fine, w_fine = histogram(n_rays, n_f, seed + 1, device, dtype)
    return {"s_fine": s_fine, "w_fine": w_fine, "s_prop": s_prop, "w_prop": w_prop}


# --- resampling ------------------------------------------------------------------------------


@pytest.mark.parametrize("jitter", ["none", "ray", "edge"])
@pytest.mark.parametrize("anneal", [1.0, 0.35, 0.0])
def test_resample_matches_the_searchsorted_twin(device, jitter, anneal):
    e, w = histogram(6, 9, device=device)
    w[1] = 0.0  # an empty ray: padding only
    w[2, 4] = 0.0
    g = torch.Generator().manual_seed(3)
    jit = {"none": None, "ray": torch.rand(6, generator=g, dtype=F64),
           "edge": torch.rand(6, 13, generator=g, dtype=F64)}[jitter]  # fmt: skip
    inputs = dict(s_edges=e, weights=w, n_samples=12, anneal=anneal,
                  jitter=None if jit is None else jit.to(device))  # fmt: skip
    for padding in (0.01, 0.0):
        run = assert_matches_twin(proposal_resample, R.proposal_resample,
                                  {**inputs, "padding": padding}, tol=TOL)  # fmt: skip
        out = run.out["out"]
        assert out.shape == (6, 13)
        assert (out[:, 1:] >= out[:, :-1]).all()  # sorted
        assert (out >= e[:, :1]).all() and (out <= e[:, -1:]).all()  # inside the ray's bins


def test_resample_known_values(device):
    """Uniform masses on [0, 1]: the quantiles themselves; all weight in one bin (no padding):
    every new edge inside it; annealing to 0 flattens any histogram to its bins' count."""
    kw = dict(dtype=F64, device=device)
    e = torch.linspace(0, 1, 5, **kw).expand(1, 5)
    flat = proposal_resample(e, torch.full((1, 4), 0.2, **kw), 3)
    assert torch.allclose(flat, (torch.arange(4, **kw) + 0.5) / 4)
    peak = torch.tensor([[0.0, 0.0, 0.9, 0.0]], **kw)
    inside = proposal_resample(e, peak, 7, padding=0.0)
    assert (inside >= 0.5).all() and (inside <= 0.75).all()
    assert torch.allclose(proposal_resample(e, peak, 3, anneal=0.0), flat)
    jit = torch.zeros(1, **kw)
    assert torch.allclose(proposal_resample(e, peak * 0, 3, jitter=jit), torch.arange(4, **kw) / 4)


def test_resample_follows_the_histogram(device):
    """Many samples: the fraction of new intervals in each bin tracks its mass."""
    kw = dict(dtype=F64, device=device)
    e = torch.tensor([[0.0, 0.1, 0.5, 0.6, 1.0]], **kw)
    w = torch.tensor([[0.1, 0.0, 0.6, 0.3]], **kw)
    n = 10_000
    out = proposal_resample(e, w, n, padding=0.0)[0]
    mid = 0.5 * (out[1:] + out[:-1])
    counts = torch.histc(mid.cpu(), bins=4, min=0, max=1)  # (bins of 0.25: not the histogram's)
    share = [float(((mid >= a) & (mid < b)).sum()) / n for a, b in ((0, 0.1), (0.5, 0.6),
                                                                     (0.6, 1.0))]  # fmt: skip
    assert share == pytest.approx([0.1, 0.6, 0.3], abs=2e-3) and counts.sum() == n


def test_resample_float32_and_huge_weights(device):
    """float32 against the float64 twin; weights up to 1e30 (annealed to a power) stay finite."""
    e, w = histogram(40, 64, seed=5)
    w[3] *= 1e30
    for a in (1.0, 0.5):
        exact = R.proposal_resample(e, w, 48, anneal=a)
        got = proposal_resample(e.float().to(device), w.float().to(device), 48, anneal=a)
        assert torch.isfinite(got).all()
        assert torch.allclose(got.double().cpu(), exact, atol=2e-5)


def test_resample_nan_inf_and_checks(device):
    e, w = histogram(3, 5, device=device)
    bad = w.clone()
    bad[1, 2] = float("nan")
    with pytest.raises(ValueError, match="weights"):
        proposal_resample(e, bad, 4)
    out = proposal_resample(e, bad, 4, check=False)
    assert out[1].isnan().all() and torch.isfinite(out[[0, 2]]).all()
    bad[1, 2] = float("inf")
    assert proposal_resample(e, bad, 4, check=False)[1].isnan().all()
    e_bad = e.clone()
    e_bad[2, 0] = float("-inf")
    with pytest.raises(ValueError, match="finite"):
        proposal_resample(e_bad, w, 4)
    assert proposal_resample(e_bad, w, 4, check=False)[2].isnan().all()
    with pytest.raises(ValueError, match="non-decreasing"):
        proposal_resample(e.flip(-1), w, 4)
    with pytest.raises(ValueError, match=">= 0"):
        proposal_resample(e, -w, 4)
    with pytest.raises(ValueError, match="jitter"):
        proposal_resample(e, w, 4, jitter=torch.ones(3, dtype=F64, device=device))
    with pytest.raises(ValueError, match="shape"):
        proposal_resample(e[:, :-1], w, 4)
    with pytest.raises(ValueError, match="anneal"):
        proposal_resample(e, w, 4, anneal=1.5)
    with pytest.raises(ValueError, match="n_samples"):
        proposal_resample(e, w, 0)
    assert proposal_resample(e[:0], w[:0], 4).shape == (0, 5)


def test_resample_has_no_gradient(device):
    e, w = histogram(2, 4, device=device)
    out = proposal_resample(e, w.requires_grad_(True), 3)
    assert not out.requires_grad


# --- the interlevel loss ---------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_interlevel_matches_nerfstudio_twin(device, dtype):
    inputs = interlevel_inputs(12, 8, 16, device=device, dtype=dtype)
    assert_matches_twin(interlevel_loss, R.interlevel_loss, inputs, tol=TOL, grad=("w_prop",),
                        twin_dtype=torch.float64)  # fmt: skip


def test_interlevel_gradcheck(device):
    inputs = interlevel_inputs(3, 4, 5, device=device)
    inputs["w_prop"] = inputs["w_prop"] * 0.3  # (most fine intervals above their bound)
    gradcheck_op(interlevel_loss, inputs, ("w_prop",))


def test_interlevel_known_values(device):
    """Identical histograms: 0. A proposal with no weight where the fine one has w: w^2/(w+eps)
    per interval. The fine weights get no gradient."""
    kw = dict(dtype=F64, device=device)
    s = torch.linspace(0, 1, 5, **kw).expand(2, 5).contiguous()
    w = torch.tensor([[0.1, 0.5, 0.2, 0.0], [0.0, 0.3, 0.0, 0.6]], **kw)
    assert interlevel_loss(s, w, s, w).abs().max() == 0
    zero = torch.zeros_like(w)
    got = interlevel_loss(s, w, s, zero)
    assert torch.allclose(got, (w * w / (w + 1e-7)).sum(-1))
    wf = w.clone().requires_grad_(True)
    wp = zero.clone().requires_grad_(True)
    interlevel_loss(s, wf, s, wp).sum().backward()
    assert wf.grad is None and (wp.grad <= 0).all() and wp.grad.abs().sum() > 0
    # a coarse proposal bin covering two fine ones bounds both
    coarse = torch.linspace(0, 1, 3, **kw).expand(2, 3).contiguous()
    bound = torch.stack([w[:, :2].sum(-1), w[:, 2:].sum(-1)], -1)
    assert interlevel_loss(s, w, coarse, bound).abs().max() == 0


def test_interlevel_hard_cases(device):
    """Fine edges outside the proposal's span, zero-length intervals on both sides, 1,024 fine
    against 2,048 proposal intervals, and NaN weights staying in their ray."""
    inputs = interlevel_inputs(4, 6, 5, seed=7, device=device)
    inputs["s_fine"] = inputs["s_fine"] * 3 - 1  # beyond both ends of the proposal
    inputs["s_fine"][1] = 0.5  # all zero-length
    assert_matches_twin(interlevel_loss, R.interlevel_loss, inputs, tol=TOL, grad=("w_prop",))
    big = interlevel_inputs(2, 1024, 2048, seed=9, device=device)
    assert_matches_twin(interlevel_loss, R.interlevel_loss, big, tol=TOL, grad=("w_prop",))
    nan = interlevel_inputs(3, 4, 5, device=device)
    nan["w_prop"][1, 2] = float("nan")
    out = interlevel_loss(**nan)
    assert math.isnan(float(out[1])) and torch.isfinite(out[[0, 2]]).all()
    inf = interlevel_inputs(3, 4, 5, device=device)
    inf["w_fine"][2, 0] = float("inf")
    assert not math.isfinite(float(interlevel_loss(**inf)[2]))
    with pytest.raises(ValueError, match="non-decreasing"):
        interlevel_loss(**{**nan, "s_prop": nan["s_prop"].flip(-1)})
    with pytest.raises(ValueError, match="shape"):
        interlevel_loss(**{**nan, "s_fine": nan["s_fine"][:, :-1]})
