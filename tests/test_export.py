"""`warpnerf export RUN pointcloud|cameras`: a coloured point cloud with normals where the rays
terminate, and the cameras as a nerfstudio transforms.json that the project's own loader reads
back to the same cameras."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from warpnerf.cli.parser import main
from warpnerf.mesh import read_ply, write_ply

TINY = ["--data", "builtin", "--field", "hash_sdf", "--hash-levels", "3", "--hash-log2-size", "8",
        "--hash-max-res", "16", "--grid-res", "8", "--builtin-size", "16", "--batch", "64",
        "--val-images", "0", "--quiet", "--iters", "2"]  # fmt: skip


@pytest.fixture(scope="module")
def sdf_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("export") / "r"
    assert main(["train", "volsdf", *TINY, "--out", str(run)]) == 0
    return run


@pytest.mark.slow
def test_pointcloud_lies_on_the_surface_with_outward_normals(sdf_run, tmp_path, capsys):
    """Points are where rays terminate: near the learned SDF's zero level set (within a few
    beta); normals are the SDF's unit gradient there; colours are the rendered ones."""
    from warpnerf.train.nerf import load_run

    out = tmp_path / "pc.ply"
    assert main(["export", str(sdf_run), "pointcloud", "--out", str(out), "--views", "3",
                 "--stride", "2"]) == 0  # fmt: skip
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    v, f, rgb, nrm = read_ply(out, colors=True, normals=True)
    assert len(f) == 0 and len(v) == res["points"] > 50 and rgb.dtype == np.uint8
    assert np.allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-4)
    _, model, _ = load_run(sdf_run)
    field = model.field
    x = torch.as_tensor(v)
    with torch.no_grad():
        d = field.sdf(x)
        g = torch.nn.functional.normalize(field.gradient(x), dim=-1)
    beta = field.beta.item()
    assert float(d.abs().median()) < 3 * beta
    assert float((g * torch.as_tensor(nrm)).sum(-1).median()) > 0.99


