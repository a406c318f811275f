"""The density level `warpnerf mesh` chooses for a NeRF run (warpnerf/mesh.py density_level):
the level set lies on the built-in scene's analytic surface (its box and sphere), for the
scene's own density and for a hash run trained on it, where the former fixed level 10 left
holes; an explicit --level still wins."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from warpnerf.data.synthetic import GlossyScene
from warpnerf.fields.sdf_volume import sdf_box, sdf_sphere
from warpnerf.mesh import density_level, extract_mesh, read_ply

from ._launches import cli_cpu_launches

SCENE = GlossyScene()


def scene_sdf(p) -> torch.Tensor:
    """The built-in scene's exact SDF: the union of its box and sphere."""
    p = torch.as_tensor(np.asarray(p), dtype=torch.float32)
    s = SCENE
    return torch.minimum(sdf_box(p, s.box_c, s.box_s), sdf_sphere(p, s.sph_c, s.sph_r))


def surface_points(n: int = 4000) -> torch.Tensor:
    """About n points spread by area over the scene's surface (the box's faces and the sphere)."""
    pts = SCENE.surface_points(n)
    assert scene_sdf(pts).abs().max() < 1e-4
    return pts


def against_scene(v) -> dict:
    """How a mesh (its vertices) lies on the scene's surface: accuracy (|true SDF| at the
    vertices: mean) and completeness (distance from the surface's points to the nearest vertex:
    mean and 95th percentile; a hole shows in the percentile)."""
    v = torch.as_tensor(np.asarray(v), dtype=torch.float32)
    ref = surface_points()
    near = torch.cat([torch.cdist(ref[i : i + 1000], v).min(1).values
                      for i in range(0, len(ref), 1000)])  # fmt: skip
    return {"accuracy": float(scene_sdf(v).abs().mean()), "completeness": float(near.mean()),
            "completeness_p95": float(near.quantile(0.95))}  # fmt: skip


def test_level_of_the_scene_density_lies_on_its_surface():
    """The scene's own density (Laplace of the SDF, beta 0.02: 50 inside, 25 on the surface):
    the chosen level is where its rays turn opaque, and its level set lies within 0.02 of the
    true surface (measured 0.017 on this 64^3 grid; 12.4 chosen)."""
    res = 64
    chosen = {}

    def level(vals):
        chosen["level"], chosen["why"] = density_level(-vals, res, [-1.0] * 3, [1.0] * 3)
        return -chosen["level"]

    v, f = extract_mesh(lambda p: -SCENE(p, torch.zeros_like(p))[0], [-1.0] * 3, [1.0] * 3, res,
                        level)  # fmt: skip
    assert 8 < chosen["level"] < 25, chosen
    assert "opacity 0.5" in chosen["why"], chosen
    s = scene_sdf(v)
    assert len(f) > 1000 and float(s.abs().mean()) < 0.02 and float(s.abs().max()) < 0.03


def test_a_faint_field_falls_back_to_half_its_peak():
    """No ray through the grid reaches opacity 0.5 (a ball of density 0.1): half the largest
    density, said so."""
    res = 24
    ax = torch.linspace(-1, 1, res)
    p = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    dens = 0.1 * (p.norm(dim=-1) < 0.5).float()
    level, why = density_level(dens, res, [-1.0] * 3, [1.0] * 3)
    assert level == pytest.approx(0.05) and "half the largest density" in why


# ---------------------------------------------------------------- a hash run on the built-in scene


@pytest.fixture(scope="module")
def hash_run(tmp_path_factory):
    """The README's `--preset cpu` hash run on the built-in scene (300 steps; no validation)."""
    from warpnerf.cli.parser import main

    run = tmp_path_factory.mktemp("mesh_level") / "hash"
    with cli_cpu_launches():  # (as the command runs: one lane per block on the CPU)
        assert main(["train", "nerf", "--data", "builtin", "--field", "hash", "--preset", "cpu",
                     "--val-images", "0", "--quiet", "--no-tensorboard", "--device", "cpu",
                     "--out", str(run)]) == 0  # fmt: skip
    return run


