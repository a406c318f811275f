"""Ray kernels (kernels/rays.py via warpnerf.ops.rays): pinhole ray generation and ray / box
intersection against the pure-PyTorch reference, exact hand-worked cases and hard cases."""

from __future__ import annotations

import math

import pytest
import torch

import warpnerf as W
from warpnerf import reference as R

from ._twin import EXACT, assert_matches_twin

F32, F64 = torch.float32, torch.float64
NAN = float("nan")


def _random_cameras(n_cams, width, height, rows=4, dtype=F64, device="cpu"):
    """Random rotations (QR of a Gaussian matrix, det +1), translations and intrinsics."""
    q, r = torch.linalg.qr(torch.randn(n_cams, 3, 3, dtype=F64))
    q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1)).unsqueeze(-2)
    q = torch.where(torch.linalg.det(q)[:, None, None] < 0, -q, q)
    c2w = torch.zeros(n_cams, 4, 4, dtype=F64)
    c2w[:, :3, :3] = q
    c2w[:, :3, 3] = torch.randn(n_cams, 3, dtype=F64) * 3
    c2w[:, 3, 3] = 1
    f = torch.rand(n_cams, 2, dtype=F64) * 150 + 50
    c = torch.rand(n_cams, 2, dtype=F64) * torch.tensor([width, height], dtype=F64)
    intrinsics = torch.cat([f, c], 1)
    return c2w[:, :rows].to(device, dtype), intrinsics.to(device, dtype)


RAY_NAMES = ("origins", "directions")
DIR_TOL = {"directions": {"rtol": 1e-13, "atol": 1e-14}}  # origins: exact


def _match_rays(inputs, tols=DIR_TOL, twin_dtype=None, **kw):
    """W.generate_rays against its twin R.generate_rays (tests/_twin.py), no gradients."""
    r = assert_matches_twin(
        lambda **a: W.generate_rays(**a, **kw),
        lambda **a: R.generate_rays(**a, **kw),
        inputs,
        names=RAY_NAMES,
        tol=EXACT,
        tols=tols,
        twin_dtype=twin_dtype,
    )
    return r.out["origins"], r.out["directions"]


def _random_batch(n, n_cams, width, height, device):
    cam_idx = torch.randint(0, n_cams, (n,))
    px = torch.rand(n, dtype=F64) * width
    py = torch.rand(n, dtype=F64) * height
    return cam_idx.to(device), px.to(device), py.to(device)


# --------------------------------------------------------------------------------------------------
# generate_rays


@pytest.mark.parametrize("rows", [4, 3])
@pytest.mark.parametrize("normalize", [True, False])
def test_generate_rays_grid_matches_reference(device, normalize, rows):
    width, height = 7, 5
    c2w, k = _random_cameras(3, width, height, rows, device=device)
    o, d = _match_rays(
        {"c2w": c2w, "intrinsics": k}, width=width, height=height, normalize=normalize
    )
    assert o.shape == d.shape == (3 * width * height, 3)
    if normalize:
        torch.testing.assert_close(d.norm(dim=-1), torch.ones(len(d), dtype=F64, device=device))
    else:  # the camera-space z component is exactly -1: the world direction's projection on -z_cam
        cam = torch.arange(3, device=device).repeat_interleave(width * height)
        z_cam = c2w[cam, :3, 2]
        torch.testing.assert_close(
            (d * z_cam).sum(-1), -torch.ones(len(d), dtype=F64, device=device)
        )


@pytest.mark.parametrize("normalize", [True, False])
def test_generate_rays_batch_matches_reference(device, normalize):
    width, height = 64, 48
    c2w, k = _random_cameras(4, width, height, device=device)
    cam_idx, px, py = _random_batch(500, 4, width, height, device)
    batch = {"c2w": c2w, "intrinsics": k, "cam_idx": cam_idx, "px": px, "py": py}
    o, d = _match_rays(batch, normalize=normalize)
    # int32 camera indices work the same.
    o32, d32 = W.generate_rays(c2w, k, cam_idx=cam_idx.int(), px=px, py=py, normalize=normalize)
    assert torch.equal(o32, o) and torch.equal(d32, d)


def test_grid_order_is_camera_row_column(device):
    width, height = 6, 4
    c2w, k = _random_cameras(2, width, height, device=device)
    o, d = W.generate_rays(c2w, k, width, height)
    cam, row, col = torch.meshgrid(
        torch.arange(2), torch.arange(height), torch.arange(width), indexing="ij"
    )
    ob, db = W.generate_rays(
        c2w,
        k,
        cam_idx=cam.reshape(-1).to(device),
        px=(col.reshape(-1) + 0.5).to(device, F64),
        py=(row.reshape(-1) + 0.5).to(device, F64),
    )
    assert torch.equal(o, ob) and torch.equal(d, db)


