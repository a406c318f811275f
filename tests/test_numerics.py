"""Numerical hard cases across the kernel families, and property-based (hypothesis) comparisons of
every kernel family with its float64 twin. Measured error tables: scripts/numerics_report.py;
documented behaviour per case: docs/NUMERICS.md.

Only what the per-family test files did not already check is here. Where each hard case is
tested ("here" = this module; other files under tests/):

Compositing
- sigma*delta in {0, 1e-12, 1, 1e3, 1e8, inf}, every order, float64, packed/dense, sigma/alpha:
  test_composite_hard.py::test_extreme_optical_depths; float32 tiled kernel:
  test_composite_tiled.py::test_tiled_extreme_optical_depths
- sigma*delta in {0, 1e-12, 1e-3, 1, 1e3, 1e8} on whole rays and alone among ordinary samples,
  float32 and float64, outputs and gradients: here, test_composite_optical_depths
- zero-length intervals: test_composite_hard.py::test_zero_length_intervals_contribute_nothing
- negative-length intervals, sigma < 0, alpha outside [0, 1], Inf/NaN t, inf sigma on a
  zero-length interval (the ray becomes NaN): here, test_invalid_samples_poison_their_ray
- 10^4 samples: test_composite_hard.py::test_ten_thousand_samples_float32; 2^14 samples (final
  transmittance): here, test_long_ray_final_transmittance; up to 16384: the report
- rays with 0 samples: test_composite_hard.py::test_empty_rays, ::test_all_rays_empty
- all-transparent and all-opaque rays (closed forms): here, test_transparent_and_opaque_rays
- NaN sigmas/alphas/rgbs: test_composite_hard.py::test_nan_propagates_to_its_ray_only,
  ::test_nan_behind_opaque_sample_still_propagates; Inf rgbs, NaN background: here,
  test_inf_rgb_and_nan_background_propagate
Sampling / ray-box
- near == far, near > far: test_sampling.py::test_dense_intervals_partition_near_far,
  ::test_packed_layout, ::test_packed_all_rays_miss; through compositing: here,
  test_box_rays_end_to_end; random: here, test_property_stratified_matches_twin
- missing rays, axis-parallel directions, camera inside, tangent rays, unnormalised directions:
  test_rays.py::test_ray_aabb_hand_worked, ::test_ray_aabb_matches_reference; through sampling
  and compositing against the closed form: here, test_box_rays_end_to_end; direction scaled by
  2^k divides t by 2^k exactly: here, test_property_ray_aabb_matches_twin_and_scaling
- NaN origins/directions: test_rays.py::test_ray_aabb_nan_is_a_miss_with_nan_bounds; NaN/Inf
  near/far: test_sampling.py::test_non_finite_bounds_raise
Importance sampling
- all-zero weights: test_importance.py::test_zero_weights_sample_uniformly_by_length
- one-hot weights: test_importance.py::test_single_nonzero_weight_concentrates_samples
- huge (1e30; 1e300 in float64) and tiny (1e-30) weights, overflowing sums (ValueError): here,
  test_importance_extreme_weights; random kinds: here, test_property_importance_matches_twin
- NaN/Inf/negative weights (ValueError): test_importance.py::test_bad_weights_raise
SDF / VolSDF
- beta 1 .. 1e-4, sdf +-1e6: test_volsdf.py::test_laplace_density_finite_for_extreme_sdf_and_
  small_beta, ::test_field_and_render_finite_for_small_beta
- eikonal gradient and its double backward at box corners/edges/faces, sphere centre, torus axis
  and ring: here, test_eikonal_at_kinks_analytic; neural SDF at 0 and at 1e6: here,
  test_eikonal_at_kinks_neural_sdf
Sphere tracing
- grazing rays, origin inside, origin on the surface looking out, NaN input:
  test_sphere_trace.py::test_hard_cases
- exact tangent ray (HIT at 3 - sqrt(2 eps); CAP under a small cap): here,
  test_sphere_trace_tangent_ray
- origin on the surface looking in, near > far, near == far: here,
  test_sphere_trace_origin_on_surface_inward_and_bounds
- thin shells 2e-3 and a 1e-3 plate: test_sphere_trace.py::test_thin_shell_with_and_without_
  relaxation; 1e-4 and 1e-5: here, test_sphere_trace_very_thin_shell
- iteration cap is not a hit: test_sphere_trace.py::test_iteration_cap_is_not_a_hit (and here,
  test_sphere_trace_tangent_ray)
Property-based (hypothesis, derandomized): composite forward + gradients (float64 and float32),
stratified, importance, hash encoding, ray generation, ray/box, occupancy march, sphere tracing:
here, test_property_*.
"""

from __future__ import annotations

import math
import os

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import warpnerf as W
from warpnerf import reference as R
from warpnerf.fields.neural_sdf import NeuralSDF
from warpnerf.fields.sdf_scene import SDFScene
from warpnerf.fields.sdf_volume import sdf_box, sdf_sphere, sdf_torus
from warpnerf.ops import occupancy as O
from warpnerf.ops.encoding import HashGrid, hash_encode
from warpnerf.ops.sampling import Samples, importance_samples
from warpnerf.ops.sphere_trace import sphere_trace
from warpnerf.reference import occupancy as RO
from warpnerf.reference.encoding import hash_encode as ref_hash_encode
from warpnerf.reference.sampling import importance_samples as ref_importance_samples
from warpnerf.reference.sphere_trace import sphere_trace as ref_sphere_trace
from warpnerf.sphere_tracing import CAP, HIT, INSIDE, MISS

from ._composite_cases import OUT_NAMES, TOL64, _mk, _pack, _run, _to, _upstream

