"""Integer inputs of the public ops (issue 15, class 2): out-of-range or negative packed_info,
ray, cell and camera indices, float index tensors and float/bool sizes are refused with an error
naming the argument before any kernel indexes with them; a NaN or inverted box is refused instead
of reporting hits; the library's own renderers (check=False) are unchanged. Property-based fuzz:
every call either works (finite outputs) or raises ValueError/TypeError, never crashes."""

from __future__ import annotations

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from warpnerf.ops import generate_rays, random_pixels, ray_aabb_intersect, render_packed
from warpnerf.ops import occupancy as O
from warpnerf.ops.bridge import IndexDtypeError
from warpnerf.ops.composite import packed_info_from_ray_indices
from warpnerf.ops.sampling import Samples, importance_samples, stratified_samples

BOX = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]
FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _packed(n_rays=4, per=3, device="cpu"):
    """A valid packed layout: every ray ``per`` samples (ray 1 none)."""
    counts = torch.full((n_rays,), per)
    counts[1] = 0
    ri = torch.repeat_interleave(torch.arange(n_rays), counts).to(device, torch.int32)
    n = ri.shape[0]
    g = torch.Generator().manual_seed(0)
    ts = torch.rand(n, generator=g).to(device)
    te = ts + 0.1
    sig = torch.rand(n, generator=g).to(device) * 3
    rgb = torch.rand(n, 3, generator=g).to(device)
    return ts, te, ri, sig, rgb, n_rays


# ------------------------------------------------------------------------------------------------
# render_packed


def test_render_packed_same_result_checked_or_not(device):
    ts, te, ri, sig, rgb, n_rays = _packed(device=device)
    info = packed_info_from_ray_indices(ri, n_rays)
    a = render_packed(ts, te, ri, sig, rgb, n_rays, packed_info=info)
    b = render_packed(ts, te, ri, sig, rgb, n_rays, packed_info=info, check=False)
    c = render_packed(ts, te, ri, sig, rgb, n_rays)  # packed_info computed
    for x, y, z in zip(a, b, c):
        assert torch.equal(x, y) and torch.equal(x, z)


@pytest.mark.parametrize(
    "edit, words",
    [
        (lambda i: i.__setitem__((2, 0), -1), "negative start"),
        (lambda i: i.__setitem__((3, 1), -2), "negative"),
        (lambda i: i.__setitem__((3, 0), 100), "past the end"),
        (lambda i: i.__setitem__((3, 1), 100), "past the end"),
        (lambda i: i.__setitem__((0, 1), 1), "does not match"),  # counts do not add up to n
        (lambda i: i.__setitem__((2, 0), 0), "does not match"),  # overlapping segments
        (lambda i: i.__setitem__((2, 0), 2**31 - 2), "past the end"),  # int32 wrap-around
    ],
)
def test_render_packed_refuses_bad_packed_info(edit, words):
    ts, te, ri, sig, rgb, n_rays = _packed()
    info = packed_info_from_ray_indices(ri, n_rays)
    edit(info)
    with pytest.raises(ValueError, match=words):
        render_packed(ts, te, ri, sig, rgb, n_rays, packed_info=info)


def test_render_packed_refuses_bad_ray_indices():
    ts, te, ri, sig, rgb, n_rays = _packed()
    info = packed_info_from_ray_indices(ri, n_rays)
    bad = ri.clone()
    bad[-1] = n_rays  # out of range
    with pytest.raises(ValueError, match="ray_indices"):
        render_packed(ts, te, bad, sig, rgb, n_rays)
    with pytest.raises(ValueError, match="ray_indices"):
        render_packed(ts, te, bad, sig, rgb, n_rays, packed_info=info)
    neg = ri.clone()
    neg[0] = -1
    with pytest.raises(ValueError, match="ray_indices"):
        render_packed(ts, te, neg, sig, rgb, n_rays)
    unsorted = ri.flip(0).contiguous()
    with pytest.raises(ValueError, match="sorted"):
        render_packed(ts, te, unsorted, sig, rgb, n_rays)


def test_float_index_tensors_are_refused():
    ts, te, ri, sig, rgb, n_rays = _packed()
    info = packed_info_from_ray_indices(ri, n_rays)
    for kw in ({"ray_indices": ri.float()}, {"packed_info": info.float()}):
        args = dict(ray_indices=ri, packed_info=info) | kw
        with pytest.raises(IndexDtypeError, match="int32 or int64") as e:
            render_packed(ts, te, args["ray_indices"], sig, rgb, n_rays,
                          packed_info=args["packed_info"])  # fmt: skip
        assert isinstance(e.value, TypeError) and isinstance(e.value, ValueError)
    with pytest.raises(IndexDtypeError):
        packed_info_from_ray_indices(ri.double(), n_rays)
    with pytest.raises(IndexDtypeError, match="n_rays"):
        render_packed(ts, te, ri, sig, rgb, float(n_rays))