@pytest.mark.parametrize("mode", ["grid", "batch"])
def test_generate_rays_float32(device, mode):
    width, height = 32, 24
    c2w, k = _random_cameras(3, width, height, device=device, dtype=F32)
    tols = {"directions": {"rtol": 0.0, "atol": 1e-6}}  # origins: exact
    if mode == "grid":
        o, d = _match_rays({"c2w": c2w, "intrinsics": k}, tols, F64, width=width, height=height)
    else:
        cam_idx, px, py = _random_batch(300, 3, width, height, device)
        batch = {
            "c2w": c2w,
            "intrinsics": k,
            "cam_idx": cam_idx,
            "px": px.float(),
            "py": py.float(),
        }
        o, d = _match_rays(batch, tols, F64)
    assert o.dtype == d.dtype == F32


def test_identity_camera(device):
    """Centre pixel looks down -z; x to the right, y up (image rows go down)."""
    width, height = 5, 3
    c2w = torch.eye(4, dtype=F64, device=device)
    k = torch.tensor([10.0, 10.0, 2.5, 1.5], dtype=F64, device=device)
    o, d = W.generate_rays(c2w, k, width, height)
    centre = 1 * width + 2
    assert d[centre].tolist() == [0.0, 0.0, -1.0]
    assert bool((o == 0).all())
    assert d[1 * width + 4, 0] > 0 and d[1 * width + 0, 0] < 0  # right / left
    assert d[0 * width + 2, 1] > 0 and d[2 * width + 2, 1] < 0  # top row up / bottom row down
    _, d_raw = W.generate_rays(c2w, k, width, height, normalize=False)
    torch.testing.assert_close(
        d_raw[0], torch.tensor([-0.2, 0.1, -1.0], dtype=F64, device=device), rtol=0, atol=1e-16
    )
    # A translated identity-rotation camera: batch mode at (cx, cy) gives the same ray.
    c2w[:3, 3] = torch.tensor([1.0, -2.0, 3.0], dtype=F64)
    o, d = W.generate_rays(
        c2w,
        k,
        cam_idx=torch.zeros(1, dtype=torch.int64, device=device),
        px=torch.tensor([2.5], dtype=F64, device=device),
        py=torch.tensor([1.5], dtype=F64, device=device),
    )
    assert o[0].tolist() == [1.0, -2.0, 3.0] and d[0].tolist() == [0.0, 0.0, -1.0]


def _cams():
    return torch.eye(4, dtype=F64).repeat(2, 1, 1), torch.tensor([[10.0, 10, 2, 2]] * 2, dtype=F64)


GEN_BAD = {
    "c2w": lambda c, k: dict(c2w=c[:, :2]),
    "intrinsics": lambda c, k: dict(intrinsics=k[:1].repeat(3, 1)),
    "intrinsics ": lambda c, k: dict(intrinsics=k.float()),  # dtype mismatch
    "px": lambda c, k: dict(
        cam_idx=torch.zeros(3, dtype=torch.int64), px=torch.zeros(2), py=torch.zeros(3)
    ),
    "cam_idx": lambda c, k: dict(
        cam_idx=torch.tensor([0, 2]), px=torch.zeros(2), py=torch.zeros(2)
    ),
    "width": lambda c, k: dict(width=None),
}


@pytest.mark.parametrize("arg", list(GEN_BAD))
def test_generate_rays_rejects_bad_argument(arg):
    c2w, k = _cams()
    kw = dict(c2w=c2w, intrinsics=k, width=4, height=4)
    W.generate_rays(**kw)
    kw.update(GEN_BAD[arg](c2w, k))
    if "cam_idx" in kw:
        kw.pop("width"), kw.pop("height")
    with pytest.raises(ValueError, match=rf"\b{arg.strip()}\b"):
        W.generate_rays(**kw)


# --------------------------------------------------------------------------------------------------
# ray_aabb_intersect

BOX = [-1.0, -0.5, -1.5, 1.0, 1.5, 0.5]


def _random_rays(n, dtype, device):
    origins = torch.rand(n, 3, dtype=F64) * 6 - 3
    directions = torch.randn(n, 3, dtype=F64)
    zero = torch.rand(n, 3) < 0.15
    directions[zero] = 0.0
    directions[zero & (torch.rand(n, 3) < 0.5)] = -0.0
    directions[(directions == 0).all(-1), 0] = 1.0
    # Some origins exactly on a face plane (grazing when that direction component is 0).
    on_face = torch.rand(n) < 0.1
    origins[on_face, 1] = BOX[4]
    return origins.to(device, dtype), directions.to(device, dtype)