F32, F64 = torch.float32, torch.float64
INF, NAN = float("inf"), float("nan")
# Deterministic property tests: same examples on every run, nothing written to disk. A deeper
# search: WARPNERF_HYPOTHESIS_EXAMPLES=500 python -m pytest tests/test_numerics.py -k property
PROPERTY = settings(
    max_examples=int(os.environ.get("WARPNERF_HYPOTHESIS_EXAMPLES", "40")),
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


def _all_finite(*xs) -> bool:
    return all(bool(torch.isfinite(x).all()) for x in xs)


def _ray_sphere(o: torch.Tensor, d: torch.Tensor, center, radius: float):
    """First intersection t of rays o + t d (d need not be unit: float32-rounded directions are
    not) with a sphere, in float64, and the discriminant scaled to a unit direction."""
    oc, d = o.double() - torch.as_tensor(center, dtype=F64), d.double()
    a, b = (d * d).sum(-1), (oc * d).sum(-1)
    disc = b**2 - a * ((oc**2).sum(-1) - radius**2)
    return (-b - torch.sqrt(disc.clamp_min(0))) / a, disc / a


def _maxabs(x: torch.Tensor) -> float:
    """max |x| (0 for an empty tensor)."""
    return float(x.abs().max()) if x.numel() else 0.0


# --------------------------------------------------------------------------------------------------
# 1. compositing

TAUS = [0.0, 1e-12, 1e-3, 1.0, 1e3, 1e8]


def _dense(rows_tau, device, dtype, seed=0):
    """Dense rays whose samples have the given optical depths sigma * delta (rows [n_rays, n_s])."""
    g = torch.Generator().manual_seed(seed)
    tau = torch.tensor(rows_tau, dtype=F64)
    n_rays, n_s = tau.shape
    deltas = torch.rand(n_rays, n_s, generator=g, dtype=F64) * 0.5 + 0.25
    t_ends = 1.0 + torch.cumsum(deltas, 1)
    case = _mk(
        "dense",
        "sigma",
        n_rays,
        t_ends - deltas,
        t_ends,
        None,
        tau / deltas,
        torch.rand(n_rays, n_s, 3, generator=g, dtype=F64),
    )
    return _to(case, device, dtype)


@pytest.mark.parametrize("dtype", [F64, F32])
def test_composite_optical_depths(device, dtype):
    """Each required sigma * delta on every sample of a ray, and alone among ordinary samples
    (tau 0.05 .. 0.4): outputs and gradients finite and equal to the float64 twin on the same
    (rounded) inputs. float32: errors relative to max(|value|, 1) measured on the CPU at 9e-8
    (outputs) and 2.8e-7 (gradients); the tolerance 3e-6 is about 10x."""
    n_s = 6
    rows = [[t] * n_s for t in TAUS]
    for t in TAUS:
        for pos in (0, 2, n_s - 1):
            row = [0.05 + 0.07 * k for k in range(n_s)]
            row[pos] = t
            rows.append(row)
    case = _dense(rows, device, dtype)
    bg = torch.rand(case.n_rays, 3, dtype=F64).to(device, dtype)
    g = _upstream(case)
    for thr in (0.0, 1e-2):
        out, grads = _run(W, case, bg, thr, g)
        g64 = [x.double() for x in g]
        ref_out, ref_grads = _run(R, _to(case, device, F64), bg.double(), thr, g64)
        assert _all_finite(*out, *grads)
        names = (*OUT_NAMES, "v_sigmas", "v_rgbs", "v_background")
        for a, e, name in zip(out + grads, ref_out + ref_grads, names):
            assert _all_finite(e), name
            if dtype == F64:
                torch.testing.assert_close(a, e, **TOL64, msg=name)
            else:
                scale = max(float(e.abs().max()), 1.0)
                err = float((a.double() - e).abs().max()) / scale
                assert err < 3e-6, (name, thr, err)
        if thr == 0.0:  # uniform rays in closed form: opacity = 1 - exp(-n tau) (to ~4 ulp)
            want = -torch.expm1(-n_s * torch.tensor(TAUS, dtype=F64))
            tol = 4 * torch.finfo(dtype).eps
            opacity = out[2][: len(TAUS)].double().cpu()
            torch.testing.assert_close(opacity, want, rtol=tol, atol=1e-20)


@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("mode", ["sigma", "alpha"])
@pytest.mark.parametrize("t_threshold", [0.0, 1e-2])
def test_transparent_and_opaque_rays(device, dtype, mode, t_threshold):
    """Closed forms. Transparent (sigma = 0 / alpha = 0): rgb = background, depth = opacity = 0,
    dL/dsigma_i = delta_i (e_i - e_bg), dL/dc_i = 0. Opaque (sigma = inf / alpha = 1 on every
    sample): the first sample alone, rgb = c_0, depth = its midpoint, opacity 1; dL/dsigma = 0,
    dL/dalpha_0 = e_0 - S_0 with S_0 = e_1 (no termination) or e_bg (terminated after sample 0),
    every other sample and the background get 0."""
    n_rays, n_s = 3, 5
    g0 = torch.Generator().manual_seed(1)
    deltas = torch.rand(n_rays, n_s, generator=g0, dtype=F64) * 0.5 + 0.25
    t_ends = torch.cumsum(deltas, 1)
    t_starts = t_ends - deltas
    rgbs = torch.rand(n_rays, n_s, 3, generator=g0, dtype=F64)
    bg = torch.rand(n_rays, 3, generator=g0, dtype=F64)
    opaque_value = 1.0 if mode == "alpha" else INF
    for kind, value in (("transparent", 0.0), ("opaque", opaque_value)):
        values = torch.full((n_rays, n_s), value, dtype=F64)
        case = _to(_mk("dense", mode, n_rays, t_starts, t_ends, None, values, rgbs), device, dtype)
        bgd = bg.to(device, dtype)
        up = _upstream(case)
        (rgb, depth, opacity, w), (v_val, v_rgbs, v_bg) = _run(W, case, bgd, t_threshold, up)
        assert _all_finite(rgb, depth, opacity, w, v_val, v_rgbs, v_bg)
        e = (case.rgbs * up[0][:, None]).sum(-1) + up[1][:, None] * 0.5 * (
            case.t_starts + case.t_ends
        )
        e = e + up[2][:, None] + up[3]
        e_bg = (up[0] * bgd).sum(-1)
        zero = torch.zeros_like
        if kind == "transparent":
            assert torch.equal(rgb, bgd) and torch.equal(depth, zero(depth))
            assert torch.equal(opacity, zero(opacity)) and torch.equal(w, zero(w))
            assert torch.equal(v_rgbs, zero(v_rgbs)) and torch.equal(v_bg, up[0])
            if mode == "sigma":
                want = (case.t_ends - case.t_starts) * (e - e_bg[:, None])
            else:
                want = e - e_bg[:, None]
            torch.testing.assert_close(v_val, want, rtol=1e-6, atol=1e-6)
        else:
            assert torch.equal(rgb, case.rgbs[:, 0]) and torch.equal(opacity, opacity.new_ones(3))
            torch.testing.assert_close(depth, 0.5 * (case.t_starts[:, 0] + case.t_ends[:, 0]))
            assert torch.equal(w[:, 0], w.new_ones(3)) and torch.equal(w[:, 1:], zero(w[:, 1:]))
            assert torch.equal(v_bg, zero(v_bg))
            assert torch.equal(v_rgbs[:, 0], up[0]) and torch.equal(
                v_rgbs[:, 1:], zero(v_rgbs[:, 1:])
            )
            assert torch.equal(v_val[:, 1:], zero(v_val[:, 1:]))
            if mode == "sigma":
                assert torch.equal(v_val[:, 0], zero(v_val[:, 0]))
            else:
                s0 = e_bg if t_threshold > 0 else e[:, 1]
                torch.testing.assert_close(v_val[:, 0], e[:, 0] - s0, rtol=1e-6, atol=1e-6)


# (name, field, value): sample 2 of ray 1 (of 3 rays x 5 samples) is made invalid.
INVALID = [
    ("negative_length", "t_ends", -0.3),  # t_end = t_start - 0.3
    ("negative_sigma", "values", -0.5),
    ("negative_alpha", "values", -0.5),
    ("alpha_above_one", "values", 1.5),
    ("inf_t_end", "t_ends", INF),
    ("neg_inf_t_start", "t_starts", -INF),
    ("nan_t_start", "t_starts", NAN),
    ("inf_sigma_zero_length", "values", INF),  # inf * 0 = NaN: propagated, not a guess
]


@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("layout", ["packed", "dense"])
@pytest.mark.parametrize("name, field, value", INVALID, ids=[c[0] for c in INVALID])
def test_invalid_samples_poison_their_ray(device, layout, dtype, name, field, value):
    """An invalid sample makes its ray's rgb, depth and opacity NaN (never a plausible finite
    result) in the kernels (sequential; float32 densities: the tiled one) and in the twin, and
    every value gradient of its ray NaN in the kernels; other rays are bit-identical to a clean
    run."""
    mode = "alpha" if "alpha" in name else "sigma"
    n_rays, n_s, bad = 3, 5, (1, 2)
    g0 = torch.Generator().manual_seed(2)
    deltas = torch.rand(n_rays, n_s, generator=g0, dtype=F64) * 0.5 + 0.25
    t_ends = torch.cumsum(deltas, 1)
    values = torch.rand(n_rays, n_s, generator=g0, dtype=F64) * (0.8 if mode == "alpha" else 2.0)
    rgbs = torch.rand(n_rays, n_s, 3, generator=g0, dtype=F64)
    case = _mk("dense", mode, n_rays, t_ends - deltas, t_ends, None, values, rgbs)
    broken = _mk("dense", mode, n_rays, *(x.clone() for x in (case.t_starts, case.t_ends)),
                 None, values.clone(), rgbs)  # fmt: skip
    target = getattr(broken, field)
    if name == "negative_length":
        target[bad] = broken.t_starts[bad] + value
    elif name == "inf_sigma_zero_length":
        broken.t_ends[bad] = broken.t_starts[bad]
        target[bad] = value
    else:
        target[bad] = value
    if layout == "packed":
        case, broken = _pack(case), _pack(broken)
    case, broken = _to(case, device, dtype), _to(broken, device, dtype)
    bg = torch.rand(n_rays, 3, dtype=F64).to(device, dtype)
    up = _upstream(case)
    for lib in (W, R):
        clean_out, clean_grads = _run(lib, case, bg, 0.0, up)
        out, grads = _run(lib, broken, bg, 0.0, up)
        for o, nm in zip(out[:3], OUT_NAMES):
            assert bool(torch.isnan(o[1]).all()), (lib.__name__, nm, o[1])
            assert torch.equal(o[[0, 2]], clean_out[OUT_NAMES.index(nm)][[0, 2]]), nm
        if lib is W:
            v_val = grads[0].reshape(n_rays, n_s)
            assert bool(torch.isnan(v_val[1]).all()), v_val[1]
            assert torch.equal(v_val[[0, 2]], clean_grads[0].reshape(n_rays, n_s)[[0, 2]])
            assert torch.equal(grads[2][[0, 2]], clean_grads[2][[0, 2]])


def test_inf_rgb_and_nan_background_propagate(device):
    """Inf colours and a NaN background are not hidden: the affected channel of that ray is
    Inf / NaN, its opacity and depth (which do not involve colours) stay exact, other rays are
    unaffected."""
    case = _dense([[0.3] * 4] * 3, device, F64)
    bg = torch.rand(3, 3, dtype=F64, device=device)
    clean, _ = _run(W, case, bg, 0.0)
    case.rgbs = case.rgbs.clone()
    case.rgbs[0, 1, 2] = INF
    bg = bg.clone()
    bg[2, 0] = NAN
    out, _ = _run(W, case, bg, 0.0)
    assert out[0][0, 2].item() == INF and bool(torch.isfinite(out[0][0, :2]).all())
    assert math.isnan(out[0][2, 0].item()) and bool(torch.isfinite(out[0][2, 1:]).all())
    assert torch.equal(out[0][1], clean[0][1])
    assert torch.equal(out[1], clean[1]) and torch.equal(out[2], clean[2])


def test_long_ray_final_transmittance(device):
    """One ray of 2^14 float32 samples, total optical depth about 12: the final transmittance
    (rgb with black samples over a white background = T_m) and the opacity against float64.
    Measured on the CPU (32-lane blocks): relative error of T_m 2.8e-6 (T_m = 6.2e-6), opacity
    7.9e-8; tolerances about 10x."""
    n = 2**14
    g = torch.Generator().manual_seed(3)
    deltas = torch.rand(n, generator=g, dtype=F64) * 2 / n + 0.5 / n
    t_ends = torch.cumsum(deltas, 0)
    sig = torch.rand(n, generator=g, dtype=F64) * 16.0
    rgbs = torch.zeros(n, 3, dtype=F64)
    idx = torch.zeros(n, dtype=torch.int64)
    case = _to(_mk("packed", "sigma", 1, t_ends - deltas, t_ends, idx, sig, rgbs), device, F32)
    bg = torch.ones(3, device=device)
    out, _ = _run(W, case, bg, 0.0)
    ref, _ = _run(R, _to(case, device, F64), bg.double(), 0.0)
    t_m, t_ref = out[0][0, 0].double(), ref[0][0, 0]
    assert 1e-7 < float(t_ref) < 1e-3
    assert abs(float(t_m / t_ref) - 1) < 3e-5, float(t_m / t_ref - 1)
    assert abs(float(out[2][0].double() - ref[2][0])) < 1e-6


# --------------------------------------------------------------------------------------------------
# 2. sampling and ray / box


@pytest.mark.parametrize("dtype", [F64, F32])
def test_box_rays_end_to_end(device, dtype):
    """ray/box -> stratified samples -> compositing of a constant-density box, against the closed
    form opacity 1 - exp(-sigma (t_far - t_near)) (t in units of |direction|, as everywhere):
    a miss, a camera inside the box, axis-parallel rays, a ray grazing along a face, a ray
    tangent to an edge, near == far and near > far (these four get no samples: rgb =
    background), and an unnormalised direction (same points, t divided by its length)."""
    box = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]
    rays = [
        ((-3.0, 2.0, 0.0), (1.0, 0.0, 0.0)),  # miss (parallel, outside the y slab)
        ((0.2, -0.3, -0.5), (0.0, 0.0, 1.0)),  # inside: t_near = 0
        ((-3.0, 0.5, 0.5), (1.0, 0.0, 0.0)),  # axis-parallel
        ((-3.0, 1.0, 0.5), (1.0, 0.0, 0.0)),  # along the face y = 1
        ((-3.0, 0.0, -1.0), (1.0, 0.0, 1.0)),  # tangent to the edge x = -1, z = 1 (t 2 .. 2)
        ((-3.0, 0.5, 0.5), (4.0, 0.0, 0.0)),  # unnormalised: t_near 0.5, t_far 1
    ]
    o = torch.tensor([r[0] for r in rays], dtype=dtype, device=device)
    d = torch.tensor([r[1] for r in rays], dtype=dtype, device=device)
    t0, t1, hit = W.ray_aabb_intersect(o, d, box)
    assert hit.tolist() == [False, True, True, True, True, True]
    assert t0.tolist() == [0.0, 0.0, 2.0, 2.0, 2.0, 0.5]
    assert t1.tolist() == [0.0, 1.5, 4.0, 4.0, 2.0, 1.0]
    # near == far and near > far rows on top: the packed layout gives them no samples
    near = torch.cat([t0, t0[2:3], t1[2:3]])
    far = torch.cat([t1, t0[2:3], t0[2:3]])
    sigma, n_s = 1.7, 16
    smp = W.stratified_samples(near, far, n_s, packed=True)
    counts = smp.packed_info[:, 1].tolist()
    assert counts == [0, n_s, n_s, n_s, 0, n_s, 0, 0]
    n = smp.t_starts.shape[0]
    sig = torch.full((n,), sigma, dtype=dtype, device=device, requires_grad=True)
    rgbs = torch.full((n, 3), 0.25, dtype=dtype, device=device)
    rgb, depth, opacity = W.render_packed(
        smp.t_starts, smp.t_ends, smp.ray_indices, sig, rgbs, 8, 1.0, packed_info=smp.packed_info
    )
    length = (far - near).clamp_min(0).double()
    want = -torch.expm1(-sigma * length)
    tol = 1e-12 if dtype == F64 else 1e-6
    torch.testing.assert_close(opacity.double(), want, rtol=0, atol=tol)
    torch.testing.assert_close(rgb[:, 0].double(), 0.25 * want + (1 - want), rtol=0, atol=tol)
    empty = torch.tensor(counts, device=device) == 0
    assert torch.equal(rgb[empty], torch.ones_like(rgb[empty]))
    assert bool((depth[empty] == 0).all()) and bool((opacity[empty] == 0).all())
    (v,) = torch.autograd.grad(opacity.sum(), sig)
    assert _all_finite(v)
    # The unnormalised ray samples the same points as the unit one (t scaled by 1/4).
    a, b = smp.packed_info[2].tolist(), smp.packed_info[5].tolist()
    p_unit = o[2] + smp.midpoints()[a[0] : a[0] + n_s, None] * d[2]
    p_long = o[5] + smp.midpoints()[b[0] : b[0] + n_s, None] * d[5]
    torch.testing.assert_close(p_long, p_unit, rtol=0, atol=4 * torch.finfo(dtype).eps)


