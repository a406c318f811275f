"""Analytic SDF scenes and sphere tracing (kernels/sphere_trace.py via warpnerf.ops): scene
distances against the PyTorch twin, hits against closed-form ray/sphere and ray/box
intersections (1e-4), normals, statuses on the hard cases (misses, grazing and tangent rays,
origins inside or on the surface, thin shells with and without over-relaxation, the iteration
cap, non-finite input), the kernel against the torch tracer, and scene validation."""

from __future__ import annotations

import json
import math

import pytest
import torch

from warpnerf.errors import UserError
from warpnerf.fields.sdf_scene import SDFScene, many_primitives_scene, torus_scene
from warpnerf.ops.sphere_trace import scene_sdf, sphere_trace
from warpnerf.reference.sphere_trace import scene_sdf as ref_scene_sdf
from warpnerf.reference.sphere_trace import sphere_trace as ref_sphere_trace
from warpnerf.sphere_tracing import CAP, HIT, INSIDE, INVALID, MISS

F32, F64 = torch.float32, torch.float64


def _unit(v):
    return torch.nn.functional.normalize(v, dim=-1)


def _rays_at(target, n, dist=4.0, spread=0.6, seed=0):
    """n rays from a sphere of radius dist around target, aimed near it."""
    g = torch.Generator().manual_seed(seed)
    o = _unit(torch.randn(n, 3, generator=g, dtype=F64)) * dist + target
    aim = target + (torch.rand(n, 3, generator=g, dtype=F64) - 0.5) * 2 * spread
    return o, _unit(aim - o)


def test_scene_sdf_matches_twin(device):
    scene = many_primitives_scene()
    assert len(scene) > 20
    p = (torch.rand(5000, 3, dtype=F64) - 0.5) * 4
    d, ids = scene_sdf(p.float().to(device), scene)
    d_ref, ids_ref = ref_scene_sdf(p.float().double(), scene)
    assert (d.double().cpu() - d_ref).abs().max() < 2e-5
    assert (ids.cpu() == ids_ref).float().mean() > 0.999  # ties may round differently


def test_sphere_hits_match_closed_form(device):
    c, r = torch.tensor([0.3, -0.2, 0.1], dtype=F64), 0.8
    scene = SDFScene().sphere(r, center=c.tolist())
    o, d = _rays_at(c, 2000)
    tr = sphere_trace(o.float().to(device), d.float().to(device), scene, 0.0, 10.0, eps=1e-6)
    b = ((o - c) * d).sum(-1)
    disc = b**2 - ((o - c) ** 2).sum(-1) + r * r
    hits = disc > 1e-3  # clear hits; the margin avoids grazing rays (tested separately)
    t_exact = -b - torch.sqrt(disc.clamp_min(0))
    st, t = tr.status.cpu(), tr.t.double().cpu()
    assert (st[hits] == HIT).all() and (st[disc < -1e-3] == MISS).all()
    assert (t[hits] - t_exact[hits]).abs().max() < 1e-4
    n_exact = _unit(o + t_exact.unsqueeze(-1) * d - c)
    assert (tr.normals.double().cpu()[hits] - n_exact[hits]).abs().max() < 2e-3
    assert (tr.ids.cpu()[hits] == 0).all() and (tr.ids.cpu()[~hits & (st != HIT)] == -1).all()


def test_box_hits_axis_parallel_and_oblique(device):
    half = torch.tensor([0.5, 0.3, 0.7], dtype=F64)
    scene = SDFScene().box((1.0, 0.6, 1.4))
    # axis-parallel rays (zero direction components) from each face, and oblique ones
    o = torch.tensor(
        [[3, 0.1, 0.2], [-3, 0.1, 0.2], [0.1, 3, -0.2], [0.1, -3, 0.2], [0.2, 0.1, 3], [0, 0, -3]],
        dtype=F64,
    )
    d = -_unit(torch.sign(o) * (o.abs() == o.abs().amax(-1, keepdim=True)))
    o2, d2 = _rays_at(torch.zeros(3, dtype=F64), 500, spread=0.25)
    o, d = torch.cat([o, o2]), torch.cat([d, d2])
    tr = sphere_trace(o.float().to(device), d.float().to(device), scene, 0.0, 10.0, eps=1e-6)
    # slab method in float64
    inv = 1.0 / d
    t0, t1 = (-half - o) * inv, (half - o) * inv
    tn = torch.minimum(t0, t1).amax(-1)
    tf = torch.maximum(t0, t1).amin(-1)
    hits = (tf > tn + 1e-2) & (tn > 0)
    assert hits[:6].all() and hits.sum() > 300
    assert (tr.status.cpu()[hits] == HIT).all()
    assert (tr.t.double().cpu()[hits] - tn[hits]).abs().max() < 1e-4