@pytest.mark.parametrize("t_min", [0.0, 0.5])
@pytest.mark.parametrize("dtype", [F64, F32])
def test_ray_aabb_matches_reference(device, dtype, t_min):
    o, d = _random_rays(3000, dtype, device)
    r = assert_matches_twin(
        lambda o, d: W.ray_aabb_intersect(o, d, BOX, t_min),
        lambda o, d: R.ray_aabb_intersect(o, d, BOX, t_min),
        {"o": o, "d": d},
        names=("t_near", "t_far", "hit"),
        tol=EXACT,
    )
    t_near, t_far, hit = r.out.values()
    n_hit = int(hit.sum())
    assert 100 < n_hit < 2900, n_hit  # plenty of both
    assert bool((t_near[hit] >= t_min).all()) and bool((t_near[hit] <= t_far[hit]).all())
    assert bool((t_near[~hit] == t_min).all()) and bool((t_far[~hit] == t_min).all())
    # Hit points lie on or inside the box.
    box = torch.tensor(BOX, dtype=dtype, device=device)
    for t in (t_near[hit], t_far[hit]):
        p = o[hit] + t[:, None] * d[hit]
        eps = 1e-5 if dtype == F32 else 1e-12
        assert bool(((p >= box[:3] - eps) & (p <= box[3:] + eps)).all())


UNIT = [0.0, 0.0, 0.0, 1.0, 1.0, 1.0]
# (origin, direction, t_min) -> (t_near, t_far, hit), worked by hand on the unit box.
HAND = [
    ((-1, 0.5, 0.5), (1, 0, 0), 0.0, (1.0, 2.0, True)),  # axis-parallel, inside the other slabs
    ((-1, -1, -1), (2, 2, 2), 0.0, (0.5, 1.0, True)),  # diagonal, unnormalised direction
    ((-1, 0.5, 0.5), (1, -0.0, 0.0), 0.0, (1.0, 2.0, True)),  # signed zeros
    ((0.5, 0.5, 0.5), (0, 0, 1), 0.0, (0.0, 0.5, True)),  # starts inside: t_near = t_min
    ((0.5, 0.5, 0.5), (0, 0, -1), 0.25, (0.25, 0.5, True)),  # inside, clipped at t_min
    ((0.5, 0.5, 0.5), (1, 0, 0), 1.0, (1.0, 1.0, False)),  # t_min past the exit: miss
    ((0, 0.5, 0.5), (1, 0, 0), 0.0, (0.0, 1.0, True)),  # starts on a face
    ((2, 0.5, 0.5), (1, 0, 0), 0.0, (0.0, 0.0, False)),  # box behind the ray
    ((2, 0.5, 0.5), (-1, 0, 0), 0.0, (1.0, 2.0, True)),  # same ray turned around
    ((-1, 2, 0.5), (1, 0, 0), 0.0, (0.0, 0.0, False)),  # parallel, outside the y slab
    ((-1, 1, 0.5), (1, 0, 0), 0.0, (1.0, 2.0, True)),  # grazing along the face y = 1
    ((-1, 0, 0), (1, 0, 0), 0.0, (1.0, 2.0, True)),  # along an edge
    ((-1, 1, 0.5), (1, -1, 0), 0.0, (1.0, 1.0, True)),  # tangent: touches the edge x = y = 0
    ((-1, 0.5, 0.5), (1, 2, 0), 0.0, (0.0, 0.0, False)),  # slab intervals disjoint: miss
    ((-1, 0.5, 0.5), (1, 2, 0), 0.5, (0.5, 0.5, False)),  # misses report t_near = t_far = t_min
]


@pytest.mark.parametrize("dtype", [F64, F32])
def test_ray_aabb_hand_worked(device, dtype):
    o = torch.tensor([h[0] for h in HAND], dtype=dtype, device=device)
    d = torch.tensor([h[1] for h in HAND], dtype=dtype, device=device)
    for i, (_, _, t_min, (near, far, hit)) in enumerate(HAND):
        t_near, t_far, h = W.ray_aabb_intersect(o[i : i + 1], d[i : i + 1], UNIT, t_min)
        assert (t_near.item(), t_far.item(), bool(h)) == (near, far, hit), HAND[i]
        r_near, r_far, r_hit = R.ray_aabb_intersect(o[i : i + 1], d[i : i + 1], UNIT, t_min)
        assert (r_near.item(), r_far.item(), bool(r_hit)) == (near, far, hit), HAND[i]
    # All the t_min = 0 cases at once (one launch) give the same answers.
    idx = [i for i, h in enumerate(HAND) if h[2] == 0.0]
    t_near, t_far, hit = W.ray_aabb_intersect(o[idx], d[idx], UNIT)
    assert t_near.tolist() == [HAND[i][3][0] for i in idx]
    assert t_far.tolist() == [HAND[i][3][1] for i in idx]
    assert hit.tolist() == [HAND[i][3][2] for i in idx]


