"""Compositing kernels (kernels/composite.py via warpnerf.ops.composite) against the pure-PyTorch
reference (warpnerf.reference.composite): forward, exact backward, gradcheck, packed == dense,
early termination and argument validation. Hard cases live in test_composite_hard.py."""

from __future__ import annotations

import pytest
import torch

import warpnerf as W
from warpnerf import reference as R

from ._composite_cases import (
    F32,
    F64,
    OUT_NAMES,
    _background,
    _case,
    _dense_case,
    _match,
    _mk,
    _pack,
    _packed_case,
    _render,
    _run,
    _to,
    _upstream,
)
from ._twin import EXACT, assert_outputs_close, gradcheck_op

# --------------------------------------------------------------------------------------------------
# 1. forward and gradients vs the float64 reference (tests/_twin.py: also finite, non-zero grads)


@pytest.mark.parametrize("t_threshold", [0.0, 1e-2, 0.3])
@pytest.mark.parametrize("bg_kind", ["none", "shared", "per_ray"])
@pytest.mark.parametrize("mode", ["sigma", "alpha"])
@pytest.mark.parametrize("layout", ["packed", "dense"])
def test_matches_reference_float64(device, layout, mode, bg_kind, t_threshold):
    case = _case(layout, mode, device=device)
    bg = _background(bg_kind, case.n_rays, device)
    r = _match(case, bg, t_threshold)
    # The test must exercise something: termination when asked for.
    if t_threshold > 0:
        full, _ = _run(R, case, bg, 0.0)
        assert bool((full[3] != r.ref["weights"]).any()), "no ray terminated early: weak test data"
    # Weights sum to the opacity.
    if layout == "packed":
        w_sum = torch.zeros_like(r.out["opacity"]).index_add(0, case.ray_indices, r.out["weights"])
    else:
        w_sum = r.out["weights"].sum(1)
    torch.testing.assert_close(w_sum, r.out["opacity"], rtol=0, atol=1e-12)


@pytest.mark.parametrize("mode", ["sigma", "alpha"])
@pytest.mark.parametrize("layout", ["packed", "dense"])
def test_return_weights_false_matches_reference(device, layout, mode):
    case = _case(layout, mode, device=device)
    bg = _background("per_ray", case.n_rays, device)
    r = _match(case, bg, 0.0, return_weights=False)
    assert list(r.out) == list(OUT_NAMES[:3])


@pytest.mark.parametrize("mode", ["sigma", "alpha"])
@pytest.mark.parametrize("layout", ["packed", "dense"])
def test_float32_matches_float64(device, layout, mode):
    """The float32 kernel against the float64 twin on the same float32-rounded inputs."""
    case32 = _to(_case(layout, mode, device=device), device, F32)
    bg = _background("per_ray", case32.n_rays, device, F32)
    _match(
        case32,
        bg,
        twin_dtype=F64,
        tol={"rtol": 1e-5, "atol": 1e-6},
        grad_tol={"rtol": 1e-5, "atol": 1e-5},
    )


# --------------------------------------------------------------------------------------------------
# 2. gradcheck on tiny float64 inputs


@pytest.mark.parametrize("return_weights", [False, True])
@pytest.mark.parametrize("bg_kind", ["shared", "per_ray"])
@pytest.mark.parametrize("mode", ["sigma", "alpha"])
@pytest.mark.parametrize("layout", ["packed", "dense"])
def test_gradcheck(device, layout, mode, bg_kind, return_weights):
    if layout == "packed":
        case = _packed_case([2, 3, 1], mode, sigma_max=3.0, device=device)
    else:
        case = _dense_case(3, 3, mode, sigma_max=3.0, device=device)
    bg = _background(bg_kind, case.n_rays, device)
    if mode == "alpha":
        assert bool(((case.values > 0.05) & (case.values < 0.95)).all())

    def fn(values, rgbs, background):
        return _render(W, case, values, rgbs, background, 0.0, return_weights)

    inputs = {"values": case.values, "rgbs": case.rgbs, "background": bg}
    gradcheck_op(fn, inputs, list(inputs), eps=1e-6, atol=1e-8, rtol=1e-6)


# --------------------------------------------------------------------------------------------------
# 3. packed == dense on the same samples


