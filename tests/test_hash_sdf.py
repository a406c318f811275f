"""The hash-grid SDF field (warpnerf/fields/hash_sdf.py): its initial sphere, the tetrahedral
finite-difference gradient against analytic gradients, the coarse-to-fine schedule, the
occupancy grid's conservative cell density, hard cases (tiny beta, far points) and the whole
surface workflow on the built-in scene (train, eval, render, mesh)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from warpnerf.data.materials_truth import MATERIALS_NAMES
from warpnerf.fields.hash_sdf import HashSDFField
from warpnerf.fields.sdf_volume import laplace_cdf, sdf_box
from warpnerf.mesh import read_ply, vertex_colors, write_ply
from warpnerf.ops.encoding import HashGrid

BOX = [-1.5, -1.5, -1.5, 1.5, 1.5, 1.5]


def field(**kw) -> HashSDFField:
    torch.manual_seed(0)
    grid = HashGrid(n_levels=6, log2_size=10, base_res=4, max_res=64)
    return HashSDFField(BOX, grid, hidden=16, **kw)


def inside(n=500, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = (torch.rand(n, 3, generator=g) * 2 - 1) * 1.4
    return x[x.norm(dim=-1) > 0.3]


def test_starts_as_the_sphere_sdf():
    f = field(radius=0.5)
    x = inside()
    assert torch.allclose(f.sdf(x), x.norm(dim=-1) - 0.75, atol=1e-3)  # 0.5 box units = 0.75


def test_the_sdf_is_bounded_by_the_scene_box():
    """Outside the scene box the SDF is at least the distance to the box (no surface there),
    whatever the network holds; inside it the zero set is the network's own."""
    f = field(radius=0.5)
    with torch.no_grad():  # a field that is "inside" everywhere: a huge negative residual
        f.sdf_mlp[-1].bias[0] = -5.0
    g = torch.Generator().manual_seed(1)
    out = torch.randn(400, 3, generator=g)
    out = out / out.abs().amax(-1, keepdim=True) * (1.5 + 3 * torch.rand(400, 1, generator=g))
    dist = (out.abs() - 1.5).clamp_min(0).norm(dim=-1)  # the distance to the box
    assert (f.sdf(out) >= dist - 1e-5).all() and (f.sdf(out) > 0).all()
    x = inside()  # inside: the bound is the (negative) depth from the walls, never above the
    # network's value unless the network is deeper than that, as here
    assert torch.allclose(f.sdf(x), -(1.5 - x.abs().amax(-1)), atol=1e-5)
    plain = field(radius=0.5)
    assert torch.allclose(plain.sdf(x), x.norm(dim=-1) - 0.75, atol=1e-3)  # (unchanged)


def test_tetrahedral_gradient_matches_analytic_gradients(monkeypatch):
    """The central difference is exact on linear functions and O(h^2) on smooth ones."""
    f = field()
    x = inside(200).double()
    a = torch.tensor([0.3, -1.2, 0.7], dtype=torch.float64)

    def linear(p):
        return p.double() @ a

    monkeypatch.setattr(f, "sdf", linear)
    g = f.gradient(x)
    assert torch.allclose(g.double(), a.expand_as(g), atol=1e-5)

    def smooth(p):
        p = p.double()
        return torch.sin(p[:, 0]) * p[:, 1] + 0.5 * p[:, 2] ** 2

    monkeypatch.setattr(f, "sdf", smooth)
    xr = x.clone().requires_grad_(True)
    (want,) = torch.autograd.grad(smooth(xr).sum(), xr)
    err = (f.gradient(x).double() - want).abs().max().item()
    assert err < 0.5 * f.fd_step**2  # second order (|f'''| <= 1 here: error <= h^2 / 6)
    assert err > 0  # (a real finite difference, not the analytic gradient)


def test_coarse_to_fine_opens_levels_and_shrinks_the_step():
    f = field(level_every=10, levels_start=2)
    res = f.resolutions
    f.set_step(0)
    assert f.open_levels == 2 and f.fd_step == pytest.approx(3.0 / res[1])
    x = inside(100)
    with torch.no_grad():
        f.sdf_mlp[0].weight[:, 3:] = 1.0  # (the hash inputs start at zero weight)
        before = f.sdf(x)
        first_closed = f.grid_spec.levels[2][1]
        f.encoding.table[first_closed:] += 1.0  # rows of closed levels do not reach the SDF
        assert torch.equal(f.sdf(x), before)
    f.set_step(25)
    assert f.open_levels == 4 and f.fd_step == pytest.approx(3.0 / res[3])
    assert not torch.equal(f.sdf(x), before)
    f.set_step(10**6)
    assert f.open_levels == 6 and f.level_mask.sum() == f.encoding.out_dim