def test_cameras_round_trip_through_the_nerfstudio_loader(sdf_run, tmp_path, capsys):
    from warpnerf.data import load_nerfstudio
    from warpnerf.train.nerf import load_data, load_run

    out = tmp_path / "ns" / "transforms.json"
    out.parent.mkdir()
    assert main(["export", str(sdf_run), "cameras", "--out", str(out)]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["images_written"] == res["frames"] > 0  # the built-in scene has no files
    cfg, _, _ = load_run(sdf_run, "cpu")
    train = load_data(cfg, "train")
    doc = json.loads(out.read_text())
    doc["frames"] = [fr for fr in doc["frames"] if fr["split"] == "train"]
    out.write_text(json.dumps(doc))  # the train cameras alone, read back as one split
    back = load_nerfstudio(out.parent, holdout=0)
    assert torch.allclose(back.c2w.float(), train.c2w.float(), atol=1e-6)
    assert torch.allclose(back.intrinsics.float(), train.intrinsics.float(), atol=1e-4)
    assert torch.allclose(back.images, train.images, atol=1.5 / 255)


def test_export_refuses_bad_requests(sdf_run, tmp_path):
    assert main(["export", str(sdf_run), "pointcloud", "--out", str(tmp_path / "x.txt")]) == 2
    assert main(["export", str(sdf_run), "pointcloud", "--out", str(tmp_path / "x.ply"),
                 "--min-opacity", "1.5"]) == 2  # fmt: skip
    assert main(["export", str(sdf_run), "cameras", "--out", str(tmp_path / "x.ply")]) == 2
    assert main(["export", str(tmp_path / "nothing"), "cameras", "--out",
                 str(tmp_path / "t.json")]) == 2  # fmt: skip
    assert not (tmp_path / "x.ply").exists() and not (tmp_path / "t.json").exists()


def test_ply_with_normals_round_trips(tmp_path):
    g = np.random.default_rng(0)
    v = g.normal(size=(9, 3)).astype(np.float32)
    n = g.normal(size=(9, 3)).astype(np.float32)
    c = g.integers(0, 256, (9, 3)).astype(np.uint8)
    write_ply(tmp_path / "p.ply", v, np.zeros((0, 3), np.int32), colors=c, normals=n)
    v2, f2, c2, n2 = read_ply(tmp_path / "p.ply", colors=True, normals=True)
    assert np.array_equal(v, v2) and np.array_equal(c, c2) and np.array_equal(n, n2)
    assert len(f2) == 0
    pv = pytest.importorskip("pyvista")
    cloud = pv.read(tmp_path / "p.ply")
    assert cloud.n_points == 9 and np.allclose(np.asarray(cloud.points), v)


def test_an_exported_capture_trains_as_the_capture_it_came_from(tmp_path, capsys):
    """A COLMAP capture's run exported as a nerfstudio folder (`export cameras`: per-frame
    intrinsics and splits, the poses in the run's normalised frame, its near/far/box in
    ``warpnerf_scene``) resolves to the same scene settings and splits, and trains to the same
    result (same seed) as the COLMAP folder."""
    from warpnerf.train.nerf import load_data, load_run

    from .test_capture import _colmap_capture, _object_cameras

    _colmap_capture(tmp_path / "cap", _object_cameras(12))
    flags = ["--field", "hash", "--hash-levels", "2", "--hash-log2-size", "8", "--hash-max-res",
             "16", "--hidden", "8", "--grid-res", "8", "--batch", "64", "--iters", "4",
             "--val-images", "0", "--quiet", "--no-tensorboard", "--holdout", "4"]  # fmt: skip
    assert main(["train", "nerf", "--data", str(tmp_path / "cap"), *flags, "--out",
                 str(tmp_path / "a")]) == 0  # fmt: skip
    out = tmp_path / "ns" / "transforms.json"
    out.parent.mkdir()
    assert main(["export", str(tmp_path / "a"), "cameras", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert set(doc["warpnerf_scene"]) == {"near", "far", "aabb", "inner"}
    assert main(["train", "nerf", "--data", str(out.parent), *flags, "--allow-outside-paths",
                 "--out", str(tmp_path / "b")]) == 0  # fmt: skip
    ca, ma, _ = load_run(tmp_path / "a")
    cb, mb, _ = load_run(tmp_path / "b")
    assert cb.scene["format"] == "nerfstudio" and ca.scene["format"] == "colmap"
    for k in ("near", "far", "aabb", "contract", "appearance_dim", "hash_max_res", "march_step"):
        va, vb = getattr(ca, k), getattr(cb, k)
        if isinstance(va, (int, float)) and not isinstance(va, bool):
            assert va == pytest.approx(vb, rel=1e-6), k
        else:  # strings (contract) and lists compare exactly, not through approx
            assert va == vb, k
    for split in ("train", "val"):
        da, db = load_data(ca, split), load_data(cb, split)
        assert torch.allclose(da.c2w.float(), db.c2w.float(), atol=1e-5)
        assert torch.allclose(da.intrinsics.float(), db.intrinsics.float(), atol=1e-4)
        assert torch.allclose(da.images, db.images, atol=1.5 / 255)
    ha = json.loads((tmp_path / "a" / "history.json").read_text())["loss"]
    hb = json.loads((tmp_path / "b" / "history.json").read_text())["loss"]
    assert np.allclose(ha, hb, rtol=1e-3)
    capsys.readouterr()
    bad = dict(doc, warpnerf_scene={"near": 1.0, "far": 0.5, "aabb": 1.0})
    out.write_text(json.dumps(bad))
    assert main(["train", "nerf", "--data", str(out.parent), *flags, "--allow-outside-paths",
                 "--out", str(tmp_path / "c")]) == 2  # fmt: skip
    assert "warpnerf_scene" in capsys.readouterr().err and not (tmp_path / "c").exists()


def test_a_downscaled_run_exports_the_images_it_trained_on(tmp_path, capsys):
    """A run trained with --downscale 2 (the capture's files are full size): the export's
    frames point at images of the size its intrinsics describe, and the nerfstudio loader reads
    back the run's own cameras and pixels (was: downscaled intrinsics beside full-size files)."""
    from warpnerf.data import load_nerfstudio
    from warpnerf.data.images import read_image
    from warpnerf.train.nerf import load_data, load_run

    from .test_capture import _colmap_capture, _object_cameras

    _colmap_capture(tmp_path / "cap", _object_cameras(8))
    flags = ["--field", "hash", "--hash-levels", "2", "--hash-log2-size", "8", "--hash-max-res",
             "16", "--hidden", "8", "--grid-res", "8", "--batch", "32", "--iters", "2",
             "--val-images", "0", "--quiet", "--no-tensorboard", "--holdout", "0",
             "--downscale", "2"]  # fmt: skip
    run = tmp_path / "run"
    assert main(["train", "nerf", "--data", str(tmp_path / "cap"), *flags, "--out",
                 str(run)]) == 0  # fmt: skip
    out = tmp_path / "ns" / "transforms.json"
    out.parent.mkdir()
    assert main(["export", str(run), "cameras", "--out", str(out)]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    cfg, _, _ = load_run(run, "cpu")
    train = load_data(cfg, "train")
    assert res["images_written"] == res["frames"] >= len(train)
    doc = json.loads(out.read_text())
    doc["frames"] = [fr for fr in doc["frames"] if fr["split"] == "train"]
    out.write_text(json.dumps(doc))  # the train cameras alone, read back as one split
    assert len(doc["frames"]) == len(train)
    for fr in doc["frames"]:
        img = read_image(out.parent / fr["file_path"])
        assert img.shape[:2] == (fr["h"], fr["w"]) == (train.height, train.width)
    back = load_nerfstudio(out.parent, holdout=0)
    assert torch.allclose(back.intrinsics.float(), train.intrinsics.float(), atol=1e-4)
    assert torch.allclose(back.images, train.images, atol=1.5 / 255)
    # the same run without --downscale points at the capture's own files
    full = tmp_path / "full"
    assert main(["train", "nerf", "--data", str(tmp_path / "cap"), *flags[:-2], "--out",
                 str(full)]) == 0  # fmt: skip
    capsys.readouterr()
    assert main(["export", str(full), "cameras", "--out", str(tmp_path / "f.json")]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["images_written"] == 0