# --------------------------------------------------------------------------------------------------
# 3. importance sampling


def _edges(s: Samples) -> torch.Tensor:
    return torch.cat([s.t_starts[:, :1], s.t_ends], -1)


@pytest.mark.parametrize("dtype", [F64, F32])
def test_importance_extreme_weights(device, dtype):
    """Huge weights (1e30; 1e300 in float64) give finite, sorted edges inside [near, far] that
    equal the twin's and fall in the weighted intervals; tiny weights (1e-30, absorbed by the
    padding) give exactly the all-zero result; a total that overflows the dtype raises."""
    n_rays, n_c, n_f = 3, 16, 24
    near = torch.full((n_rays,), 0.5, dtype=dtype, device=device)
    s = W.stratified_samples(near, near + 1.5, n_c, perturb=True, seed=1)
    huge = 1e300 if dtype == F64 else 1e30
    w = torch.zeros(n_rays, n_c, dtype=dtype, device=device)
    w[0] = huge  # uniform and huge
    w[1, 5] = huge  # one-hot and huge
    w[2, [3, 9]] = huge  # two huge peaks
    for perturb in (False, True):
        out = importance_samples(s, w, n_f, perturb=perturb, seed=4)
        e = _edges(out)
        assert _all_finite(e) and bool((e.diff(dim=1) >= 0).all())
        assert torch.equal(e[:, 0], near) and torch.equal(e[:, -1], near + 1.5)
        new = e[1][(e[1] >= s.t_starts[1, 5]) & (e[1] <= s.t_ends[1, 5])]
        assert new.numel() == n_f + 2  # every new position in the weighted interval
    ref = ref_importance_samples(s, w, n_f)
    out = importance_samples(s, w, n_f)
    tol = 0.0 if (dtype == F64 and device.type == "cpu") else 1e-5
    torch.testing.assert_close(out.t_starts, ref.t_starts, rtol=0, atol=tol)
    tiny = importance_samples(s, torch.full_like(w, 1e-30), n_f)
    zero = importance_samples(s, torch.zeros_like(w), n_f)
    assert torch.equal(tiny.t_starts, zero.t_starts) and torch.equal(tiny.t_ends, zero.t_ends)
    big = torch.full_like(w, torch.finfo(dtype).max / 4)
    with pytest.raises(ValueError, match="too large"):
        importance_samples(s, big, n_f)