def test_hard_cases(device):
    scene = SDFScene().sphere(1.0)
    rows = {
        "miss_away": ([0, 0, 3], [0, 0, 1]),
        "grazing_out": ([1.0 + 1e-3, 0, 3], [0, 0, -1]),
        "grazing_in": ([1.0 - 1e-3, 0, 3], [0, 0, -1]),
        "inside": ([0.2, 0, 0], [1, 0, 0]),
        "on_surface": ([0, 1.0, 0], [0, 1, 0]),
        "nan": ([float("nan"), 0, 0], [1, 0, 0]),
    }
    o = torch.tensor([v[0] for v in rows.values()], dtype=F32, device=device)
    d = _unit(torch.tensor([v[1] for v in rows.values()], dtype=F32, device=device))
    tr = sphere_trace(o, d, scene, 0.0, 10.0, eps=1e-5, max_iters=10_000)
    st = dict(zip(rows, tr.status.tolist()))
    assert st["miss_away"] == MISS and st["grazing_out"] == MISS
    assert st["grazing_in"] == HIT
    # a hit is declared at sdf < eps, i.e. up to eps / |n . d| before the surface along the ray:
    # 2.2e-4 here (|n . d| = 0.045), the grazing-angle error of sphere tracing
    z = math.sqrt(1 - (1 - 1e-3) ** 2)
    err = (3 - z) - tr.t[2].item()
    assert 0 <= err <= 1.1 * 1e-5 / z
    assert st["inside"] == INSIDE and tr.t[3].item() == 0.0
    assert st["on_surface"] == HIT and tr.iters[4].item() == 1 and tr.t[4].item() == 0.0
    assert st["nan"] == INVALID and math.isnan(tr.t[5].item())
    hits = tr.status == HIT
    assert torch.allclose(tr.normals[hits].norm(dim=-1), torch.ones(int(hits.sum()), device=device))


def test_iteration_cap_is_not_a_hit(device):
    scene = SDFScene().sphere(0.5)
    o = torch.tensor([[0.0, 0.0, 5.0], [0.5 + 2e-5, 0.0, 5.0]], device=device)
    d = torch.tensor([[0.0, 0.0, -1.0]] * 2, device=device)
    tr = sphere_trace(o, d, scene, 0.0, 10.0, eps=1e-6, max_iters=1)  # head-on needs 2
    assert tr.status.tolist() == [CAP, CAP] and (tr.ids == -1).all()
    assert (tr.normals == 0).all()
    tr = sphere_trace(o, d, scene, 0.0, 10.0, eps=1e-6, max_iters=100_000)
    assert tr.status.tolist() == [HIT, MISS]  # the tangent-ish ray needs many steps to pass


@pytest.mark.parametrize("omega", [1.0, 1.6, 1.9])
def test_thin_shell_with_and_without_relaxation(device, omega):
    """A 2e-3 thick shell (sphere minus a slightly smaller sphere) and a thin plate: relaxed
    steps overshoot, the fallback must bring every ray back to the outer surface."""
    scene = SDFScene().sphere(1.0).sphere(0.998, op="subtraction")
    o, d = _rays_at(torch.zeros(3, dtype=F64), 400, dist=5.0, spread=0.5)
    tr = sphere_trace(o.float().to(device), d.float().to(device), scene, 0.0, 20.0, eps=1e-6,
                      omega=omega, max_iters=2000)  # fmt: skip
    b = (o * d).sum(-1)
    disc = b**2 - (o**2).sum(-1) + 1.0
    t_exact = -b - torch.sqrt(disc.clamp_min(0))
    hits = disc > 1e-2
    assert (tr.status.cpu()[hits] == HIT).all()
    assert (tr.t.double().cpu()[hits] - t_exact[hits]).abs().max() < 1e-4
    plate = SDFScene().box((2.0, 1e-3, 2.0))
    o = torch.tensor([[0.1, 3.0, 0.2], [0.3, 3.0, -0.4]], device=device)
    d = _unit(torch.tensor([[0.0, -1.0, 0.05], [0.05, -1.0, 0.0]], device=device))
    tr = sphere_trace(o, d, plate, 0.0, 10.0, eps=1e-6, omega=omega)
    assert (tr.status == HIT).all() and (tr.points[:, 1] - 5e-4).abs().max() < 1e-4


@pytest.mark.parametrize("omega", [1.0, 1.6])
def test_surface_just_before_far_is_found_when_relaxed(device, omega):
    """A relaxed step may jump past far; only t_prev + d_prev is certified empty, so the march
    returns there and finds a surface between it and far (review finding)."""
    scene = SDFScene().sphere(1.0)
    o = torch.tensor([[0.0, 0.0, 5.0]], device=device)
    d = torch.tensor([[0.0, 0.0, -1.0]], device=device)
    kw = dict(eps=1e-6, omega=omega)
    for tr in (
        sphere_trace(o, d, scene, 0.0, 4.5, **kw),
        ref_sphere_trace(o.cpu(), d.cpu(), scene, 0.0, 4.5, **kw),
    ):
        assert tr.status.tolist() == [HIT] and abs(tr.t.item() - 4.0) < 1e-5
    far_miss = sphere_trace(o, d, scene, 0.0, 3.9, eps=1e-6, omega=omega)
    assert far_miss.status.tolist() == [MISS] and far_miss.t.item() == pytest.approx(3.9)