def test_without_coarse_to_fine_the_all_ones_mask_is_skipped_bit_for_bit():
    """level_every = 0 (the default): every level is open from the start and the SDF skips the
    mask's multiply; values and parameter gradients are those of the masked form exactly."""
    f = field()
    assert f.level_every == 0 and bool((f.level_mask == 1).all())
    x = inside(64)
    with torch.no_grad():
        f.sdf_mlp[0].weight[:, 3:] = 0.1  # (the hash inputs start at zero weight)

    def masked(p):  # the masked form, as with coarse to fine
        lo, hi = f.aabb[:3], f.aabb[3:]
        u = ((p - lo) / (hi - lo)).clamp(0.0, 1.0)
        c = 2.0 * u - 1.0
        h = f.sdf_mlp(torch.cat([c, f.encoding(u) * f.level_mask], -1))
        d = (c.norm(dim=-1) - f.radius + h[:, 0]) * f.half
        return torch.maximum(d, sdf_box(p, (lo + hi) * 0.5, hi - lo))

    got, want = f.sdf(x), masked(x)
    assert torch.equal(got, want)
    g1 = torch.autograd.grad(got.sum(), f.encoding.table)[0]
    g2 = torch.autograd.grad(want.sum(), f.encoding.table)[0]
    assert torch.equal(g1, g2)


def test_grid_density_bounds_the_density_in_the_cell():
    f = field(beta=0.05)
    x = inside(300)
    r = 0.1
    g = torch.Generator().manual_seed(1)
    off = torch.nn.functional.normalize(torch.randn(300, 3, generator=g), dim=-1)[: len(x)]
    off = off * torch.rand(len(x), 1, generator=g) * r
    sig_near, _ = f.density(x + off)
    assert (sig_near <= f.grid_density(x, r) * (1 + 1e-5) + 1e-6).all()
    # a cell whose nearest point is on the surface: the surface density, 0.5 / beta
    s = torch.tensor([[0.75 + r, 0.0, 0.0]])  # d = r: the cell reaches the surface
    assert f.grid_density(s, r).item() == pytest.approx(0.5 / 0.05, rel=1e-2)


@pytest.mark.parametrize("density", ["laplace", "logistic"])
@pytest.mark.parametrize("beta", [1e-4, 1e-2, 1.0])
def test_hard_cases_stay_finite(beta, density):
    """Tiny beta (the floor), points far outside the box and on its faces: finite densities,
    colours, eikonal term and parameter gradients, for both SDF-to-density conversions."""
    f = field(beta=beta, beta_min=min(beta, 1e-4), density=density)
    x = torch.cat([inside(50), torch.tensor([[100.0, 0, 0], [-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]])])
    d = torch.nn.functional.normalize(torch.randn(len(x), 3), dim=-1)
    sigma, rgb = f(x, d)
    loss = sigma.mean() * 1e-4 + rgb.mean() + f.aux_losses()["eikonal"] + f.eikonal(x)
    loss.backward()
    assert torch.isfinite(sigma).all() and torch.isfinite(rgb).all()
    for p in f.parameters():
        assert p.grad is None or torch.isfinite(p.grad).all()
    assert f.aux_losses() == {}  # taken once
    assert torch.isclose(sigma.max(), torch.tensor(1.0 / f.beta.item()), rtol=1e-3) or beta == 1.0
    if density == "laplace":
        want = laplace_cdf(-f.sdf(x), f.beta) / f.beta
    else:
        want = 1.0 / (f.beta * (1.0 + torch.exp(f.sdf(x).double() / f.beta.double())))
    assert torch.allclose(sigma.double(), want.double(), rtol=1e-5, atol=1e-30)