# --------------------------------------------------------------------------------------------------
# 4. SDFs: gradients where the distance is not differentiable

F64D = dict(dtype=F64)
KINKS = {
    "box": (
        lambda p, c, s: sdf_box(p, c, s),
        [[0.5, 0.5, 0.5], [-0.5, 0.5, 0.0], [0.5, 0.0, 0.0], [0.0, 0.0, 0.0], [0.2, -0.1, 0.3]],
    ),
    "sphere": (lambda p, c, s: sdf_sphere(p, c, s[0]), [[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]),
    "torus": (lambda p, c, s: sdf_torus(p, c, s[0], s[1]), [[0.0, 0.3, 0.0], [0.6, 0.0, 0.0]]),
}


@pytest.mark.parametrize("shape", list(KINKS))
def test_eikonal_at_kinks_analytic(shape):
    """On a box's corner, edge and face (where the clamped outside vector is 0 with a live
    gradient; the eikonal loss's parameter gradient was NaN there before sdf_volume._norm), at
    its centre and inside, at a sphere's centre, on a torus' axis and its core ring: the distance
    gradient and the eikonal loss's double backward (to points and parameters) are finite; at
    the sphere centre the gradient is 0 and the eikonal residual exactly 1."""
    fn, pts = KINKS[shape]
    params = {"box": [1.0, 1.0, 1.0], "sphere": [0.5], "torus": [0.6, 0.25]}[shape]
    c = torch.zeros(3, **F64D, requires_grad=True)
    s = torch.tensor(params, **F64D, requires_grad=True)
    p = torch.tensor(pts, **F64D, requires_grad=True)
    d = fn(p, c, s)
    (g,) = torch.autograd.grad(d.sum(), p, create_graph=True)
    eik = (g.norm(dim=-1) - 1.0) ** 2
    grads = torch.autograd.grad(eik.sum(), (p, c, s), allow_unused=True)
    assert _all_finite(d, g, eik, *[x for x in grads if x is not None])
    if shape == "sphere":
        assert torch.equal(g[0], torch.zeros(3, **F64D)) and eik[0].item() == 1.0
        assert g[1].tolist() == [1.0, 0.0, 0.0]
    # Away from the kinks the values are unchanged: exact distances.
    if shape == "box":
        assert d.tolist() == [0.0, 0.0, 0.0, -0.5, -0.2]


def test_eikonal_at_kinks_neural_sdf():
    """The neural SDF (softplus: smooth) at the origin, on its init sphere and at |x| = 1e6:
    values, gradient and the eikonal loss's parameter gradients are finite."""
    torch.manual_seed(0)
    model = NeuralSDF(n_layers=3, width=32, skip=1, pos_freqs=4).double()
    p = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [1e6, -1e6, 3.0]], **F64D)
    f, g = model.gradient(p, create_graph=True)
    loss = ((g.norm(dim=-1) - 1.0) ** 2).sum()
    loss.backward()
    assert _all_finite(f, g, loss)
    grads = [q.grad for q in model.parameters() if q.grad is not None]  # (out.bias: unused)
    assert len(grads) == len(list(model.parameters())) - 1 and _all_finite(*grads)