def test_rotation_convention_matches_closed_form(device):
    """Rotations are local-to-world R = Rz Ry Rx: a torus rotated 90 degrees about x has its
    ring in the world xy plane, a capsule rotated (90, 90, 0) lies along world x."""
    torus = SDFScene().torus(1.0, 0.1, rotation_deg=(90, 0, 0))
    p = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], device=device)
    dist = scene_sdf(p, torus)[0].cpu()
    assert torch.allclose(dist, torch.tensor([-0.1, -0.1, 2**0.5 - 0.1]), atol=1e-6)
    cap = SDFScene().capsule(2.0, 0.1, rotation_deg=(90, 90, 0))
    q = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], device=device)
    assert torch.allclose(scene_sdf(q, cap)[0].cpu(), torch.tensor([-0.1, 0.9, 0.9]), atol=1e-6)


def test_directions_must_be_unit_length(device):
    scene = SDFScene().sphere(1.0)
    o = torch.tensor([[0.0, 0.0, 5.0]], device=device)
    with pytest.raises(ValueError, match="unit length"):
        sphere_trace(o, torch.tensor([[0.0, 0.0, -3.0]], device=device), scene)


@pytest.mark.parametrize("omega", [1.0, 1.6])
def test_kernel_matches_torch_tracer(device, omega):
    scene = many_primitives_scene()
    o, d = _rays_at(torch.tensor([0.0, 0.0, -0.2], dtype=F64), 3000, dist=5.0, spread=1.8)
    kw = dict(eps=1e-4, max_iters=300, omega=omega)
    tr = sphere_trace(o.float().to(device), d.float().to(device), scene, 0.0, 12.0, **kw)
    ref = ref_sphere_trace(o.float(), d.float(), scene, 0.0, 12.0, **kw)
    st, st_ref = tr.status.cpu(), ref.status
    assert (st == st_ref).float().mean() > 0.995  # float rounding may flip a grazing ray
    both = (st == HIT) & (st_ref == HIT)
    assert both.sum() > 1000
    assert (tr.t.cpu()[both] - ref.t[both]).abs().max() < 1e-3
    assert ((tr.normals.cpu()[both] * ref.normals[both]).sum(-1) > 0.99).float().mean() > 0.99
    assert (tr.ids.cpu()[both] == ref.ids[both]).float().mean() > 0.99


def test_scene_json_round_trip_and_validation(tmp_path):
    scene = torus_scene()
    path = tmp_path / "s.json"
    path.write_text(json.dumps(scene.to_dict()))
    assert SDFScene.load(path).to_dict() == scene.to_dict()
    bad = [
        {"primitives": []},
        {"primitives": [{"kind": "cone", "params": [1, 0, 0, 0]}]},
        {"primitives": [{"kind": "sphere", "params": [-1, 0, 0, 0]}]},
        {"primitives": [{"kind": "sphere", "params": [1, 0, 0, 0], "op": "xor"}]},
        {"primitives": [{"kind": "sphere", "params": [1, 0, 0]}]},
        {"primitives": [{"kind": "sphere", "params": [1, 0, 0, 0], "center": [0, "a", 0]}]},
        {"primitives": [{"kind": "sphere", "params": [1, 0, 0, 0], "colour": [1, 1, 1]}]},
        {"primitives": [{"kind": "sphere", "params": [1, 0, 0, 0], "op": "smooth_union"}]},
        {"primitives": [{"kind": "sphere", "params": 1}]},
        {"primitives": [{"kind": "sphere", "params": [1, 0, 0, 0], "center": None}]},
        {"primitives": [{"kind": {}, "params": [1, 0, 0, 0]}]},
        {"primitives": [{"kind": "sphere", "params": [1, 0, 0, 0], "op": [[1]]}]},
        {"primitives": [{"kind": "sphere", "params": [1, 0, 0, 0], "color": [1, 1]}]},
        {"primitives": [{"kind": "sphere", "params": [1e300, 0, 0, 0]}]},
        {"primitives": [{"kind": "sphere", "params": [True, 0, 0, 0]}]},
        [1, 2],
    ]
    for d in bad:
        with pytest.raises(UserError):
            SDFScene.from_dict(d)
    with pytest.raises(UserError, match="no such"):
        SDFScene.load(tmp_path / "missing.json")


def test_marching_cubes_of_analytic_sphere_within_one_percent(device, tmp_path):
    from warpnerf.mesh import extract_mesh, read_ply, sample_surface, write_ply

    scene = SDFScene().sphere(0.7, center=(0.1, -0.05, 0.0))
    v, f = extract_mesh(scene.sdf, [-1] * 3, [1] * 3, 64, 0.0, device=str(device))
    r = ((v - [0.1, -0.05, 0.0]) ** 2).sum(1) ** 0.5
    assert len(f) > 1000 and abs(r - 0.7).max() < 0.007  # within 1 % of the radius
    write_ply(tmp_path / "m.ply", v, f)
    v2, f2 = read_ply(tmp_path / "m.ply")
    assert (v2 == v).all() and (f2 == f).all()
    s = sample_surface(v, f, 2000)
    assert abs(((s - [0.1, -0.05, 0.0]) ** 2).sum(1) ** 0.5 - 0.7).max() < 0.01