def test_logistic_density_is_neus_along_the_normal():
    """NeuS's opaque density rho = -(d/dt Phi_s(d(t))) / Phi_s(d(t)) on a head-on ray through a
    plane d(t) = t0 - t (cos theta = -1) is the logistic density s Phi_s(-d), s = 1 / beta: the
    closed form against autograd of the definition in float64, and the laplace / logistic pair
    integrates to the same total opacity (both CDFs: the surface is crossed once)."""
    from warpnerf.fields.hash_sdf import logistic_density, sdf_density

    beta = torch.tensor(0.03, dtype=torch.float64)
    t = torch.linspace(0.0, 2.0, 20001, dtype=torch.float64, requires_grad=True)
    d = 1.0 - t
    phi = torch.sigmoid(d / beta)
    (dphi,) = torch.autograd.grad(phi.sum(), t)
    rho = -dphi / phi.detach()
    assert torch.allclose(logistic_density(d.detach(), beta), rho, rtol=1e-9, atol=1e-12)
    dt = 2.0 / 20000
    for kind in ("laplace", "logistic"):
        sig = sdf_density(kind, d.detach(), beta)
        tau = (0.5 * (sig[1:] + sig[:-1]) * dt).sum()  # optical depth behind the surface
        assert float(tau) > 0.9 * 1.0 / float(beta)  # inside: sigma -> 1 / beta (opaque)
        # the density is half its maximum exactly at the surface
        mid = sdf_density(kind, torch.zeros(1, dtype=torch.float64), beta)
        assert float(mid) == pytest.approx(0.5 / float(beta), rel=1e-12)


def test_reflected_direction_colour_input():
    """color_direction="reflect": the head sees SH(w_r) with w_r = d - 2 (d . n) n (unit, the
    mirror law: equal angles to the normal, in the plane of d and n) and n . v; gradients reach
    the SDF network; hard cases stay finite."""
    from warpnerf.fields.hash_sdf import reflect

    g = torch.Generator().manual_seed(1)
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    n = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    r = reflect(d, n)
    assert torch.allclose(r.norm(dim=-1), torch.ones(64, dtype=torch.float64))
    assert torch.allclose((r * n).sum(-1), -(d * n).sum(-1))  # angle of reflection
    assert torch.allclose(torch.linalg.det(torch.stack([d, n, r], 1)), torch.zeros(64,
                          dtype=torch.float64), atol=1e-12)  # coplanar  # fmt: skip
    head_on = reflect(-n, n)
    assert torch.allclose(head_on, n)  # looking straight at a mirror: back along the normal
    f = field(color_direction="reflect")
    seen = {}
    f.color_mlp[0].register_forward_hook(lambda m, a, o: seen.update(x=a[0]))
    x = inside(40)
    dirs = torch.nn.functional.normalize(torch.randn(len(x), 3, generator=g), dim=-1)
    sigma, rgb = f(x, dirs)
    nrm = torch.nn.functional.normalize(f.gradient(x), dim=-1)
    want = f.sh(reflect(dirs, nrm))
    k = 3 + 15
    assert torch.allclose(seen["x"][:, k : k + f.sh.out_dim], want, atol=1e-5)
    assert torch.allclose(seen["x"][:, -1], -(dirs * nrm).sum(-1), atol=1e-5)
    (rgb.sum()).backward()
    first = f.sdf_mlp[0].weight.grad
    assert first is not None and torch.isfinite(first).all() and first.abs().max() > 0
    far = torch.tensor([[100.0, 0.0, 0.0], [1.5, 1.5, 1.5]])
    s2, c2 = f(far, torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]))
    assert torch.isfinite(s2).all() and torch.isfinite(c2).all()
    with pytest.raises(ValueError, match="color_direction"):
        field(color_direction="sideways")
    with pytest.raises(ValueError, match="view_dependence"):
        field(color_direction="reflect", view_dependence=False)


def test_annealed_beta_follows_its_schedule_and_is_saved():
    """--beta-final: beta goes geometrically from beta to beta_final over anneal_steps, then
    stays; it is not a parameter; the value is in the state dict (a checkpoint renders with it)."""
    f = field(beta=0.1, beta_min=1e-4, beta_final=0.001, anneal_steps=100)
    assert f.beta_param is None
    assert f.beta.item() == pytest.approx(0.1, rel=1e-6)
    f.set_step(50)
    assert f.beta.item() == pytest.approx(0.01, rel=1e-5)  # sqrt(0.1 * 0.001)
    f.set_step(100)
    assert f.beta.item() == pytest.approx(0.001, rel=1e-5)
    f.set_step(10**6)
    assert f.beta.item() == pytest.approx(0.001, rel=1e-5)
    g = field(beta=0.1, beta_min=1e-4, beta_final=0.001, anneal_steps=100)
    g.load_state_dict(f.state_dict())
    assert g.beta.item() == pytest.approx(0.001, rel=1e-5)
    with pytest.raises(ValueError, match="beta_final"):
        field(beta=0.1, beta_final=0.5)
    with pytest.raises(ValueError, match="density"):
        field(density="gaussian")