# ------------------------------------------------------------------------------------------------
# rays, boxes, sizes


def _cams(n=2, device="cpu"):
    c2w = torch.eye(4).repeat(n, 1, 1).to(device)
    c2w[:, 2, 3] = 3.0
    k = torch.tensor([[20.0, 20.0, 8.0, 8.0]]).repeat(n, 1).to(device)
    return c2w, k


def test_generate_rays_checks_camera_indices(device):
    c2w, k = _cams(device=device)
    px = py = torch.full((3,), 4.0, device=device)
    ok = torch.tensor([0, 1, 1], device=device)
    o1, d1 = generate_rays(c2w, k, cam_idx=ok, px=px, py=py)
    o2, d2 = generate_rays(c2w, k, cam_idx=ok, px=px, py=py, check=False)
    assert torch.equal(o1, o2) and torch.equal(d1, d2)
    for bad in ([0, 2, 1], [-1, 0, 0]):
        with pytest.raises(ValueError, match="cam_idx"):
            generate_rays(c2w, k, cam_idx=torch.tensor(bad, device=device), px=px, py=py)
    with pytest.raises(IndexDtypeError, match="cam_idx"):
        generate_rays(c2w, k, cam_idx=ok.float(), px=px, py=py)


def test_sizes_must_be_ints():
    c2w, k = _cams()
    for w, h in ((8.0, 8), (True, 8), (8, -1)):
        with pytest.raises(ValueError, match="width|height"):
            generate_rays(c2w, k, w, h)
    with pytest.raises(ValueError, match="n_samples"):
        stratified_samples(torch.zeros(2), torch.ones(2), 2.0)
    with pytest.raises(ValueError, match="batch"):
        random_pixels(1, 4, 4, 3.5)
    with pytest.raises(ValueError, match="int32"):
        stratified_samples(torch.zeros(2**16), torch.ones(2**16), 2**16)  # 2^32 offsets


def test_nan_or_inverted_box_is_refused_not_hit():
    o = torch.zeros(2, 3)
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    nan_box = [float("nan")] * 3 + [1.0] * 3
    for box in (nan_box, [1.0, 1, 1, -1, -1, -1], [0, 0, 0, float("inf"), 1, 1]):
        with pytest.raises(ValueError, match="aabb"):
            ray_aabb_intersect(o, d, box)
    with pytest.raises(ValueError, match="t_min"):
        ray_aabb_intersect(o, d, BOX, t_min=float("nan"))


# ------------------------------------------------------------------------------------------------
# occupancy grid ops


def test_cell_indices_are_checked(device):
    res = 4
    jit = torch.rand(3, 3, device=device)
    for bad in ([0, 64, 1], [-1, 0, 1]):
        cells = torch.tensor(bad, device=device, dtype=torch.int32)
        with pytest.raises(ValueError, match="cells"):
            O.grid_cell_points(cells, jit, res, BOX)
        density = torch.zeros(res**3, device=device)
        with pytest.raises(ValueError, match="cells"):
            O.grid_ema_update(density, cells, torch.ones(3, device=device), 0.9)
    with pytest.raises(IndexDtypeError):
        O.grid_cell_points(torch.zeros(3, device=device), jit, res, BOX)
    good = torch.tensor([0, 63, 5], device=device, dtype=torch.int32)
    assert torch.equal(
        O.grid_cell_points(good, jit, res, BOX),
        O.grid_cell_points(good, jit, res, BOX, check=False),
    )


def _march_inputs(n=3, device="cpu"):
    o = torch.tensor([[0.1, 0.2, -3.0]], device=device).repeat(n, 1)
    d = torch.tensor([[0.0, 0.0, 1.0]], device=device).repeat(n, 1)
    bits = torch.full((8,), 255, dtype=torch.uint8, device=device)
    return o, d, bits


def test_march_rays_refuses_bad_rays_without_hanging(device):
    o, d, bits = _march_inputs(device=device)
    with pytest.raises(ValueError, match="near"):
        O.march_rays(o, d, float("nan"), 6.0, bits, 4, BOX, 0.01)
    with pytest.raises(ValueError, match="far"):
        O.march_rays(o, d, 0.0, torch.tensor([1.0, float("nan"), 2.0]), bits, 4, BOX, 0.01)
    with pytest.raises(ValueError, match="lattice steps"):  # ~2^31 steps otherwise
        O.march_rays(o, d, 0.0, 6.0, bits, 4, BOX, 1e-9)
    with pytest.raises(ValueError, match="jitter"):
        O.march_rays(o, d, 0.0, 6.0, bits, 4, BOX, 0.01, jitter=torch.full((3,), 1.5))
    kb = torch.tensor([0, -5, 0], dtype=torch.int32, device=device)
    with pytest.raises(ValueError, match="k_begin"):
        O.march_rays(o, d, 0.0, 6.0, bits, 4, BOX, 0.01, k_begin=kb)
    with pytest.raises(IndexDtypeError, match="k_begin"):
        O.march_rays(o, d, 0.0, 6.0, bits, 4, BOX, 0.01, k_begin=kb.float())
    smp, _ = O.march_rays(o, d, 0.0, 6.0, bits, 4, BOX, 0.01)  # still fine
    assert smp.t_starts.numel() > 0