# --------------------------------------------------------------------------------------------------
# 5. sphere tracing

UNIT_SPHERE = SDFScene().sphere(1.0)


@pytest.mark.parametrize("eps", [1e-4, 1e-6])
def test_sphere_trace_tangent_ray(device, eps):
    """A ray exactly tangent to the unit sphere at (1, 0, 0) (from (1, 0, 3) along -z): the
    distance along it is sqrt(1 + s^2) - 1 ~ s^2 / 2, so sphere tracing creeps towards the
    tangent point in ~sqrt(2 / eps) steps and stops where s ~ sqrt(2 eps): a HIT at
    t = 3 - sqrt(2 eps) (within 5%) with the sphere's normal at that point, agreeing with the torch
    tracer; with too small an iteration cap it is CAP, not a hit, with t short of the tangent."""
    o = torch.tensor([[1.0, 0.0, 3.0]], device=device)
    d = torch.tensor([[0.0, 0.0, -1.0]], device=device)
    tr = sphere_trace(o, d, UNIT_SPHERE, 0.0, 10.0, eps=eps, max_iters=100_000)
    ref = ref_sphere_trace(o.cpu(), d.cpu(), UNIT_SPHERE, 0.0, 10.0, eps=eps, max_iters=100_000)
    assert tr.status.tolist() == [HIT] == ref.status.tolist()
    s = 3.0 - tr.t.item()
    assert abs(s / math.sqrt(2 * eps) - 1) < 0.05, s
    assert abs(tr.t.item() - ref.t.item()) < 1e-5
    assert abs(tr.iters.item() / math.sqrt(2 / eps) - 1) < 0.1
    n_exact = torch.nn.functional.normalize(tr.points[0].double().cpu(), dim=0)
    assert (tr.normals[0].double().cpu() - n_exact).abs().max() < 2e-3
    capped = sphere_trace(o, d, UNIT_SPHERE, 0.0, 10.0, eps=eps, max_iters=30)
    assert capped.status.tolist() == [CAP] and capped.ids.tolist() == [-1]
    assert capped.t.item() < tr.t.item() and bool((capped.normals == 0).all())


def test_sphere_trace_origin_on_surface_inward_and_bounds(device):
    """Origin exactly on the surface looking inward: HIT at t = near after one evaluation (the
    distance there is 0 < eps). near > far: MISS with t = far, no evaluation. near == far off the
    surface: one evaluation, then MISS at far."""
    o = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 3.0], [0.0, 0.0, 3.0]], device=device)
    d = torch.tensor([[0.0, 0.0, -1.0]] * 3, device=device)
    near = torch.tensor([0.0, 5.0, 1.0], device=device)
    far = torch.tensor([10.0, 4.0, 1.0], device=device)
    tr = sphere_trace(o, d, UNIT_SPHERE, near, far, eps=1e-6)
    assert tr.status.tolist() == [HIT, MISS, MISS]
    assert tr.t.tolist() == [0.0, 4.0, 1.0] and tr.iters.tolist() == [1, 0, 1]
    assert tr.normals[0].tolist() == pytest.approx([0.0, 0.0, 1.0], abs=1e-3)