def test_surface_workflow_on_the_builtin_scene(tmp_path):
    """train volsdf --field hash_sdf, eval, render (rgb, depth, geometry), mesh: the commands
    run end to end on a tiny run (quality is measured on the GPU, docs/design/surfaces.md)."""
    from warpnerf.cli.parser import main

    run = tmp_path / "r"
    common = ["--hash-levels", "3", "--hash-log2-size", "8", "--hash-max-res", "16"]
    assert main(["train", "volsdf", "--data", "builtin", "--field", "hash_sdf", "--out", str(run),
                 "--iters", "4", "--batch", "64", "--grid-res", "8", "--builtin-size", "16",
                 "--val-images", "1", "--c2f-every", "2", "--quiet", "--sdf-density", "logistic",
                 "--beta-final", "0.02", "--beta-anneal-steps", "2", *common]) == 0  # fmt: skip
    assert main(["eval", str(run), "--max-images", "1", "--out", str(tmp_path / "e")]) == 0
    assert main(["render", str(run), "--frames", "2", "--size", "16x16"]) == 0
    assert (run / "render_spiral" / "geometry_001.png").is_file()
    ply = tmp_path / "m.ply"
    assert main(["mesh", str(run), "--out", str(ply), "--resolution", "24", "--colors"]) == 0
    v, f, rgb = read_ply(ply, colors=True)
    assert len(f) > 0 and rgb.shape == (len(v), 3) and rgb.dtype == np.uint8
    # the baked colour is the field's colour seen along the inward normal
    from warpnerf.train.nerf import load_run

    cfg, model, _ = load_run(run)
    assert cfg.sdf_density == "logistic" and model.field.density_kind == "logistic"
    assert model.field.beta.item() == pytest.approx(0.02, rel=1e-5)  # annealed, then saved
    fn = model.field.sdf
    want = vertex_colors(model.field, fn, v[:50], "cpu")
    assert np.abs(want.astype(int) - rgb[:50]).max() <= 1
    assert main(["mesh", "--sdf", "torus", "--out", str(tmp_path / "t.ply"), "--colors"]) == 2
    bad = ["train", "volsdf", "--data", "builtin", "--field", "hash_sdf", "--out",
           str(tmp_path / "bad"), "--iters", "1", "--quiet"]  # fmt: skip
    assert main([*bad, "--beta-final", "0.5"]) == 2  # above --beta
    assert main([*bad, "--sdf-density", "gaussian"]) == 2
    assert main([*bad[:5], "volsdf", *bad[6:], "--sdf-density", "logistic"]) == 2  # hash_sdf only


def test_ply_with_colors_round_trips(tmp_path):
    g = np.random.default_rng(0)
    v = g.normal(size=(7, 3)).astype(np.float32)
    f = g.integers(0, 7, (5, 3)).astype(np.int32)
    c = g.integers(0, 256, (7, 3)).astype(np.uint8)
    write_ply(tmp_path / "c.ply", v, f, colors=c)
    v2, f2, c2 = read_ply(tmp_path / "c.ply", colors=True)
    assert np.array_equal(v, v2) and np.array_equal(f, f2) and np.array_equal(c, c2)
    write_ply(tmp_path / "n.ply", v, f)
    assert read_ply(tmp_path / "n.ply", colors=True)[2] is None
    assert all(np.array_equal(a, b) for a, b in zip(read_ply(tmp_path / "n.ply"), (v, f)))
    with pytest.raises(ValueError, match="colors must be uint8"):
        write_ply(tmp_path / "x.ply", v, f, colors=c[:3])


