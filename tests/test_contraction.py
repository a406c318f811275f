"""Unbounded scenes: the contraction and its inverse, contracted marching against its brute-force
twin (hard rays included), the grid's update in contracted space, the field, the run settings
(automatic on inward-facing captures) and a short contracted training that resumes exactly."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from warpnerf.cli import main
from warpnerf.errors import UserError
from warpnerf.fields.hash_nerf import HashNeRFField
from warpnerf.occupancy import OccupancyGrid
from warpnerf.ops import occupancy as O
from warpnerf.ops.encoding import HashGrid
from warpnerf.reference import occupancy as R
from warpnerf.train.nerf import NeRFConfig, resolve_data

from .test_capture import _colmap_capture, _forward_cameras, _llff_capture, _object_cameras

A = 1.5  # inner half-size
DT = 2 * A * math.sqrt(3) / 256
CONE = 1 / 64


def test_contraction_maps_space_into_the_cube_and_back():
    g = torch.Generator().manual_seed(0)
    dirs = torch.randn(2000, 3, dtype=torch.float64, generator=g)
    p = dirs * torch.logspace(-3, 8, 2000, dtype=torch.float64)[:, None]
    c = O.contract_points(p, A)
    m = c.abs().amax(-1)
    assert bool((m < 2 * A).all())
    inside = p.abs().amax(-1) <= A
    assert torch.equal(c[inside], p[inside])  # the inner cube stays as it is
    # continuous at the inner cube's surface, monotonic along a ray from the centre
    radial = O.contract_points(dirs[:1] * torch.logspace(-2, 6, 500, dtype=torch.float64)[:, None],
                               A).abs().amax(-1)  # fmt: skip
    assert bool((radial[1:] > radial[:-1]).all())
    edge = dirs / dirs.abs().amax(-1, keepdim=True) * A
    torch.testing.assert_close(O.contract_points(edge * (1 + 1e-9), A), edge, rtol=1e-8, atol=0)
    back = O.uncontract_points(c, A)
    ok = p.abs().amax(-1) < 1e3 * A  # beyond, the inverse's clamp takes over (by design)
    torch.testing.assert_close(back[ok], p[ok], rtol=1e-9, atol=1e-12)
    # the cube's surface and beyond stay finite (the outermost cells stand for infinity)
    far = O.uncontract_points(torch.tensor([[2 * A, 0.0, 0.0], [9.0, 9.0, 9.0]]), A)
    assert bool(torch.isfinite(far).all()) and float(far[0, 0]) >= 1e3 * A


def _rays(n, seed=0):
    """Rays from cameras inside the inner cube in all directions, plus axis-parallel ones, rays
    along cell planes of the contracted grid and rays starting far outside."""
    g = torch.Generator().manual_seed(seed)
    o = (torch.rand(n, 3, generator=g) * 2 - 1) * A
    d = torch.randn(n, 3, generator=g)
    d[:6] = torch.tensor([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
    o[6:10] = torch.tensor([0.0, 0.0, 0.0])  # on cell planes (res 8: planes at multiples of A/2)
    d[6:10] = torch.tensor([1.0, 0.0, 0.0])
    o[10:14] = torch.tensor([30.0, -40.0, 5.0])  # far outside, looking back or away
    d[10:12] = -o[10:12]
    d = d / d.norm(dim=-1, keepdim=True)
    return o, d


def _compare(got, k_got, ref_lattice, bits, near, jit=None):
    """The kernel's samples equal the float64 brute force, except for intervals whose
    contracted midpoint lies within 1e-4 cells of a cell face (float32 rounding may put those
    on either side); such flips must be rare."""
    s64, e64, valid, cell, face = ref_lattice
    occ = O.unpack_bits(bits.cpu())[cell.cpu()]
    want = valid.cpu() & occ
    n_rays = s64.shape[0]
    mine = torch.zeros_like(want)
    ri = got.ray_indices.long().cpu()
    # each sample's lattice index, from its start: s(t) - s(near) - jitter, rounded
    j = torch.zeros(n_rays, dtype=torch.float64) if jit is None else jit.double().cpu()
    s0 = O.lattice_s(torch.full((n_rays,), float(near), dtype=torch.float64), DT, CONE)
    k = O.lattice_s(got.t_starts.double().cpu(), DT, CONE) - s0[ri] - j[ri]
    assert k.numel() == 0 or float((k - k.round()).abs().max()) < 0.05
    mine[ri, k.round().long()] = True
    differ = mine ^ want
    assert bool((face.cpu()[differ] < 1e-4).all()), "a sample differs away from a cell face"
    assert int(differ.sum()) <= max(2, int(want.sum()) // 1000)
    assert bool((k_got == -1).all())
    # starts/ends are the lattice's (float32 of the float64 values)
    torch.testing.assert_close(
        got.t_starts.double().cpu(), s64.cpu()[ri, k.round().long()], rtol=2e-6, atol=1e-6
    )


@pytest.mark.parametrize("frac", [0.0, 0.3, 1.0])
def test_march_contracted_equals_brute_force(device, frac):
    res = 8
    g = torch.Generator().manual_seed(1)
    dens = torch.rand(res**3, generator=g) * (torch.rand(res**3, generator=g) < frac)
    bits = O.grid_pack_bits(dens.to(device), 0.0)
    o, d = _rays(120)
    jit = torch.rand(120, generator=g)
    for kw in ({}, {"jitter": jit}):
        kwd = {k: v.to(device) for k, v in kw.items()}
        got, k = O.march_rays_contracted(
            o.to(device), d.to(device), 0.05, 500.0, bits, res, A, DT, CONE, **kwd
        )
        lat = R.contracted_lattice(o.double(), d.double(), 0.05, 500.0, res, A, DT, CONE,
                                   kw.get("jitter"))  # fmt: skip
        _compare(got, k.cpu(), lat, bits, 0.05, kw.get("jitter"))
        ref, _ = R.march_rays_contracted(o, d, 0.05, 500.0, bits.cpu(), res, A, DT, CONE, **kw)
        if frac == 0.0:
            assert got.t_starts.numel() == 0 and ref.t_starts.numel() == 0
    if frac == 1.0:  # every ray gets every lattice interval up to far
        assert bool((got.packed_info[:, 1] > 0).all())


def test_march_contracted_steps_grow_and_rounds_resume(device):
    res = 8
    bits = O.grid_pack_bits(torch.ones(res**3, device=device), 0.0)
    o = torch.zeros(1, 3, device=device)
    d = torch.tensor([[0.0, 0.6, 0.8]], device=device)
    s, _ = O.march_rays_contracted(o, d, 0.0, 1e6, bits, res, A, DT, CONE, max_samples=10**6)
    ln = (s.t_ends - s.t_starts).double().cpu()
    mid = (0.5 * (s.t_starts + s.t_ends)).double().cpu()
    near_part = s.t_ends.cpu() <= DT / CONE
    torch.testing.assert_close(ln[near_part], torch.full_like(ln[near_part], DT), rtol=1e-4,
                               atol=1e-6)  # fmt: skip
    beyond = s.t_starts.cpu() > 2 * DT / CONE
    rel = ln[beyond][:-1] / mid[beyond][:-1]  # (the last one is cut at far)
    torch.testing.assert_close(rel, torch.full_like(rel, CONE), rtol=0.01, atol=0)
    # a million units in a few thousand steps: 1/cone + log(far cone / dt) / cone
    expect = 1 / CONE + math.log(1e6 * CONE / DT) / CONE
    assert abs(s.t_starts.numel() - expect) <= 2
    assert float(s.t_ends[-1]) == pytest.approx(1e6, rel=1e-6)
    # in rounds of 7 samples: the same samples
    k, parts = None, []
    o2, d2 = _rays(30)
    full, _ = O.march_rays_contracted(o2.to(device), d2.to(device), 0.1, 50.0, bits, res, A, DT,
                                      CONE)  # fmt: skip
    per_ray = [[] for _ in range(30)]
    for _ in range(400):
        part, k = O.march_rays_contracted(o2.to(device), d2.to(device), 0.1, 50.0, bits, res, A,
                                          DT, CONE, k_begin=k, max_samples=7)  # fmt: skip
        assert bool((part.packed_info[:, 1] <= 7).all())
        for r, t in zip(part.ray_indices.tolist(), part.t_starts.tolist()):
            per_ray[r].append(t)
        parts.append(part)
        if bool((k < 0).all()):
            break
    assert bool((k < 0).all())
    flat = torch.tensor([t for p in per_ray for t in p], device=device)
    torch.testing.assert_close(flat, full.t_starts, rtol=0, atol=0)


def test_march_contracted_hard_inputs(device):
    res = 8
    bits = O.grid_pack_bits(torch.ones(res**3, device=device), 0.0)
    o = torch.zeros(3, 3, device=device)
    d = torch.tensor([[1.0, 0.0, 0.0]] * 3, device=device)
    # far <= near, zero-length: no samples
    s, k = O.march_rays_contracted(o, d, torch.tensor([2.0, 5.0, 3.0], device=device),
                                   torch.tensor([1.0, 5.0, 3.0 + 1e-7], device=device), bits,
                                   res, A, DT, CONE)  # fmt: skip
    assert s.packed_info[:2, 1].tolist() == [0, 0] and bool((k == -1).all())
    assert int(s.packed_info[2, 1]) <= 1
    bad = [
        (o * float("nan"), d, 0.0, "finite"),
        (o, d * 0, 0.0, "non-zero"),
        (o, d * float("inf"), 0.0, "finite"),
        (o, d, -1.0, "near must be >= 0"),
    ]
    for oo, dd, near, msg in bad:
        with pytest.raises(ValueError, match=msg):
            O.march_rays_contracted(oo, dd, near, 10.0, bits, res, A, DT, CONE)
    with pytest.raises(ValueError, match="jitter"):
        O.march_rays_contracted(o, d, 0.0, 10.0, bits, res, A, DT, CONE,
                                jitter=torch.full((3,), 1.0, device=device))  # fmt: skip
    with pytest.raises(ValueError, match="lattice steps"):  # no cone: 1e30 / dt steps
        O.march_rays_contracted(o, d, 0.0, 1e30, bits, res, A, DT, 0.0)
    for name, kw in (("a", {"a": 0.0}), ("dt", {"dt": float("inf")}), ("cone", {"cone": -1.0})):
        args = {"a": A, "dt": DT, "cone": CONE, **kw}
        with pytest.raises(ValueError, match=name):
            O.march_rays_contracted(o, d, 0.0, 10.0, bits, res, **args)


def test_contracted_grid_update_sees_world_points(device):
    """The grid's cells tile contracted space; the field is asked about world points: a density
    that is non-zero only beyond 20 inner half-sizes marks only the outer shell's cells."""
    res = 16
    grid = OccupancyGrid([-2 * A] * 3 + [2 * A] * 3, res, dt=DT, contract=A, cone=CONE,
                         warmup=1).to(device)  # fmt: skip
    seen = []

    def density(x):
        seen.append(x)
        return (x.abs().amax(-1) > 20 * A).float() * 100

    grid.update(density, torch.Generator(device=device).manual_seed(0))
    x = torch.cat(seen)
    assert float(x.abs().amax()) > 100 * A  # world points, far beyond the contracted cube
    occ = O.unpack_bits(grid.bits).cpu()
    c = torch.arange(res**3)
    ijk = torch.stack([c // res**2, (c // res) % res, c % res], -1)
    centre = (ijk + 0.5) * (4 * A / res) - 2 * A  # contracted cell centres
    m = centre.abs().amax(-1) / A
    assert bool(occ.any()) and bool((m[occ] > 2 - 1 / 20 - 4 / res).all())
    with pytest.raises(ValueError, match="contracted"):
        OccupancyGrid([-1.0] * 3 + [1.0] * 3, res, dt=DT, contract=A)


def test_contracted_field_has_density_everywhere(device):
    torch.manual_seed(0)
    f = HashNeRFField([-2 * A] * 3 + [2 * A] * 3, HashGrid(4, 10, 4, 64), 16,
                      contract=A).to(device)  # fmt: skip
    x = torch.tensor([[0.0, 0, 0], [1e3, 0, 0], [-1e9, 3.0, 2e8], [0, A * 1.01, 0]],
                     device=device)  # fmt: skip
    sigma, _ = f.density(x)
    assert bool(torch.isfinite(sigma).all() & (sigma > 0).all())  # nothing is "outside"
    bounded = HashNeRFField([-A] * 3 + [A] * 3, HashGrid(4, 10, 4, 64), 16).to(device)
    assert float(bounded.density(x)[0][1].detach()) == 0.0
    with pytest.raises(ValueError, match="contracted"):
        HashNeRFField([-A] * 3 + [A] * 3, HashGrid(4, 10, 4, 64), 16, contract=A)


def test_contraction_is_chosen_from_the_camera_layout(tmp_path):
    """auto: on for an inward-facing COLMAP capture with the hash field and a grid (the inner
    cube holds the cameras, far is far away); off for forward-facing (NDC) captures, for other
    data and for the MLP field; --contract on is refused where it cannot work."""
    _colmap_capture(tmp_path / "obj", _object_cameras(8))
    cfg = resolve_data(NeRFConfig(data=str(tmp_path / "obj"), field="hash"))
    assert cfg.contract == "on" and cfg.march_cone == 1 / 256
    assert cfg.aabb == cfg.scene["inner"] and cfg.far >= 1000 * cfg.aabb
    assert cfg.aabb_box() == [-2 * cfg.aabb] * 3 + [2 * cfg.aabb] * 3
    info = resolve_data(NeRFConfig(data=str(tmp_path / "obj"), field="hash", contract="off"))
    assert info.contract == "off" and info.aabb == info.scene["aabb"]
    assert resolve_data(NeRFConfig(data=str(tmp_path / "obj"), field="mlp")).contract == "off"
    _llff_capture(tmp_path / "ff", _forward_cameras(9), 20.0, [10.0, 40.0])
    assert resolve_data(NeRFConfig(data=str(tmp_path / "ff"), field="hash")).contract == "off"
    with pytest.raises(UserError, match="NDC"):
        resolve_data(NeRFConfig(data=str(tmp_path / "ff"), field="hash", contract="on"))
    with pytest.raises(UserError, match="contract"):
        resolve_data(NeRFConfig(data="builtin", field="mlp", contract="on"))
    with pytest.raises(UserError, match="march_cone|march-cone"):
        resolve_data(NeRFConfig(data="builtin", field="hash", march_cone=0.01))
    assert resolve_data(NeRFConfig(data="builtin", field="hash")).contract == "off"


def test_contracted_training_on_a_capture(tmp_path, capsys):
    """A few steps on an inward-facing capture (random backgrounds, contracted grid); eval and
    render work on it; a run from before contraction loads bounded. (Exact resume of a
    contracted run: tests/test_nerf.py::test_resume_continues_exactly.)"""
    pts = np.random.default_rng(0).uniform(-1, 1, (50, 3)) + np.array([1.0, -2.0, 0.5])
    _colmap_capture(tmp_path / "obj", _object_cameras(8), points=pts)
    args = ["train", "nerf", "--data", str(tmp_path / "obj"), "--field", "hash",
            "--batch", "24", "--val-every", "3", "--val-images", "1", "--hash-levels", "4",
            "--hash-log2-size", "10", "--grid-res", "8", "--grid-every", "2",
            "--grid-warmup", "2", "--max-samples", "256", "--quiet", "--iters", "6",
            "--out", str(tmp_path / "a")]  # fmt: skip
    assert main(args) == 0
    cfg = json.loads((tmp_path / "a" / "config.json").read_text())
    assert cfg["contract"] == "on" and "inner" in cfg["scene"]
    ckpt = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=True)["fields"]
    assert float(ckpt["grid"]["aabb"][3]) == pytest.approx(2 * cfg["aabb"])
    capsys.readouterr()
    assert main(["eval", str(tmp_path / "a"), "--max-images", "1"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert math.isfinite(res["psnr"])
    assert main(["render", str(tmp_path / "a"), "--frames", "2", "--size", "12x8"]) == 0
    capsys.readouterr()
    # a run from before contraction (no "contract" in its config) loads bounded
    import shutil

    from warpnerf.train.nerf import load_run

    shutil.copytree(tmp_path / "a", tmp_path / "old", ignore=shutil.ignore_patterns("*.lock"))
    old = dict(cfg)
    del old["contract"], old["march_cone"]  # (neither existed then)
    old["scene"] = {k: v for k, v in cfg["scene"].items() if k != "inner"}
    (tmp_path / "old" / "config.json").write_text(json.dumps(old))
    assert load_run(tmp_path / "old")[0].contract == "off"


def test_depth_maps_of_contracted_runs_show_the_scene():
    """A contracted run's far plane lies a thousand scene sizes away: its depth maps are scaled by
    the visible surfaces' 99th percentile instead (a bounded run keeps the far plane), so they are
    not black; pixels that see nothing stay 0; a frame without any surface gives None (the
    caller falls back to far); large frames are subsampled over all their rows."""
    from types import SimpleNamespace

    from warpnerf.train.nerf import depth_scale
    from warpnerf.train.nerf_eval import depth_image

    depth = torch.linspace(1.0, 4.0, 64).reshape(8, 8)
    opacity = torch.ones(8, 8)
    opacity[0, :] = 0.0  # a row that hits nothing
    unbounded = SimpleNamespace(contract="on", far=1500.0)
    scale = depth_scale(unbounded, depth, opacity)
    assert 3.5 < scale <= 4.0
    img = depth_image(depth, opacity, scale).numpy()
    assert img.shape == (8, 8, 3) and img.dtype == np.uint8
    assert img[0].max() == 0 and img[1:].min() > 50 and img.max() == 255
    bounded = SimpleNamespace(contract="off", far=6.0)
    assert depth_scale(bounded, depth, opacity) == 6.0
    assert depth_scale(unbounded, depth, torch.zeros(8, 8)) is None
    nan = depth.clone()
    nan[3, 3] = float("nan")
    assert math.isfinite(depth_scale(unbounded, nan, opacity))
    big = torch.ones(1080, 1920)  # 2 million pixels: the top half near, the bottom half far
    big[540:] = 10.0
    assert depth_scale(unbounded, big, torch.ones_like(big)) == pytest.approx(10.0)
