"""Compositing hard cases: extreme sigma * delta, zero-length intervals, 10^4 samples on a ray,
empty rays, the background gradient on opaque rays, opaque (alpha = 1) samples and NaN inputs."""

from __future__ import annotations

import itertools
from types import SimpleNamespace

import pytest
import torch

import warpnerf as W
from warpnerf import reference as R

from ._composite_cases import (
    F32,
    F64,
    OUT_NAMES,
    _background,
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

# --------------------------------------------------------------------------------------------------
# 4. hard cases


def _extreme_case(mode, layout, device):
    """Every ordered triple of distinct extreme optical depths (or opacities) as one ray each."""
    if mode == "sigma":
        levels = [0.0, 1e-12, 1.0, 1e3, 1e8, float("inf")]
    else:
        levels = [0.0, 1e-12, 0.5, 1.0 - 1e-9, 1.0]
    rows = torch.tensor(list(itertools.permutations(levels, 3)), dtype=F64)
    n_rays, n_s = rows.shape
    deltas = torch.rand(n_rays, n_s, dtype=F64) + 0.5  # > 0, so sigma = inf / delta is inf
    t_ends = torch.cumsum(deltas, 1)
    t_starts = t_ends - deltas
    values = rows / deltas if mode == "sigma" else rows
    rgbs = torch.rand(n_rays, n_s, 3, dtype=F64)
    case = _mk("dense", mode, n_rays, t_starts, t_ends, None, values, rgbs)
    return _to(_pack(case) if layout == "packed" else case, device, F64)


@pytest.mark.parametrize("t_threshold", [0.0, 1e-2])
@pytest.mark.parametrize("mode", ["sigma", "alpha"])
@pytest.mark.parametrize("layout", ["packed", "dense"])
def test_extreme_optical_depths(device, layout, mode, t_threshold):
    case = _extreme_case(mode, layout, device)
    bg = _background("per_ray", case.n_rays, device)
    # Outputs and gradients finite; against the reference wherever the reference is itself
    # finite. Its alpha-mode gradient goes through d(-log(1 - a))/da = 1 / (1 - a): inf at a = 1
    # (NaN gradient, skipped), and at a = 1 - 1e-9, 1 - a carries a relative rounding error of
    # ~1e-16 / 1e-9 = 1e-7.
    tol = {"rtol": 1e-7 if mode == "alpha" else 1e-10, "atol": 1e-10}
    r = _match(case, bg, t_threshold, tol=tol, where_twin_finite=True)
    rgb, depth, opacity, weights = r.out.values()
    assert bool(((opacity >= 0) & (opacity <= 1)).all()), opacity
    assert bool((weights >= 0).all())
    w_sum = weights.sum(1) if layout == "dense" else weights.reshape(case.n_rays, -1).sum(1)
    torch.testing.assert_close(w_sum, opacity, rtol=0, atol=1e-15)
    if mode == "sigma":
        assert all(bool(torch.isfinite(x).all()) for x in r.ref_grads.values())


def test_zero_length_intervals_contribute_nothing(device):
    """Samples with t_start == t_end (any finite density, even 1e8) change nothing and get zero
    gradient: ray 0 is ray 1 with three zero-length samples inserted."""
    base = _packed_case([6], "sigma", device=device)
    t0, t1 = base.t_starts, base.t_ends
    sig_zero = torch.tensor([5.0, 1e8, 2.0], dtype=F64, device=device)
    t_zero = torch.stack([t0[0], t0[3], t1[5]])
    keep = torch.ones(9, dtype=torch.bool)
    keep[[0, 4, 8]] = False  # inserted before the first, in the middle, after the last sample
    merged = SimpleNamespace(
        t_starts=torch.empty(9, dtype=F64, device=device),
        values=torch.empty(9, dtype=F64, device=device),
    )
    merged.t_starts[keep], merged.t_starts[~keep] = t0, t_zero
    t_ends = merged.t_starts.clone()
    t_ends[keep] = t1
    merged.values[keep], merged.values[~keep] = base.values, sig_zero
    rgbs = torch.rand(9, 3, dtype=F64, device=device)
    rgbs[keep] = base.rgbs
    t_s, t_e = torch.cat([merged.t_starts, t0]), torch.cat([t_ends, t1])
    idx = torch.tensor([0] * 9 + [1] * 6, device=device)
    values, rgbs = torch.cat([merged.values, base.values]), torch.cat([rgbs, base.rgbs])
    case = _mk("packed", "sigma", 2, t_s, t_e, idx, values, rgbs)
    bg = torch.rand(3, dtype=F64, device=device)
    g = _upstream(case)
    g[0][0], g[1][0], g[2][0] = g[0][1], g[1][1], g[2][1]  # same upstream on both rays
    g[3][:9][keep] = g[3][9:]
    r = _match(case, bg, 0.0, cotangents=g)
    for o in list(r.out.values())[:3]:
        torch.testing.assert_close(o[0], o[1], rtol=0, atol=1e-15)
    w = r.out["weights"]
    assert bool((w[:9][~keep] == 0).all())
    torch.testing.assert_close(w[:9][keep], w[9:], rtol=0, atol=1e-15)
    v_sig, v_rgb = r.grads["d/dvalues"], r.grads["d/drgbs"]
    assert bool((v_sig[:9][~keep] == 0).all()) and bool((v_rgb[:9][~keep] == 0).all())
    torch.testing.assert_close(v_sig[:9][keep], v_sig[9:], rtol=1e-13, atol=1e-14)
    torch.testing.assert_close(v_rgb[:9][keep], v_rgb[9:], rtol=1e-13, atol=1e-14)


# Float32 error on one ray of 10^4 samples (naive float32 sums in the kernel) against the float64
# reference on the same float32-rounded inputs, measured over seeds 0..3 with this set-up:
# sigma_max 1 (opacity ~0.92): rgb <= 1.2e-6, depth <= 6.7e-6, opacity <= 3.4e-6, weights <= 2.1e-9,
#   v_sigmas, v_rgbs <= 6.6e-6, 1.0e-6 of their max;
# sigma_max 5 (opacity ~0.999997): rgb <= 1.6e-5, depth <= 3.4e-6, opacity <= 1.4e-5,
#   weights <= 4.5e-9, gradients <= 7.4e-6, 5.6e-7 of their max;
# v_background (as an error on T_m): <= 1.5e-5.
# On an H100 (CUDA's float32 exp/log differ from the CPU's by a few ulp) v_sigmas reached 5.5e-5
# of its max (2026-11-22). Tolerances below: about 3x the worst measured value on either device.
LONG_RAY_TOL = {
    "rgb": 5e-5,
    "depth": 2e-5,
    "opacity": 5e-5,
    "weights": 2e-8,
    "grad_rel": 1.5e-4,
    "v_background": 5e-5,
}


@pytest.mark.parametrize("sigma_max", [1.0, 5.0])
def test_ten_thousand_samples_float32(device, sigma_max):
    n = 10**4
    ts = torch.sort(torch.rand(n) * 5)[0]
    t0 = torch.cat([torch.zeros(1), ts[:-1]])
    idx = torch.zeros(n, dtype=torch.int64)
    case32 = _mk("packed", "sigma", 1, t0, ts, idx, torch.rand(n) * sigma_max, torch.rand(n, 3))
    case32 = _to(case32, device, F32)
    case64 = _to(case32, device, F64)
    bg = torch.rand(3, device=device)
    # The float64 kernel on the same ray is exact to float64 tolerance; the twin's run is the
    # float64 truth for the float32 kernel below (same cotangents).
    r64 = _match(case64, bg.double(), 0.0, cotangents=_upstream(case64))
    out64, grads64 = list(r64.ref.values()), list(r64.ref_grads.values())
    g = list(r64.cotangents.values())
    out32, grads32 = _run(W, case32, bg, 0.0, [x.float() for x in g])
    err = {name: (a.double() - e).abs().max().item() for a, e, name in zip(out32, out64, OUT_NAMES)}
    for a, e, name in zip(grads32[:2], grads64[:2], ("v_sigmas", "v_rgbs")):
        err[name] = ((a.double() - e).abs().max() / e.abs().max()).item()
    # v_background = T_m v_rgb with T_m ~ 1e-6 here: compared in units of |v_rgb| (an absolute
    # error on T_m); its relative accuracy is test_background_gradient_is_final_transmittance's.
    err["v_background"] = ((grads32[2].double() - grads64[2]).abs().max() / g[0].abs().max()).item()
    print(
        f"\n10^4 samples, sigma_max={sigma_max}, float32 kernel vs float64 reference: "
        + ", ".join(f"{k} {v:.2e}" for k, v in err.items())
    )
    for name in OUT_NAMES:
        assert err[name] <= LONG_RAY_TOL[name], (name, err[name])
    for name in ("v_sigmas", "v_rgbs"):
        assert err[name] <= LONG_RAY_TOL["grad_rel"], (name, err[name])
    assert err["v_background"] <= LONG_RAY_TOL["v_background"], err["v_background"]


@pytest.mark.parametrize("mode", ["sigma", "alpha"])
def test_empty_rays(device, mode):
    """Rays with no samples: rgb == background, depth 0, opacity 0; their upstream gradients reach
    only the background, never another ray's samples."""
    counts = [0, 4, 0, 3, 0]
    case = _packed_case(counts, mode, device=device)
    bg = _background("per_ray", case.n_rays, device)
    r = _match(case, bg, 0.0)
    out, grads, g = list(r.out.values()), list(r.grads.values()), list(r.cotangents.values())
    empty = torch.tensor([c == 0 for c in counts], device=device)
    assert torch.equal(out[0][empty], bg[empty])
    assert bool((out[1][empty] == 0).all()) and bool((out[2][empty] == 0).all())
    # d rgb / d background = 1 on an empty ray.
    assert torch.equal(grads[2][empty], g[0][empty])
    # Upstream gradients on the empty rays change nothing for the samples.
    g2 = [x.clone() for x in g]
    for x in g2[:3]:
        x[empty] = 0
    _, grads2 = _run(W, case, bg, 0.0, g2)
    assert torch.equal(grads2[0], grads[0]) and torch.equal(grads2[1], grads[1])


@pytest.mark.parametrize(
    "dtype, tau_total", [(F32, 12.0), (F32, 20.0), (F64, 30.0)], ids=["f32-12", "f32-20", "f64-30"]
)
def test_background_gradient_is_final_transmittance(device, dtype, tau_total):
    """d rgb / d background = T_m, the transmittance the forward multiplies the background by
    (exp of the log-space sum, > 0). On nearly opaque rays T_m ~ e^-tau_total lies below the
    rounding error of 1 - opacity, so the gradient must not be formed as 1 - opacity."""
    n_rays, n_s = 8, 32
    t_starts = torch.arange(n_s, dtype=F64).repeat(n_rays, 1)
    sig = torch.rand(n_rays, n_s, dtype=F64) * 2 * tau_total / n_s
    rgbs = torch.rand(n_rays, n_s, 3, dtype=F64)
    case = _mk("dense", "sigma", n_rays, t_starts, t_starts + 1, None, sig, rgbs)
    case = _to(case, device, dtype)
    bg = _background("per_ray", n_rays, device, dtype)
    g = [x.abs() for x in _upstream(case)]
    _, grads = _run(W, case, bg, 0.0, g)
    _, ref_grads = _run(R, _to(case, device, F64), bg.double(), 0.0, [x.double() for x in g])
    assert bool((ref_grads[2] > 0).all())
    assert bool((grads[2] >= 0).all()), f"negative d rgb / d background: {grads[2].min()}"
    torch.testing.assert_close(grads[2].double(), ref_grads[2], rtol=1e-3, atol=0)


@pytest.mark.parametrize("mode", ["sigma", "alpha"])
def test_all_rays_empty(device, mode):
    none = torch.empty(0, dtype=F64, device=device)
    bg = torch.rand(4, 3, dtype=F64, device=device, requires_grad=True)
    sig, kw = (None, {"alphas": none}) if mode == "alpha" else (none, {})
    rgb, depth, opacity = W.render_packed(
        none,
        none,
        torch.empty(0, dtype=torch.int64, device=device),
        sig,
        none.reshape(0, 3),
        4,
        bg,
        **kw,
    )
    assert torch.equal(rgb, bg.detach())
    assert bool((depth == 0).all()) and bool((opacity == 0).all())
    v = torch.randn(4, 3, dtype=F64, device=device)
    (v_bg,) = torch.autograd.grad(rgb, bg, v)
    assert torch.equal(v_bg, v)
    # Dense with zero samples per ray behaves the same.
    e = torch.empty(4, 0, dtype=F64, device=device)
    sig, kw = (None, {"alphas": e}) if mode == "alpha" else (e, {})
    rgb, depth, opacity = W.render_dense(e, e, sig, e.reshape(4, 0, 1).expand(4, 0, 3), bg, **kw)
    assert torch.equal(rgb, bg.detach())
    assert bool((depth == 0).all()) and bool((opacity == 0).all())


def _alpha_grad_formula(alphas, e, e_bg):
    """dL/dalpha_i = T_i (e_i - S_i), S_{n-1} = e_bg, S_{i-1} = a_i e_i + (1 - a_i) S_i, written
    with products (no logs), so it is exact for a_i = 1."""
    n = len(alphas)
    trans = [1.0]
    for a in alphas[:-1]:
        trans.append(trans[-1] * (1.0 - a))
    out, s = [0.0] * n, e_bg
    for i in reversed(range(n)):
        out[i] = trans[i] * (e[i] - s)
        s = alphas[i] * e[i] + (1.0 - alphas[i]) * s
    return torch.tensor(out, dtype=F64)


@pytest.mark.parametrize("position", [0, 2, 4])
def test_opaque_alpha_gradient(device, position):
    """alpha = 1 exactly: finite gradients equal to T_i (e_i - S_i), to finite differences (the
    outputs are affine in each single alpha, so a one-sided difference is exact) and to the
    reference at alpha = 1 - 1e-12."""
    n = 5
    alphas = torch.rand(n, dtype=F64) * 0.9 + 0.05
    alphas[position] = 1.0
    t_starts = torch.arange(n, dtype=F64) * 0.5
    idx, rgbs = torch.zeros(n, dtype=torch.int64), torch.rand(n, 3, dtype=F64)
    case = _mk("packed", "alpha", 1, t_starts, t_starts + 0.5, idx, alphas, rgbs)
    case = _to(case, device, F64)
    bg = torch.rand(3, dtype=F64, device=device)
    g = _upstream(case)
    out, grads = _run(W, case, bg, 0.0, g)
    v_alpha = grads[0].cpu()
    assert bool(torch.isfinite(v_alpha).all())
    assert bool((out[3][position + 1 :] == 0).all())
    assert bool((v_alpha[position + 1 :] == 0).all()) and bool(
        (grads[1][position + 1 :] == 0).all()
    )
    # Closed form.
    mids = (0.5 * (case.t_starts + case.t_ends)).cpu()
    e = case.rgbs.cpu() @ g[0][0].cpu() + g[1][0].cpu() * mids + g[2][0].cpu() + g[3].cpu()
    e_bg = float(g[0][0].cpu() @ bg.cpu())
    expected = _alpha_grad_formula(alphas.tolist(), e.tolist(), e_bg)
    torch.testing.assert_close(v_alpha, expected, rtol=1e-12, atol=1e-13)

    # Finite differences of the kernel's own forward.
    def loss(a):
        o = _render(W, case, a, case.rgbs, bg, 0.0, True)
        return sum(float((x * y).sum()) for x, y in zip(o, g))

    fd = torch.empty(n, dtype=F64)
    for i in range(n):
        h = 0.5 * float(alphas[i])
        a = case.values.clone()
        a[i] -= h
        fd[i] = (loss(case.values) - loss(a)) / h
    torch.testing.assert_close(v_alpha, fd, rtol=1e-9, atol=1e-11)
    # The reference just below 1 (its gradient at exactly 1 is inf * 0 = NaN).
    near_one = SimpleNamespace(**vars(case))
    near_one.values = case.values.clone()
    near_one.values[position] = 1.0 - 1e-12
    _, ref_grads = _run(R, near_one, bg, 0.0, g)
    torch.testing.assert_close(v_alpha, ref_grads[0].cpu(), rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(grads[1], ref_grads[1], rtol=1e-9, atol=1e-11)


@pytest.mark.parametrize("t_threshold", [0.0, 1e-2])
@pytest.mark.parametrize("field", ["values", "rgbs"])
@pytest.mark.parametrize("mode", ["sigma", "alpha"])
@pytest.mark.parametrize("layout", ["packed", "dense"])
def test_nan_propagates_to_its_ray_only(device, layout, mode, field, t_threshold):
    bad_ray, bad_sample = 2, 1
    if layout == "packed":
        case = _packed_case([4, 5, 5, 3, 5], mode, sigma_max=1.0, device=device)
        idx = (int(case.ray_indices.tolist().index(bad_ray)) + bad_sample,)
    else:
        case = _dense_case(5, 5, mode, sigma_max=1.0, device=device)
        idx = (bad_ray, bad_sample)
    bg = _background("per_ray", case.n_rays, device)
    g = _upstream(case)
    clean_out, clean_grads = _run(W, case, bg, t_threshold, g)
    bad = SimpleNamespace(**vars(case))
    setattr(bad, field, getattr(case, field).clone())
    if field == "values":
        bad.values[idx] = float("nan")
    else:
        bad.rgbs[idx + (1,)] = float("nan")
    out, grads = _run(W, bad, bg, t_threshold, g)
    ref_out, _ = _run(R, bad, bg, t_threshold, g)
    if field == "values":
        for o, name in zip(out[:3], OUT_NAMES):
            assert bool(torch.isnan(o[bad_ray]).all()), f"{name} of the NaN ray is {o[bad_ray]}"
    else:
        assert bool(torch.isnan(out[0][bad_ray, 1])), out[0][bad_ray]
    assert bool(torch.isnan(ref_out[0][bad_ray]).any())  # the reference agrees it is NaN
    # Other rays: bit-identical outputs and gradients.
    others = torch.arange(case.n_rays, device=device) != bad_ray
    sample_ok = others[case.ray_indices] if layout == "packed" else others
    for o, c, name in zip(out[:3], clean_out[:3], OUT_NAMES):
        assert torch.equal(o[others], c[others]), name
    assert torch.equal(out[3][sample_ok], clean_out[3][sample_ok])
    for gr, c, m in zip(grads, clean_grads, (sample_ok, sample_ok, others), strict=True):
        assert torch.equal(gr[m], c[m])


@pytest.mark.parametrize("mode", ["sigma", "alpha"])
def test_nan_behind_opaque_sample_still_propagates(device, mode):
    """With no early termination a NaN behind an opaque sample is still reported (0 * NaN)."""
    case = _dense_case(2, 4, mode, device=device)
    case.values[1, 0] = float("inf") if mode == "sigma" else 1.0
    case.values[1, 2] = float("nan")
    out, _ = _run(W, case, None, 0.0)
    assert bool(torch.isfinite(out[0][0]).all())
    for o in out[:3]:
        assert bool(torch.isnan(o[1]).all())