@pytest.mark.slow
def test_eval_geometry_against_a_reference(tmp_path, capsys):
    """`eval RUN --geometry REF`: a reference sampled from the run's own surface gives a Chamfer
    distance near zero, a shifted one the shift; --clean; the materials reference and its depth
    error (a point cloud has none); the refusals."""
    import json

    from warpnerf.cli.parser import main
    from warpnerf.mesh import extract_mesh, sample_surface
    from warpnerf.train.nerf import load_run
    from warpnerf.train.nerf_eval import evaluate_geometry, materials_reference

    run = tmp_path / "r"
    common = ["--hash-levels", "3", "--hash-log2-size", "8", "--hash-max-res", "16"]
    assert main(["train", "volsdf", "--data", "builtin", "--field", "hash_sdf", "--out", str(run),
                 "--iters", "2", "--batch", "64", "--grid-res", "8", "--builtin-size", "8",
                 "--val-images", "0", "--quiet", *common]) == 0  # fmt: skip
    cfg, model, _ = load_run(run)
    a = cfg.aabb
    v, f = extract_mesh(model.field.sdf, [-a] * 3, [a] * 3, 64, 0.0)
    own = sample_surface(v, f, 20000, seed=5).astype(np.float32)
    np.savez(tmp_path / "own.npz", points=own)
    np.savez(tmp_path / "shifted.npz", points=own + np.float32([0.0, 0.0, 0.05]))
    capsys.readouterr()
    assert main(["eval", str(run), "--geometry", str(tmp_path / "own.npz"), "--clean",
                 "--mesh-resolution", "64", "--geometry-points", "20000"]) == 0  # fmt: skip
    same = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert same["chamfer"] < 0.01 and same["accuracy"] < 0.01 and same["completeness"] < 0.01
    assert same["depth_error_mean"] is None and "point-cloud" in same["depth_note"]
    cleaned = same["cleaned"]  # one surface: nothing to remove
    assert cleaned["components_removed"] == 0 and cleaned["chamfer"] == same["chamfer"]
    far = evaluate_geometry(run, tmp_path / "shifted.npz", 64, 20000)
    assert far["chamfer"] > 2 * same["chamfer"] and far["chamfer"] < 0.05
    ref = materials_reference(1000)
    assert ref.shape == (1000, 3) and np.isclose(ref[:, 2].min(), -0.32 + 0.32, atol=0.01)
    capsys.readouterr()
    assert main(["eval", str(run), "--geometry", "materials", "--geometry-points", "500",
                 "--geometry-views", "0", "--mesh-resolution", "32"]) == 0  # fmt: skip
    mat = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert mat["depth_views"] == 4 and mat["depth_pixels"] > 0  # (its sphere vs materials')
    assert 0 < mat["depth_error_mean"] < 3.0 and 0 < mat["depth_error_median"] < 3.0
    by_shape = mat["depth_by_shape"]  # (by the shape each true ray hits, pixels add up)
    assert set(by_shape) <= set(MATERIALS_NAMES) and by_shape
    assert sum(v["pixels"] for v in by_shape.values()) == mat["depth_pixels"]
    # the figures of the mesh as delivered (culled by the training cameras, cleaned) and of the
    # raw level set with every face counted (the main figures leave out what lies under the disk)
    raw, dl = mat["raw_every_face"], mat["delivered"]
    assert dl["culled_by_views"] is True and dl["clean"] == 0.01
    assert set(dl["disk_top_by_radius"]) == {"0-0.4", "0.4-0.8", "0.8-1.2", "1.2-1.45", "1.45-1.6"}
    # and first by the training rays' weights (issue 49), or a note saying why not
    assert dl["culled_by_weights"] is ("weight_grid" in dl) is ("weights_note" not in dl)
    assert dl["mesh_faces"] <= raw["mesh_faces"] and raw["surface_points"] >= mat["surface_points"]
    assert all(raw[k] is not None and raw[k] >= 0 for k in ("accuracy", "chamfer"))
    assert "raw_every_face" not in same and same["delivered"]["culled_by_views"] is True
    assert main(["eval", str(run), "--geometry", "materials", "--clean", "1"]) == 2
    assert main(["eval", str(run), "--clean"]) == 2  # only with --geometry
    assert main(["eval", str(run), "--geometry", str(tmp_path / "nope.npz")]) == 2
    assert main(["eval", str(run), "--geometry", "materials", "--mesh-resolution", "4"]) == 2


def test_annealed_beta_below_the_march_step_warns(tmp_path, capsys):
    """--beta-final below a given marching step trains, with a warning naming the fix."""
    from warpnerf.cli.parser import main

    assert main(["train", "volsdf", "--data", "builtin", "--field", "hash_sdf", "--out",
                 str(tmp_path / "r"), "--iters", "1", "--batch", "32", "--grid-res", "8",
                 "--builtin-size", "8", "--hash-levels", "2", "--hash-log2-size", "8",
                 "--hash-max-res", "16", "--val-images", "0", "--quiet", "--beta-final", "0.001",
                 "--beta-anneal-steps", "1", "--march-step", "0.01",
                 "--max-samples", "1024"]) == 0  # fmt: skip
    out = capsys.readouterr()
    assert "below the marching step" in out.out + out.err and "--march-step" in out.out + out.err