@pytest.mark.slow
def test_mesh_of_a_hash_run_lies_on_the_scene(hash_run, tmp_path, capsys, cli_launches):
    """`warpnerf mesh RUN` with no --level: the result's JSON gives the level chosen and why, and
    the mesh lies on the box and the sphere without holes; the former fixed level 10 fails the
    same bounds (a holed sphere, the box in pieces), and --level 10 is still obeyed.

    Measured on one training of this run (96^3 grid): level 4.7 chosen; accuracy 0.050,
    completeness 0.040 (95th percentile 0.103). At level 10: accuracy 0.038 (the mesh sits
    inside the surface, where the density peaks: accuracy alone prefers it), completeness 0.091
    (95th percentile 0.278: the holes). Those are the command's figures (one lane per block on
    the CPU, as this test launches); seeds 1 / 2 (2026-12-02): accuracy 0.055 / 0.052,
    completeness 0.045 / 0.042 (95th percentile 0.129 / 0.128), level 10 off the surface."""
    from warpnerf.cli.parser import main

    base = ["mesh", str(hash_run), "--resolution", "96", "--no-screenshot", "--quiet"]
    assert main([*base, "--out", str(tmp_path / "auto.ply")]) == 0
    out, err = capsys.readouterr()
    res = json.loads(out.strip().splitlines()[-1])
    assert "opacity 0.5" in res["level_rule"] and "--level sets it" in res["level_rule"], res
    assert "warpnerf mesh: level" not in err  # (said in the JSON: stderr stays progress only)
    auto = against_scene(read_ply(tmp_path / "auto.ply")[0])

    def on_surface(m):
        return (m["accuracy"] < 0.07 and m["completeness"] < 0.06
                and m["completeness_p95"] < 0.15)  # fmt: skip

    assert on_surface(auto), (res["level"], auto)
    rc = main([*base, "--out", str(tmp_path / "ten.ply"), "--level", "10"])
    out, err = capsys.readouterr()
    assert "level_rule" not in (out.strip().splitlines() or ["{}"])[-1]  # (--level given)
    if rc != 0:  # (a run whose densities stay under 10 has no surface there at all)
        assert rc == 2 and "no surface at level 10.0" in err, err
        return
    assert json.loads(out.strip().splitlines()[-1])["level"] == 10.0
    ten = against_scene(read_ply(tmp_path / "ten.ply")[0])
    assert not on_surface(ten), ten


# ------------------------------------------------------- a surface run on the built-in scene


@pytest.mark.slow
def test_delivered_mesh_of_a_surface_run_lies_on_the_scene(tmp_path, capsys, cli_launches):
    """`train volsdf --data builtin --field hash_sdf --preset cpu` (150 steps; the opacity loss
    against the scene's alpha by default), then `warpnerf mesh` as
    delivered (culled, cleaned): its Chamfer distance to the analytic box and sphere is under
    0.05 (issue 49's target), with no hole. Measured: accuracy 0.0098, completeness 0.0136
    (95th percentile 0.029), Chamfer 0.0117; before the mask loss about 0.2 (the box's white
    faces invisible on the white background, its extent short by 0.22-0.26 on three sides).
    Seeds 1 / 2 (2026-12-02, one lane per block as the command): Chamfer 0.0132 / 0.0116.
    Since 2026-12-03 it takes forward differences (hash_sdf's default, `--sdf-gradient`): Chamfer
    0.0117 as with central ones, training 50.8 s against 87.2 s (docs/design/training.md); and
    Huber (hash_sdf's default colour loss since the same day): Chamfer 0.0136, p95 0.034."""
    from warpnerf.cli.parser import main

    run = tmp_path / "surface"
    assert main(["train", "volsdf", "--data", "builtin", "--field", "hash_sdf", "--preset", "cpu",
                 "--val-images", "0", "--quiet", "--no-tensorboard", "--device", "cpu", "--out",
                 str(run)]) == 0  # fmt: skip
    capsys.readouterr()
    assert main(["mesh", str(run), "--resolution", "96", "--no-screenshot", "--quiet", "--out",
                 str(tmp_path / "m.ply")]) == 0  # fmt: skip
    m = against_scene(read_ply(tmp_path / "m.ply")[0])
    chamfer = 0.5 * (m["accuracy"] + m["completeness"])
    assert chamfer < 0.05 and m["completeness_p95"] < 0.1, m