@pytest.mark.parametrize("thickness", [1e-4, 1e-5])
@pytest.mark.parametrize("omega", [1.0, 1.9])
def test_sphere_trace_very_thin_shell(device, thickness, omega):
    """Shells far thinner than the existing 2e-3 case (down to 1e-5, 10x eps) with and without
    over-relaxation: every clear hit lands on the outer surface (1e-4), every clear miss is a
    MISS, and a ray starting inside the shell's material is INSIDE."""
    scene = SDFScene().sphere(1.0).sphere(1.0 - thickness, op="subtraction")
    g = torch.Generator().manual_seed(5)
    o = torch.nn.functional.normalize(torch.randn(300, 3, generator=g, dtype=F64), dim=-1) * 5
    aim = (torch.rand(300, 3, generator=g, dtype=F64) - 0.5) * 3
    d = torch.nn.functional.normalize(aim - o, dim=-1)
    tr = sphere_trace(o.float().to(device), d.float().to(device), scene, 0.0, 20.0, eps=1e-6,
                      omega=omega, max_iters=5000)  # fmt: skip
    t_exact, disc = _ray_sphere(o.float(), d.float(), [0.0, 0.0, 0.0], 1.0)
    hits, misses = disc > 1e-2, disc < -1e-2
    assert int(hits.sum()) > 100 and int(misses.sum()) > 10
    st, t = tr.status.cpu(), tr.t.double().cpu()
    assert bool((st[hits] == HIT).all()) and bool((st[misses] == MISS).all())
    assert float((t[hits] - t_exact[hits]).abs().max()) < 1e-4
    inside = sphere_trace(torch.tensor([[1.0 - thickness / 2, 0.0, 0.0]], device=device),
                          torch.tensor([[1.0, 0.0, 0.0]], device=device), scene)  # fmt: skip
    assert inside.status.tolist() == [INSIDE]


# --------------------------------------------------------------------------------------------------
# 6. property-based: kernels against their twins on random valid inputs


@PROPERTY
@given(
    counts=st.lists(st.integers(0, 40), min_size=1, max_size=5),
    log_sigma=st.floats(-8.0, 3.0),
    mode=st.sampled_from(["sigma", "alpha"]),
    t_threshold=st.sampled_from([0.0, 1e-4, 0.3]),
    specials=st.lists(st.sampled_from([0.0, 1e-12, 1e3, 1e8, INF]), max_size=3),
    seed=st.integers(0, 2**16),
)
def test_property_composite_matches_twin(
    device, counts, log_sigma, mode, t_threshold, specials, seed
):
    """Packed rays of random lengths (0 included), densities around 10^log_sigma with a few
    extreme values (or opacities in [0, 1] with exact 0 / 1), some zero-length intervals, random
    upstream gradients: the float64 kernel equals the twin to 1e-9, the float32 kernel is within
    1e-4 of it (relative to the largest value), and everything is finite."""
    g = torch.Generator().manual_seed(seed)
    n_rays, n = len(counts), sum(counts)
    ray_indices = torch.repeat_interleave(torch.arange(n_rays), torch.tensor(counts))
    deltas = torch.rand(n, generator=g, dtype=F64) * 0.3
    deltas[torch.rand(n, generator=g) < 0.1] = 0.0
    t_starts = torch.rand(n, generator=g, dtype=F64) + torch.cumsum(deltas, 0) - deltas
    if mode == "sigma":
        values = torch.rand(n, generator=g, dtype=F64) * 10.0**log_sigma
        for k, v in enumerate(specials):
            if n:
                values[(seed + 7 * k) % n] = v
        values[deltas == 0] = values[deltas == 0].clamp(max=1e8)  # inf * 0 = NaN by design
    else:
        values = torch.rand(n, generator=g, dtype=F64)
        values[torch.rand(n, generator=g) < 0.1] = 1.0
        values[torch.rand(n, generator=g) < 0.1] = 0.0
    rgbs = torch.rand(n, 3, generator=g, dtype=F64)
    case = _mk("packed", mode, n_rays, t_starts, t_starts + deltas, ray_indices, values, rgbs)
    case = _to(case, device, F64)
    bg = torch.rand(n_rays, 3, generator=g, dtype=F64).to(device)
    up = _upstream(case)
    out, grads = _run(W, case, bg, t_threshold, up)
    ref_out, ref_grads = _run(R, case, bg, t_threshold, up)
    assert _all_finite(*out, *grads)
    names = (*OUT_NAMES, "v_values", "v_rgbs", "v_background")
    for a, e, name in zip(out + grads, ref_out + ref_grads, names):
        fin = torch.isfinite(e)  # the twin's alpha gradient at alpha = 1 is inf * 0 = NaN
        torch.testing.assert_close(a[fin], e[fin], rtol=1e-9, atol=1e-9, msg=name)
    case32 = _to(case, device, F32)
    up32 = [x.float() for x in up]
    out32, grads32 = _run(W, case32, bg.float(), t_threshold, up32)
    up64 = [x.double() for x in up32]  # the twin gets the same rounded inputs
    ref32, rgrads32 = _run(R, _to(case32, device, F64), bg.float().double(), t_threshold, up64)
    assert _all_finite(*out32, *grads32)
    if t_threshold > 0:
        return  # float32 rounding may move the termination point by one sample
    for a, e, name in zip(out32 + grads32, ref32 + rgrads32, names):
        fin = torch.isfinite(e)
        scale = max(_maxabs(e[fin]), 1.0)
        assert _maxabs(a.double()[fin] - e[fin]) <= 1e-4 * scale, name


@PROPERTY
@given(
    n_rays=st.integers(1, 12),
    n_samples=st.integers(1, 64),
    span=st.sampled_from([0.0, -1.0, 1e-6, 1.0, 1e3]),
    perturb=st.booleans(),
    dtype=st.sampled_from([F64, F32]),
    seed=st.integers(0, 2**16),
)
def test_property_stratified_matches_twin(device, n_rays, n_samples, span, perturb, dtype, seed):
    """Random near, far = near + span * U (near == far and near > far included): evaluation
    samples equal the twin exactly (CPU), jittered ones partition [near, max(near, far)] in
    order; packed rays with far <= near have no samples."""
    g = torch.Generator().manual_seed(seed)
    near = (torch.rand(n_rays, generator=g, dtype=F64) * 4 - 1).to(device, dtype)
    far = near + (span * torch.rand(n_rays, generator=g, dtype=F64)).to(device, dtype)
    s = W.stratified_samples(near, far, n_samples, perturb=perturb, seed=seed)
    hi = torch.maximum(near, far)
    assert torch.equal(s.t_starts[:, 0], near) and torch.equal(s.t_ends[:, -1], hi)
    assert torch.equal(s.t_ends[:, :-1], s.t_starts[:, 1:])
    assert bool((s.t_ends >= s.t_starts).all())
    if not perturb:
        r = R.stratified_samples(near, far, n_samples)
        tol = 0.0 if device.type == "cpu" else 4 * torch.finfo(dtype).eps
        torch.testing.assert_close(s.t_starts, r.t_starts, rtol=tol, atol=0.0)
        torch.testing.assert_close(s.t_ends, r.t_ends, rtol=tol, atol=0.0)
    p = W.stratified_samples(near, far, n_samples, perturb=perturb, seed=seed, packed=True)
    assert p.packed_info[:, 1].tolist() == [
        n_samples if f > n_ else 0 for n_, f in zip(near.tolist(), far.tolist())
    ]