def test_annealed_beta_sets_the_default_march_step():
    """Without --march-step, an annealed beta's final value bounds the grid's step (5/6 of it:
    0.0025 at 0.003, the measured materials recipe) and --max-samples grows to the steps across
    the box's diagonal; a given step, a final beta above the default step, no anneal, and a
    NeRF field keep the default rules."""
    import math

    from warpnerf.train.nerf_config import NeRFConfig

    def cfg(**kw):
        base = dict(field="hash_sdf", data="builtin", aabb=1.7, beta=0.01, learn_beta=False)
        return NeRFConfig(**{**base, **kw}).validate()

    default = 2 * 1.7 * math.sqrt(3) / 1024
    c = cfg(beta_final=0.003, beta_anneal_steps=6000)
    assert c.march_step == pytest.approx(0.0025) and c.max_samples == 2356
    c = cfg(beta_final=0.003, max_samples=4096)
    assert c.march_step == pytest.approx(0.0025) and c.max_samples == 4096
    assert cfg(beta_final=0.003, march_step=0.004, max_samples=2048).march_step == 0.004
    assert cfg(beta_final=0.008).march_step == pytest.approx(default)  # (0.0067 > the default)
    assert cfg().march_step == pytest.approx(default) and cfg().max_samples == 1024
    nerf = NeRFConfig(field="hash", data="builtin", aabb=1.7).validate()
    assert nerf.march_step == pytest.approx(default) and nerf.max_samples == 1024


@pytest.mark.parametrize("flag,value,key,on,other", [
    ("--color-direction", "reflect", "color_direction", lambda f: f.reflect, "reflect"),
    # (forward is hash_sdf's default: the flag's other value; the MLP field has central only)
    ("--sdf-gradient", "central", "sdf_gradient", lambda f: not f.forward_differences, "forward"),
])  # fmt: skip
def test_hash_sdf_flags(tmp_path, capsys, flag, value, key, on, other):
    """A hash_sdf-only flag trains, is saved and reaches the loaded field; another value and
    another field are refused (exit 2, the flag named)."""
    from warpnerf.cli.parser import main
    from warpnerf.train.nerf import load_run

    tiny = ["--data", "builtin", "--builtin-size", "16", "--batch", "64", "--val-images", "0",
            "--quiet", "--iters", "2"]  # fmt: skip
    hashed = ["--hash-levels", "3", "--hash-log2-size", "8", "--hash-max-res", "16",
              "--grid-res", "8"]  # fmt: skip
    run = tmp_path / "r"
    assert main(["train", "volsdf", *tiny, *hashed, "--field", "hash_sdf", flag, value,
                 "--out", str(run)]) == 0  # fmt: skip
    cfg, model, _ = load_run(run)
    assert getattr(cfg, key) == value and on(model.field)
    assert main(["train", "volsdf", *tiny, "--field", "volsdf", flag, other,
                 "--out", str(tmp_path / "v")]) == 2  # fmt: skip
    assert flag in capsys.readouterr().err
    assert main(["train", "volsdf", *tiny, *hashed, "--field", "hash_sdf", flag, "bogus",
                 "--out", str(tmp_path / "b")]) == 2  # fmt: skip
    assert key in capsys.readouterr().err.replace("-", "_")


def test_a_loaded_run_has_its_steps_schedule(tmp_path):
    """load_run sets the step's schedules (open hash levels, so the normals' step), which are
    not all in the weights."""
    from warpnerf.cli.parser import main
    from warpnerf.train.nerf import load_run

    run = tmp_path / "r"
    assert main(["train", "volsdf", "--data", "builtin", "--field", "hash_sdf", "--hash-levels",
                 "6", "--hash-log2-size", "8", "--hash-max-res", "32", "--grid-res", "8",
                 "--builtin-size", "16", "--batch", "64", "--val-images", "0", "--quiet",
                 "--iters", "3", "--c2f-every", "1", "--out", str(run)]) == 0  # fmt: skip
    _, model, ckpt = load_run(run)
    f = model.field
    # the last step (index 2) had 4 + 2 levels open: the saved mask and the normals' step agree
    assert ckpt["step"] == 3 and f.open_levels == 6 and int(f.level_mask.sum()) == 6 * 2
    assert f.fd_step == pytest.approx(2 * f.half / f.resolutions[5])