def test_ray_aabb_box_with_offset_hand_worked(device):
    box = [1.0, 2.0, 3.0, 3.0, 6.0, 4.0]
    o = torch.tensor([[0.0, 0.0, 0.0]], dtype=F64, device=device)
    d = torch.tensor([[1.0, 2.0, 1.0]], dtype=F64, device=device)
    # x in [1, 3], y in [1, 3], z in [3, 4]  ->  [3, 3]: touches the edge x = 3, z = 3.
    t_near, t_far, hit = W.ray_aabb_intersect(o, d, box)
    assert (t_near.item(), t_far.item(), bool(hit)) == (3.0, 3.0, True)
    d = torch.tensor([[2.0, 4.0, 1.0]], dtype=F64, device=device)
    # x in [0.5, 1.5], y in [0.5, 1.5], z in [3, 4] -> disjoint: miss.
    t_near, t_far, hit = W.ray_aabb_intersect(o, d, box)
    assert (t_near.item(), t_far.item(), bool(hit)) == (0.0, 0.0, False)
    d = torch.tensor([[1.0, 2.0, 1.4]], dtype=F64, device=device)
    # x in [1, 3], y in [1, 3], z in [3/1.4, 4/1.4] = [2.142.., 2.857..] -> [2.142.., 2.857..]
    t_near, t_far, hit = W.ray_aabb_intersect(o, d, box)
    assert bool(hit)
    assert t_near.item() == 3.0 / 1.4 and t_far.item() == 4.0 / 1.4


@pytest.mark.parametrize("component", [0, 1, 2])
@pytest.mark.parametrize("field", ["origin", "direction"])
def test_ray_aabb_nan_is_a_miss_with_nan_bounds(device, field, component):
    """A NaN anywhere must not yield a plausible interval: hit False, t_near and t_far NaN. The
    ray would otherwise hit the box through [0.75, 1.25]; its neighbours are unaffected."""
    o = torch.tensor([[-0.5, -0.25, -0.75]] * 3, dtype=F64, device=device)
    d = torch.ones(3, 3, dtype=F64, device=device)
    (o if field == "origin" else d)[1, component] = NAN
    t_near, t_far, hit = W.ray_aabb_intersect(o, d, UNIT)
    assert hit.tolist() == [True, False, True]
    assert t_near[0].item() == t_near[2].item() == 0.75 and t_far[0].item() == 1.25
    assert math.isnan(t_near[1].item()) and math.isnan(t_far[1].item()), (
        f"NaN in {field}[{component}] gave t_near={t_near[1].item()}, t_far={t_far[1].item()}"
    )


@pytest.mark.parametrize("component", [0, 1, 2])
def test_ray_aabb_nan_axis_parallel(device, component):
    """NaN in an axis-parallel ray (the zero-direction branch)."""
    o = torch.tensor([[-1.0, 0.5, 0.5]], dtype=F64, device=device)
    d = torch.tensor([[1.0, 0.0, 0.0]], dtype=F64, device=device)
    o[0, component] = NAN
    t_near, t_far, hit = W.ray_aabb_intersect(o, d, UNIT)
    assert not bool(hit)
    assert math.isnan(t_near.item()) and math.isnan(t_far.item())


def test_ray_aabb_huge_direction_is_exact(device):
    o = torch.tensor([[-1.0, 0.5, 0.5]], dtype=F64, device=device)
    d = torch.tensor([[2.0**1000, 0.0, 0.0]], dtype=F64, device=device)
    t_near, t_far, hit = W.ray_aabb_intersect(o, d, UNIT)
    assert bool(hit) and t_near.item() == 2.0**-1000 and t_far.item() == 2.0**-999


AABB_BAD = {
    "origins": lambda o, d: dict(origins=o[:, :2]),
    "directions": lambda o, d: dict(directions=d.float()),
    "directions ": lambda o, d: dict(directions=d[:1]),
    "aabb": lambda o, d: dict(aabb=[0.0, 0.0, 0.0, 1.0, 1.0]),
    "aabb ": lambda o, d: dict(aabb=[1.0, 0.0, 0.0, 0.0, 1.0, 1.0]),  # min > max
}


@pytest.mark.parametrize("arg", list(AABB_BAD))
def test_ray_aabb_rejects_bad_argument(arg):
    o, d = torch.zeros(2, 3, dtype=F64), torch.ones(2, 3, dtype=F64)
    kw = dict(origins=o, directions=d, aabb=UNIT)
    W.ray_aabb_intersect(**kw)
    kw.update(AABB_BAD[arg](o, d))
    with pytest.raises(ValueError, match=rf"\b{arg.strip()}\b"):
        W.ray_aabb_intersect(**kw)