@PROPERTY
@given(
    n_rays=st.integers(1, 6),
    n_c=st.integers(1, 24),
    n_f=st.integers(1, 32),
    kind=st.sampled_from(["random", "zero", "one_hot", "huge", "sparse"]),
    dtype=st.sampled_from([F64, F32]),
    perturb=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_property_importance_matches_twin(device, n_rays, n_c, n_f, kind, dtype, perturb, seed):
    """Importance samples on random stratified coarse rays (a miss included) with random, zero,
    one-hot, huge (1e30) or sparse weights: finite, sorted, a partition of [near, far] that keeps
    every coarse edge; in evaluation equal to the float64 twin (exact on the CPU in float64)."""
    g = torch.Generator().manual_seed(seed)
    near = (torch.rand(n_rays, generator=g, dtype=F64) + 0.1).to(device, dtype)
    far = near + (torch.rand(n_rays, generator=g, dtype=F64) * 3 + 0.1).to(device, dtype)
    far[0] = near[0]  # a miss: everything at near
    s = W.stratified_samples(near, far, n_c, perturb=True, seed=seed)
    w = torch.rand(n_rays, n_c, generator=g, dtype=F64)
    if kind == "zero":
        w.zero_()
    elif kind == "one_hot":
        w = torch.nn.functional.one_hot(torch.randint(0, n_c, (n_rays,), generator=g), n_c).double()
    elif kind == "huge":
        w = w * 1e30
    elif kind == "sparse":
        w[torch.rand(n_rays, n_c, generator=g) < 0.8] = 0.0
    w = w.to(device, dtype)
    out = importance_samples(s, w, n_f, perturb=perturb, seed=seed)
    e = _edges(out)
    assert e.shape == (n_rays, n_c + n_f + 1) and _all_finite(e)
    assert bool((e.diff(dim=1) >= 0).all())
    assert torch.equal(e[:, 0], near) and torch.equal(e[:, -1], far)
    coarse = _edges(s)
    assert torch.equal(e.gather(1, torch.searchsorted(e, coarse)), coarse)
    if not perturb:
        ref = ref_importance_samples(s, w, n_f)
        if dtype == F64:
            tol = 0.0 if device.type == "cpu" else 1e-12
        else:
            tol = 2e-4
        torch.testing.assert_close(out.t_starts, ref.t_starts, rtol=0.0, atol=tol)


@PROPERTY
@given(
    n_levels=st.integers(1, 4),
    n_features=st.integers(1, 3),
    log2_size=st.integers(4, 10),
    base_res=st.integers(1, 8),
    growth=st.integers(1, 6),
    dtype=st.sampled_from([F64, F32]),
    seed=st.integers(0, 2**16),
)
def test_property_hash_encoding_matches_twin(
    device, n_levels, n_features, log2_size, base_res, growth, dtype, seed
):
    """Random grid layouts (dense and hashed levels, heavy collisions) and points (inside the
    cube, on its faces and outside it): features and table gradients equal the float64 twin
    (1e-12 in float64, 1e-4 relative to the largest value in float32)."""
    grid = HashGrid(n_levels, n_features, log2_size, base_res, base_res * growth)
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(40, 3, generator=g, dtype=F64) * 1.4 - 0.2
    x[:4] = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.5, 1.0, 0.0], [1.0, 0.0, 0.25]])
    table = torch.randn(grid.n_rows, n_features, generator=g, dtype=F64)
    v_out = torch.randn(40, grid.out_dim, generator=g, dtype=F64)
    xt, tt = x.to(device, dtype), table.to(device, dtype).requires_grad_(True)
    out = hash_encode(xt, tt, grid)
    (g_t,) = torch.autograd.grad(out, tt, v_out.to(device, dtype))
    t64 = tt.detach().double().requires_grad_(True)
    ref = ref_hash_encode(xt.double(), t64, grid)
    (g_ref,) = torch.autograd.grad(ref, t64, v_out.to(device))
    tol = 1e-12 if dtype == F64 else 1e-4
    for a, e in ((out.detach(), ref.detach()), (g_t, g_ref)):
        assert _maxabs(a.double() - e) <= tol * max(_maxabs(e), 1.0)


@PROPERTY
@given(
    n_cams=st.integers(1, 3),
    rows=st.sampled_from([3, 4]),
    normalize=st.booleans(),
    dtype=st.sampled_from([F64, F32]),
    seed=st.integers(0, 2**16),
)
def test_property_generate_rays_matches_twin(device, n_cams, rows, normalize, dtype, seed):
    """Random rotations, translations and intrinsics, every pixel and a random pixel batch:
    origins exact, directions within a few ulps of the twin (unit length when normalised)."""
    g = torch.Generator().manual_seed(seed)
    q, r = torch.linalg.qr(torch.randn(n_cams, 3, 3, generator=g, dtype=F64))
    q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1)).unsqueeze(-2)
    c2w = torch.zeros(n_cams, 4, 4, dtype=F64)
    c2w[:, :3, :3], c2w[:, :3, 3], c2w[:, 3, 3] = q, torch.randn(n_cams, 3, generator=g) * 3, 1.0
    k = torch.cat([torch.rand(n_cams, 2, generator=g, dtype=F64) * 200 + 20,
                   torch.rand(n_cams, 2, generator=g, dtype=F64) * 8], 1)  # fmt: skip
    c2w, k = c2w[:, :rows].to(device, dtype), k.to(device, dtype)
    eps = torch.finfo(dtype).eps
    o, d = W.generate_rays(c2w, k, 8, 6, normalize=normalize)
    ro, rd = R.generate_rays(c2w, k, 8, 6, normalize=normalize)
    assert torch.equal(o, ro)
    torch.testing.assert_close(d, rd, rtol=16 * eps, atol=16 * eps)
    if normalize:
        torch.testing.assert_close(d.norm(dim=-1), torch.ones_like(d[:, 0]), rtol=0, atol=8 * eps)
    cam = torch.randint(0, n_cams, (20,), generator=g).to(device)
    px = (torch.rand(20, generator=g, dtype=F64) * 8).to(device, dtype)
    py = (torch.rand(20, generator=g, dtype=F64) * 6).to(device, dtype)
    o, d = W.generate_rays(c2w, k, cam_idx=cam, px=px, py=py, normalize=normalize)
    ro, rd = R.generate_rays(c2w, k, cam_idx=cam, px=px, py=py, normalize=normalize)
    assert torch.equal(o, ro)
    torch.testing.assert_close(d, rd, rtol=16 * eps, atol=16 * eps)