def test_live_samples_checks_the_layout(device):
    o, d, bits = _march_inputs(device=device)
    smp, _ = O.march_rays(o, d, 0.0, 6.0, bits, 4, BOX, 0.05)
    sig = torch.ones(smp.t_starts.shape[0], device=device)
    keep, n_live = O.live_samples(smp, sig, 1e-3)
    keep2, n_live2 = O.live_samples(smp, sig, 1e-3, check=False)
    assert torch.equal(keep, keep2) and torch.equal(n_live, n_live2)
    info = smp.packed_info.clone()
    info[0, 1] += 5
    with pytest.raises(ValueError, match="packed_info"):
        O.live_samples(Samples(smp.t_starts, smp.t_ends, smp.ray_indices, info), sig, 1e-3)


def test_importance_samples_refuses_float_packed_info():
    near, far = torch.zeros(3), torch.ones(3)
    smp = stratified_samples(near, far, 4, packed=True)
    w = torch.ones(smp.t_starts.shape[0])
    bad = Samples(smp.t_starts, smp.t_ends, smp.ray_indices, smp.packed_info.float())
    with pytest.raises(IndexDtypeError):
        importance_samples(bad, w, 4)


# ------------------------------------------------------------------------------------------------
# property-based fuzz: works with finite outputs, or a ValueError/TypeError; never a crash

_INT = st.integers(-(2**33), 2**33)


@FUZZ
@given(
    starts=st.lists(_INT | st.integers(0, 12), min_size=4, max_size=4),
    counts=st.lists(_INT | st.integers(0, 4), min_size=4, max_size=4),
    dtype=st.sampled_from([torch.int32, torch.int64, torch.float32]),
    rays=st.lists(st.integers(-3, 6), min_size=0, max_size=12),
)
def test_fuzz_render_packed(starts, counts, dtype, rays):
    ri = torch.tensor(sorted(rays), dtype=torch.int64)
    n, n_rays = ri.shape[0], 4
    g = torch.Generator().manual_seed(len(rays))
    ts = torch.rand(n, generator=g)
    info64 = torch.tensor([starts, counts], dtype=torch.int64).T.contiguous()
    info = info64.clamp(-(2**31), 2**31 - 1).to(dtype) if dtype != torch.float32 else info64.float()
    try:
        rgb, depth, opacity = render_packed(
            ts, ts + 0.1, ri, torch.rand(n, generator=g), torch.rand(n, 3, generator=g), n_rays,
            packed_info=info,
        )  # fmt: skip
    except (ValueError, TypeError):
        return
    # accepted: the layout must have been exactly the samples', and the outputs finite
    assert torch.equal(info.long(), packed_info_from_ray_indices(ri, n_rays).long())
    assert all(torch.isfinite(t).all() for t in (rgb, depth, opacity))


@FUZZ
@given(
    cams=st.lists(st.integers(-(2**40), 2**40) | st.integers(-2, 3), min_size=1, max_size=6),
    as_float=st.booleans(),
)
def test_fuzz_generate_rays(cams, as_float):
    c2w, k = _cams(3)
    idx = torch.tensor(cams, dtype=torch.int64)
    idx = idx.double() if as_float else idx
    px = py = torch.full((len(cams),), 2.0)
    try:
        o, d = generate_rays(c2w, k, cam_idx=idx, px=px, py=py)
    except (ValueError, TypeError):
        assert as_float or min(cams) < 0 or max(cams) >= 3
        return
    assert not as_float and 0 <= min(cams) and max(cams) < 3
    assert torch.isfinite(o).all() and torch.isfinite(d).all()


@FUZZ
@given(
    cells=st.lists(st.integers(-(2**35), 2**35) | st.integers(-2, 66), min_size=0, max_size=8),
    values=st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=8,
                    max_size=8),
)  # fmt: skip
def test_fuzz_grid_ops(cells, values):
    res = 4
    idx = torch.tensor(cells, dtype=torch.int64)
    m = idx.shape[0]
    ok = all(0 <= c < res**3 for c in cells)
    try:
        pts = O.grid_cell_points(idx, torch.rand(m, 3), res, BOX)
        assert ok and torch.isfinite(pts).all()
    except ValueError:
        assert not ok
    density = torch.zeros(res**3)
    vals = torch.tensor(values[:m], dtype=torch.float32)
    try:
        out = O.grid_ema_update(density, idx, vals, 0.5)
        assert ok and not torch.isnan(out).any()
    except ValueError:
        assert not ok or torch.isnan(vals).any()