@pytest.mark.parametrize("t_threshold", [0.0, 1e-2])
@pytest.mark.parametrize("mode", ["sigma", "alpha"])
def test_packed_equals_dense(device, mode, t_threshold):
    n_rays, n_s = 5, 8
    near = (torch.rand(n_rays, dtype=F64) * 0.5 + 0.1).to(device)
    far = near + 1.0 + torch.rand(n_rays, dtype=F64).to(device)
    dense = W.stratified_samples(near, far, n_s, perturb=True, seed=3)
    packed = W.stratified_samples(near, far, n_s, perturb=True, seed=3, packed=True)
    assert torch.equal(packed.t_starts, dense.t_starts.reshape(-1))
    values = torch.rand(n_rays, n_s, dtype=F64) * (0.9 if mode == "alpha" else 6.0)
    values = (values + (0.05 if mode == "alpha" else 0.0)).to(device)
    rgbs = torch.rand(n_rays, n_s, 3, dtype=F64).to(device)
    bg = _background("per_ray", n_rays, device)
    dcase = _mk("dense", mode, n_rays, dense.t_starts, dense.t_ends, None, values, rgbs)
    pcase = _pack(dcase)
    pcase.ray_indices, pcase.t_starts, pcase.t_ends = packed[2], packed[0], packed[1]
    g = _upstream(dcase)
    d_out, d_grads = _run(W, dcase, bg, t_threshold, g)
    p_out, p_grads = _run(W, pcase, bg, t_threshold, g[:3] + [g[3].reshape(-1)])
    d_out[3] = d_out[3].reshape(-1)
    d_grads[0] = d_grads[0].reshape(-1)
    d_grads[1] = d_grads[1].reshape(-1, 3)
    assert_outputs_close(p_out, d_out, tol=EXACT, names=OUT_NAMES)
    assert_outputs_close(p_grads, d_grads, tol=EXACT, names=("values", "rgbs", "background"))


# --------------------------------------------------------------------------------------------------
# 5. early termination


