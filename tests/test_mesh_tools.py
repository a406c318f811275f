"""Mesh post-processing (warpnerf/mesh.py clean_mesh, decimate_mesh; `warpnerf mesh --clean
--decimate`): floaters removed by area, decimation to the requested face count staying on the
surface and manifold, the command end to end and its refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from warpnerf.mesh import clean_mesh, decimate_mesh, extract_mesh, read_ply, sample_surface

pytest.importorskip("pyvista")

R, SMALL = 0.8, 0.06  # big sphere at the origin, a tiny floating one at FLOAT
FLOAT = torch.tensor([1.1, 1.1, 1.1])


def two_spheres(p):
    return torch.minimum(p.norm(dim=-1) - R, (p - FLOAT).norm(dim=-1) - SMALL)


@pytest.fixture(scope="module")
def spheres():
    return extract_mesh(two_spheres, [-1.5] * 3, [1.5] * 3, 64)


def edge_uses(f):
    """How many triangles use each undirected edge (2 everywhere: closed and manifold)."""
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), 1)
    return np.unique(np.unique(e, axis=0, return_counts=True)[1])


def test_clean_drops_the_floating_sphere(spheres):
    v, f = spheres
    v2, f2, info = clean_mesh(v, f)  # the floater has ~0.6 % of the area
    assert info["components"] == 2 and info["components_removed"] == 1
    assert info["faces_before"] == len(f) and info["faces_after"] == len(f2) < len(f)
    assert 0 < info["area_removed_fraction"] < 0.01
    assert np.abs(np.linalg.norm(v2, axis=1) - R).max() < 0.01  # only the big sphere is left
    assert f2.dtype == np.int32 and v2.dtype == np.float32 and f2.max() == len(v2) - 1
    assert np.array_equal(edge_uses(f2), [2])
    # min_fraction 0 keeps everything; a large one still keeps the largest component
    assert clean_mesh(v, f, 0.0)[2]["components_removed"] == 0
    assert len(clean_mesh(v, f, 0.0)[1]) == len(f)
    assert len(clean_mesh(v, f, 0.99)[1]) == len(f2)
    # a vertex per triangle (unshared, as some marching cubes emit): merged before connectivity
    vs, fs = v[f].reshape(-1, 3), np.arange(3 * len(f), dtype=np.int32).reshape(-1, 3)
    v3, f3, info3 = clean_mesh(vs, fs)
    assert info3["components"] == 2 and len(v3) == len(v2) and len(f3) == len(f2)
    with pytest.raises(ValueError, match="min_fraction"):
        clean_mesh(v, f, 1.0)
    with pytest.raises(ValueError, match="min_fraction"):
        clean_mesh(v, f, -0.1)
    e = clean_mesh(v[:0], f[:0])
    assert e[0].shape == (0, 3) and e[1].shape == (0, 3) and e[2]["components"] == 0


def test_decimation_keeps_the_surface(spheres):
    v, f, _ = clean_mesh(*spheres)
    for reduction in (0.5, 0.9):
        v2, f2 = decimate_mesh(v, f, reduction)
        assert len(f2) == pytest.approx((1 - reduction) * len(f), rel=0.05)
        assert np.array_equal(edge_uses(f2), [2])  # still closed and manifold
        # one-sided Hausdorff-like distances to the true sphere: vertices and the surface between
        # (the original mesh is within ~0.003 of it at this resolution)
        assert np.abs(np.linalg.norm(v2, axis=1) - R).max() < 0.01
        pts = sample_surface(v2, f2, 20000)
        assert np.abs(np.linalg.norm(pts, axis=1) - R).max() < (0.02 if reduction < 0.9 else 0.05)
    with pytest.raises(ValueError, match="reduction"):
        decimate_mesh(v, f, 0.0)
    with pytest.raises(ValueError, match="reduction"):
        decimate_mesh(v, f, 1.0)


def test_mesh_command_cleans_and_decimates(tmp_path, capsys):
    from warpnerf.cli.parser import main

    ply = tmp_path / "t.ply"
    base = ["mesh", "--sdf", "torus", "--out", str(ply), "--resolution", "48", "--no-screenshot"]
    assert main([*base, "--clean", "--decimate", "0.5"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    v, f = read_ply(ply)
    assert res["faces"] == len(f) and res["vertices"] == len(v)
    assert res["faces"] == pytest.approx(0.5 * res["faces_extracted"], rel=0.05)
    assert res["clean"] == 0.01 and res["components"] == 1 and res["components_removed"] == 0
    assert res["decimate"] == 0.5 and np.array_equal(edge_uses(f), [2])
    assert main([*base, "--clean", "0.2"]) == 0  # an explicit fraction; no decimation
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["clean"] == 0.2 and res["faces"] == res["faces_extracted"]
    assert "decimate" not in res
    for flags, needle in (
        (["--clean", "1"], "--clean MIN_FRACTION must be in [0, 1)"),
        (["--clean", "-0.5"], "--clean MIN_FRACTION"),
        (["--decimate", "0"], "--decimate R must be in (0, 1)"),
        (["--decimate", "1.5"], "--decimate R"),
    ):
        ply.unlink(missing_ok=True)
        assert main([*base, *flags]) == 2
        err = capsys.readouterr().err
        assert needle in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
        assert not ply.exists()  # refused before anything is written
    with pytest.raises(SystemExit) as e:
        main([*base, "--decimate", "nan"])
    assert e.value.code == 2 and "argument --decimate" in capsys.readouterr().err


# ------------------------------------------------------ NeRF runs: density levels and colours

RED_SIGMA = float(np.exp(4.0))  # ~54.6: the red box run's density inside its box


def red_box_run(tmp_path):
    """A one-step hash-field NeRF run on the built-in scene, then hand-set: its density is
    exp(4) ~ 54.6 everywhere inside the scene box [-1, 1]^3 (and 0 outside it, as the hash field
    always is) and its colour pure red whatever the position and direction: the level set of any
    density in (0, 54.6) is the box, and its baked colour must be red."""
    from warpnerf.cli.parser import main
    from warpnerf.outputs import load_checkpoint, save_checkpoint

    run = tmp_path / "redbox"
    assert main(["train", "nerf", "--data", "builtin", "--builtin-size", "8", "--field", "hash",
                 "--iters", "1", "--batch", "32", "--hash-levels", "2", "--hash-log2-size", "10",
                 "--hidden", "16", "--grid-res", "16", "--val-images", "0", "--quiet",
                 "--no-tensorboard", "--device", "cpu", "--out", str(run)]) == 0  # fmt: skip
    ck = load_checkpoint(run / "checkpoint.pt")
    f = ck["fields"]["coarse"]
    f["density_mlp.2.weight"].zero_()
    f["density_mlp.2.bias"].zero_()
    f["density_mlp.2.bias"][0] = 4.0  # sigma = exp(4) inside the box
    f["color_mlp.4.weight"].zero_()
    f["color_mlp.4.bias"].copy_(torch.tensor([10.0, -10.0, -10.0]))  # sigmoid: red
    save_checkpoint(run / "checkpoint.pt", ck)
    return run


@pytest.fixture(scope="module")
def red_box(tmp_path_factory):
    return red_box_run(tmp_path_factory.mktemp("mesh_runs"))


def test_vertex_colors_look_along_the_inward_normal():
    """The bake's camera looks at the surface along the inward normal, for an SDF and for minus
    a density (a NeRF's level-set function): a field coloured by the viewing direction (red
    looking inwards, blue outwards) is red on every vertex of a sphere."""
    import torch.nn.functional as F

    from warpnerf.mesh import vertex_colors

    def field(x, d):  # colour = where the camera looks: cos(d, towards the centre)
        inward = (d * -F.normalize(x, dim=-1)).sum(-1)
        rgb = torch.stack([(1 + inward) / 2, torch.zeros_like(inward), (1 - inward) / 2], -1)
        return torch.ones(len(x)), rgb

    def sdf(p):
        return p.norm(dim=-1) - 0.5

    def minus_density(p):  # dense inside: 50 in the ball, 25 on its surface
        return -50.0 * torch.sigmoid(-sdf(p) / 0.05)

    for fn, level in ((sdf, 0.0), (minus_density, -25.0)):
        v, f = extract_mesh(fn, [-1] * 3, [1] * 3, 24, level)
        assert len(f) > 100
        c = vertex_colors(field, fn, v, "cpu")
        assert c.dtype == np.uint8 and c.shape == v.shape
        assert c[:, 0].min() >= 250 and c[:, 2].max() <= 5, (c.min(0), c.max(0))


def test_mesh_of_a_nerf_run_suggests_a_level_and_bakes_its_colours(red_box, tmp_path, capsys):
    """`warpnerf mesh RUN`: with no surface at the level asked for, one error line with the
    densities seen and a level to try (exit 2); that level gives the box, whose baked colours
    are the field's red."""
    from warpnerf.cli.parser import main

    ply = tmp_path / "m.ply"
    base = ["mesh", str(red_box), "--out", str(ply), "--resolution", "20", "--bounds", "1.25",
            "--no-screenshot"]  # fmt: skip
    assert main([*base, "--level", "100"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert "no surface at level 100.0" in err
    assert f"range from 0 to {RED_SIGMA:.4g}" in err, err
    hint = float(err.split("try --level ")[1].split()[0])
    assert hint == pytest.approx(RED_SIGMA / 2, rel=1e-2)  # half the largest density
    assert not ply.exists()
    assert main([*base, "--level", str(hint), "--colors"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    v, f, c = read_ply(ply, colors=True)
    assert res["colors"] and res["level"] == hint and len(f) == res["faces"] > 0
    # the box's faces: |x|_inf within a grid step (0.13) of 1
    assert np.abs(np.abs(v).max(1) - 1.0).max() < 0.14
    assert np.array_equal(np.unique(c, axis=0), [[255, 0, 0]]), np.unique(c, axis=0)[:5]


# ------------------------------------------------------------------ PLY files (plyfile-backed)


def _tetra():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32)
    return v, f


def test_ply_round_trip_and_files_other_tools_write(tmp_path):
    import plyfile

    from warpnerf.mesh import read_ply, write_ply

    v, f = _tetra()
    c = np.arange(12, dtype=np.uint8).reshape(4, 3)
    write_ply(tmp_path / "m.ply", v, f, colors=c, normals=v)
    v2, f2, c2, n2 = read_ply(tmp_path / "m.ply", colors=True, normals=True)
    assert np.array_equal(v2, v) and np.array_equal(f2, f) and np.array_equal(c2, c)
    assert np.array_equal(n2, v)
    # ascii and big-endian files (as MeshLab or Blender may write them) read the same
    rows = np.array([tuple(p) for p in v], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    tris = np.empty(4, dtype=[("vertex_indices", "i4", (3,))])
    tris["vertex_indices"] = f
    for name, kw in (("a.ply", {"text": True}), ("b.ply", {"byte_order": ">"})):
        plyfile.PlyData([plyfile.PlyElement.describe(rows, "vertex"),
                         plyfile.PlyElement.describe(tris, "face")], **kw).write(
            str(tmp_path / name))  # fmt: skip
        v3, f3, c3 = read_ply(tmp_path / name, colors=True)
        assert np.array_equal(v3, v) and np.array_equal(f3, f) and c3 is None


@pytest.mark.parametrize("mutate, match", [
    (lambda b: b.replace(b"element vertex 4", b"element vertex 4000000"), "promises more"),
    (lambda b: b[: len(b) - 20], "unreadable"),
    (lambda b: b.replace(b"ply\n", b"plx\n", 1), "does not start"),
    (lambda b: b[:-13] + b"\x03" + np.array([0, 1, 99], "<i4").tobytes(), "outside"),
    (lambda b: b.replace(b"format binary_little_endian", b"format binary_sideways"), "header"),
])  # fmt: skip
def test_hostile_ply_files_are_refused(tmp_path, mutate, match):
    from warpnerf.errors import UserError
    from warpnerf.mesh import read_ply, write_ply

    v, f = _tetra()
    write_ply(tmp_path / "m.ply", v, f)
    bad = tmp_path / "bad.ply"
    bad.write_bytes(mutate((tmp_path / "m.ply").read_bytes()))
    with pytest.raises(UserError, match=match):
        read_ply(bad)


def test_ply_with_a_huge_extra_element_is_refused(tmp_path):
    from warpnerf.errors import UserError

    f = tmp_path / "junk.ply"
    f.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\n"
                  b"property float y\nproperty float z\nelement junk 100000000000000000\n"
                  b"property uchar a\nend_header\n" + b"\0" * 64)  # fmt: skip
    with pytest.raises(UserError, match="promises more"):
        read_ply(f)