@PROPERTY
@given(
    n=st.integers(1, 40),
    p_zero=st.sampled_from([0.0, 0.3, 0.7]),
    t_min=st.sampled_from([0.0, 0.5]),
    log2_scale=st.integers(-20, 20),
    dtype=st.sampled_from([F64, F32]),
    seed=st.integers(0, 2**16),
)
def test_property_ray_aabb_matches_twin_and_scaling(
    device, n, p_zero, t_min, log2_scale, dtype, seed
):
    """Random rays with zero (and -0) direction components and origins on faces, random boxes:
    bit-identical to the twin; scaling every direction by 2^k divides t_near / t_far by 2^k
    exactly (t_min = 0), i.e. an unnormalised direction measures t in units of its length."""
    g = torch.Generator().manual_seed(seed)
    lo = torch.rand(3, generator=g, dtype=F64) * 2 - 2
    box = torch.cat([lo, lo + torch.rand(3, generator=g, dtype=F64) * 2 + 0.1]).to(dtype)
    o = torch.rand(n, 3, generator=g, dtype=F64) * 6 - 3
    o[torch.rand(n, generator=g) < 0.2, 1] = float(box[4])
    d = torch.randn(n, 3, generator=g, dtype=F64)
    zero = torch.rand(n, 3, generator=g) < p_zero
    d[zero] = 0.0
    d[zero & (torch.rand(n, 3, generator=g) < 0.5)] = -0.0
    d[(d == 0).all(-1), 0] = 1.0
    o, d = o.to(device, dtype), d.to(device, dtype)
    out = W.ray_aabb_intersect(o, d, box.tolist(), t_min)
    ref = R.ray_aabb_intersect(o, d, box.tolist(), t_min)
    for a, e in zip(out, ref):
        assert torch.equal(a, e)
    if t_min == 0.0:
        scale = 2.0**log2_scale
        t0, t1, hit = W.ray_aabb_intersect(o, d * scale, box.tolist())
        assert torch.equal(hit, out[2])
        assert torch.equal(t0 * scale, out[0]) and torch.equal(t1 * scale, out[1])


@PROPERTY
@given(
    res=st.sampled_from([2, 4, 8]),
    frac=st.floats(0.0, 1.0),
    n_steps=st.sampled_from([8, 64, 300]),
    jitter=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_property_march_matches_brute_force(device, res, frac, n_steps, jitter, seed):
    """Random occupancy grids and rays (axis-parallel, inside, missing, grazing included): the
    marcher's samples are exactly the brute-force twin's (counts, ray indices; t within 2e-6)."""
    g = torch.Generator().manual_seed(seed)
    dens = torch.rand(res**3, generator=g) * (torch.rand(res**3, generator=g) < frac)
    bits = O.grid_pack_bits(dens.to(device), 0.0)
    box = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]
    n = 24
    o = torch.randn(n, 3, generator=g) * 2.5
    d = -o + torch.randn(n, 3, generator=g) * 0.8
    d[:4] = torch.tensor([1.0, 0.0, 0.0])  # axis-parallel
    o[:4] = torch.tensor([-3.0, 0.0, 0.0]) + torch.rand(4, 3, generator=g) * torch.tensor([0, 1, 1])
    o[4:8] = torch.rand(4, 3, generator=g) * 1.6 - 0.8  # inside
    o[8:10], d[8:10] = torch.tensor([0.0, 5.0, 0.0]), torch.tensor([0.0, 1.0, 0.0])  # away
    d[10:12] = torch.tensor([1.0, 1e-4, 0.05])  # grazing the y cell planes
    o[10:12] = torch.tensor([-3.0, 0.0, 0.1])
    d = torch.nn.functional.normalize(d, dim=-1)
    o, d = o.to(device), d.to(device)
    dt = 2 * math.sqrt(3) / n_steps
    kw = {"jitter": torch.rand(n, generator=g).to(device)} if jitter else {}
    s, k = O.march_rays(o, d, 0.0, 10.0, bits, res, box, dt, **kw)
    sr, kr = RO.march_rays(o, d, 0.0, 10.0, bits, res, box, dt, **kw)
    assert torch.equal(s.packed_info, sr.packed_info) and torch.equal(s.ray_indices, sr.ray_indices)
    torch.testing.assert_close(s.t_starts, sr.t_starts, rtol=0, atol=2e-6)
    torch.testing.assert_close(s.t_ends, sr.t_ends, rtol=0, atol=2e-6)
    assert torch.equal(k, kr)


@PROPERTY
@given(
    radius=st.floats(0.05, 2.0),
    center=st.tuples(*[st.floats(-1.0, 1.0)] * 3),
    omega=st.sampled_from([1.0, 1.5, 1.9]),
    seed=st.integers(0, 2**16),
)
def test_property_sphere_trace_matches_closed_form(device, radius, center, omega, seed):
    """A random sphere and rays aimed around it: clear hits (discriminant > 1e-2 r^2) are HITs
    within 1e-4 of the first intersection, clear misses are MISSes, and the kernel's status
    equals the torch tracer's on every clear ray."""
    c = torch.tensor(center, dtype=F64)
    scene = SDFScene().sphere(radius, center=list(center))
    g = torch.Generator().manual_seed(seed)
    o = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=F64), dim=-1) * 6 + c
    aim = c + (torch.rand(64, 3, generator=g, dtype=F64) - 0.5) * 4 * radius
    d = torch.nn.functional.normalize(aim - o, dim=-1)
    o32, d32 = o.float(), d.float()
    kw = dict(eps=1e-6, omega=omega, max_iters=4000)
    tr = sphere_trace(o32.to(device), d32.to(device), scene, 0.0, 20.0, **kw)
    ref = ref_sphere_trace(o32, d32, scene, 0.0, 20.0, **kw)
    t_exact, disc = _ray_sphere(o32, d32, c, radius)
    hits, misses = disc > 1e-2 * radius**2, disc < -1e-2 * radius**2
    st_, t = tr.status.cpu(), tr.t.double().cpu()
    assert bool((st_[hits] == HIT).all()) and bool((st_[misses] == MISS).all())
    assert _maxabs(t[hits] - t_exact[hits]) < 1e-4
    clear = hits | misses
    assert torch.equal(st_[clear], ref.status[clear])