@pytest.mark.parametrize("layout", ["packed", "dense"])
@pytest.mark.parametrize("t_threshold, n_live", [(0.3, 2), (1e-2, 5), (0.0, 6)])
def test_early_termination(device, layout, t_threshold, n_live):
    """tau = 1 per sample: T_i = e^-i = 1, .37, .14, .050, .018, .0067. A ray stops at the first
    sample with T_i < threshold; later samples get weight 0 and zero gradient, even with upstream
    gradient on their weights, and the background is seen through T_m = e^-m."""
    n_s = 6
    t_starts = torch.arange(n_s, dtype=F64) * 0.5
    sig = torch.full((1, n_s), 2.0, dtype=F64)  # delta 0.5 -> tau 1
    rgbs = torch.rand(1, n_s, 3, dtype=F64)
    case = _mk("dense", "sigma", 1, t_starts[None], t_starts[None] + 0.5, None, sig, rgbs)
    case = _to(_pack(case) if layout == "packed" else case, device, F64)
    bg = torch.rand(3, dtype=F64, device=device)
    r = _match(case, bg, t_threshold)
    out, grads, g = r.out, r.grads, r.cotangents
    w = out["weights"].reshape(-1)
    v_sig, v_rgb = grads["d/dvalues"].reshape(-1), grads["d/drgbs"].reshape(-1, 3)
    assert bool((w[:n_live] > 0).all()) and bool((w[n_live:] == 0).all())
    assert bool((v_sig[:n_live] != 0).all()) and bool((v_sig[n_live:] == 0).all())
    assert bool((v_rgb[n_live:] == 0).all())
    t_m = torch.exp(torch.tensor(-float(n_live), dtype=F64))
    torch.testing.assert_close(out["opacity"][0], 1 - t_m.to(device), rtol=0, atol=1e-15)
    expected_rgb = (w[:n_live, None] * case.rgbs.reshape(-1, 3)[:n_live]).sum(0) + t_m * bg
    torch.testing.assert_close(out["rgb"][0], expected_rgb, rtol=0, atol=1e-15)
    torch.testing.assert_close(grads["d/dbackground"], t_m * g["rgb"][0], rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("mode", ["sigma", "alpha"])
def test_early_termination_random_matches_reference(device, mode):
    """Many rays terminating at different samples; the reference masks samples with T_i < thr."""
    case = _dense_case(40, 24, mode, sigma_max=6.0, device=device)
    bg = _background("per_ray", case.n_rays, device)
    r = _match(case, bg, 0.05)
    dead = r.out["weights"] == 0
    assert 0 < int(dead.sum()) < dead.numel()
    assert bool((r.grads["d/dvalues"][dead] == 0).all())
    assert bool((r.grads["d/drgbs"][dead] == 0).all())
    # Once dead, a ray stays dead: no live sample after a dead one.
    assert bool((dead.int().diff(dim=1) >= 0).all())


# --------------------------------------------------------------------------------------------------
# 6. validation


def _valid_packed(n=6, n_rays=2):
    return dict(
        t_starts=torch.zeros(n, dtype=F64),
        t_ends=torch.ones(n, dtype=F64),
        ray_indices=torch.tensor([0] * (n // 2) + [1] * (n - n // 2)),
        sigmas=torch.ones(n, dtype=F64),
        rgbs=torch.zeros(n, 3, dtype=F64),
        n_rays=n_rays,
    )


PACKED_BAD = {
    "t_starts": dict(t_starts=torch.zeros(5, dtype=F64)),
    "t_ends": dict(t_ends=torch.ones(6, dtype=F32)),
    "rgbs": dict(rgbs=torch.zeros(6, 4, dtype=F64)),
    "sigmas": dict(sigmas=torch.ones(6, 1, dtype=F64)),
    "ray_indices": dict(ray_indices=torch.tensor([0, 1, 0, 1, 0, 1])),
    "background": dict(background=torch.zeros(3, 3, dtype=F64)),
    "packed_info": dict(packed_info=torch.zeros(3, 2, dtype=torch.int32)),
}


@pytest.mark.parametrize("arg", list(PACKED_BAD))
def test_render_packed_rejects_bad_argument(arg):
    kw = _valid_packed()
    W.render_packed(**kw)  # the valid call works
    kw.update(PACKED_BAD[arg])
    with pytest.raises(ValueError, match=rf"\b{arg}\b"):
        W.render_packed(**kw)


def test_render_packed_rejects_mismatched_rgbs_dtype_and_unsorted_indices():
    kw = _valid_packed()
    kw["rgbs"] = kw["rgbs"].float()
    with pytest.raises(ValueError, match=r"\brgbs\b"):
        W.render_packed(**kw)
    kw = _valid_packed()
    kw["ray_indices"] = torch.tensor([1, 1, 1, 0, 0, 0])
    with pytest.raises(ValueError, match=r"ray_indices.*sorted"):
        W.render_packed(**kw)
    kw = _valid_packed()
    kw["ray_indices"] = torch.tensor([0, 0, 1, 1, 2, 2])  # ray 2 of n_rays=2
    with pytest.raises(ValueError, match=r"ray_indices"):
        W.render_packed(**kw)


@pytest.mark.parametrize("which", ["both", "neither"])
def test_sigmas_xor_alphas(which):
    kw = _valid_packed()
    if which == "both":
        kw["alphas"] = torch.full((6,), 0.5, dtype=F64)
    else:
        kw["sigmas"] = None
    with pytest.raises(ValueError, match=r"sigmas.*alphas"):
        W.render_packed(**kw)
    d = dict(
        t_starts=torch.zeros(2, 3, dtype=F64),
        t_ends=torch.ones(2, 3, dtype=F64),
        sigmas=torch.ones(2, 3, dtype=F64),
        rgbs=torch.zeros(2, 3, 3, dtype=F64),
    )
    if which == "both":
        d["alphas"] = torch.full((2, 3), 0.5, dtype=F64)
    else:
        d["sigmas"] = None
    with pytest.raises(ValueError, match=r"sigmas.*alphas"):
        W.render_dense(**d)


DENSE_BAD = {
    "sigmas": dict(sigmas=torch.ones(6, dtype=F64)),
    "alphas": dict(sigmas=None, alphas=torch.full((2, 3), 0.5, dtype=torch.float16)),
    "t_starts": dict(t_starts=torch.zeros(2, 4, dtype=F64)),
    "t_ends": dict(t_ends=torch.ones(2, 3, dtype=F32)),
    "rgbs": dict(rgbs=torch.zeros(2, 3, dtype=F64)),
    "background": dict(background=torch.zeros(4, 3, dtype=F64)),
}


@pytest.mark.parametrize("arg", list(DENSE_BAD))
def test_render_dense_rejects_bad_argument(arg):
    kw = dict(
        t_starts=torch.zeros(2, 3, dtype=F64),
        t_ends=torch.ones(2, 3, dtype=F64),
        sigmas=torch.ones(2, 3, dtype=F64),
        rgbs=torch.zeros(2, 3, 3, dtype=F64),
    )
    W.render_dense(**kw)
    kw.update(DENSE_BAD[arg])
    with pytest.raises(ValueError, match=rf"\b{arg}\b"):
        W.render_dense(**kw)


def test_packed_info_from_ray_indices():
    info = W.packed_info_from_ray_indices(torch.tensor([1, 1, 3, 3, 3]), 5)
    assert info.dtype == torch.int32
    assert info.tolist() == [[0, 0], [0, 2], [2, 0], [2, 3], [5, 0]]
    with pytest.raises(ValueError, match="ray_indices"):
        W.packed_info_from_ray_indices(torch.tensor([3, 1]), 5)
