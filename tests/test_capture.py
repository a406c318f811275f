"""COLMAP (text + binary) and LLFF loaders on tiny synthetic captures written by the tests:
pose conventions (a known point projects to the right pixel), distortion, normalisation (reversible,
the same for COLMAP and LLFF), hold-out, NDC, `warpnerf data` and bad input."""

from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest
import torch

from warpnerf.cli import main
from warpnerf.data import load_dataset
from warpnerf.data.cameras import camera_rays, look_at, ndc_rays
from warpnerf.data.capture import capture_info, normalised_to_world, reprojection_errors
from warpnerf.data.colmap import Camera, Image, read_model, rotmat_to_qvec, write_model
from warpnerf.errors import UserError
from warpnerf.train.nerf import resolve_data

W, H = 24, 16
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _object_cameras(n=10, radius=5.0, centre=(1.0, -2.0, 0.5)):
    """OpenGL c2w [n, 4, 4] on an arc around ``centre`` (an object capture), y up."""
    mats = []
    for i in range(n):
        az = math.radians(-70 + 140 * i / (n - 1))
        eye = np.array(centre) + radius * np.array(
            [math.sin(az), 0.3 + 0.1 * (i % 3), math.cos(az)]
        )
        mats.append(look_at(eye, centre, up=(0.0, 1.0, 0.0), dtype=torch.float64).numpy())
    return np.stack(mats)


def _forward_cameras(n=9):
    """Forward-facing: small translations, all looking down -z at a scene 10..40 units away."""
    mats = []
    for i in range(n):
        m = np.eye(4)
        m[:3, 3] = [0.5 * math.cos(i), 0.3 * math.sin(i), 0.1 * i / n]
        a = math.radians(3 * math.sin(2 * i))
        m[:3, :3] = [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]
        mats.append(m)
    return np.stack(mats)


def _project(c2w_gl, k, dist, x_world):
    """Pixel (u, v) of a world point, OpenCV model with distortion (k1, k2, p1, p2)."""
    w2c = np.linalg.inv(c2w_gl @ _GL_TO_CV)
    xc = w2c[:3, :3] @ x_world + w2c[:3, 3]
    x, y = xc[0] / xc[2], xc[1] / xc[2]
    k1, k2, p1, p2 = dist
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return k[0] * xd + k[2], k[1] * yd + k[3]


def _write_images(folder, names, size=(W, H)):
    import imageio.v3 as iio

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for name in names:
        iio.imwrite(folder / name, rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))


def _colmap_capture(root, c2w, model="PINHOLE", params=None, text=False, points=None,
                    posed=None):  # fmt: skip
    """A COLMAP capture of cameras ``c2w`` (OpenGL); its images' observations of ``points`` are
    their true projections through the cameras ``posed`` (default: ``c2w``)."""
    names = [f"img_{i:03d}.png" for i in range(len(c2w))]
    params = params if params is not None else [20.0, 21.0, W / 2 + 0.3, H / 2 - 0.2]
    cams = {1: Camera(1, model, W, H, np.asarray(params, dtype=np.float64))}
    k, dist = cams[1].pinhole()
    images = {}
    for i, m in enumerate(c2w):
        w2c = np.linalg.inv(m @ _GL_TO_CV)
        ids = np.arange(1, len(points) + 1) if points is not None else np.zeros(0, np.int64)
        src = m if posed is None else posed[i]
        xys = np.array([_project(src, k, dist, x) for x in points]) if points is not None else None
        images[i + 1] = Image(i + 1, rotmat_to_qvec(w2c[:3, :3]), w2c[:3, 3], 1, names[i], ids, xys)
    write_model(root / "sparse" / "0", cams, images, points, text=text)
    _write_images(root / "images", names)
    return names


def _llff_capture(root, c2w, focal, bounds, folder="images", size=(W, H)):
    root.mkdir(parents=True, exist_ok=True)
    rows = []
    for m in c2w:
        pose = np.stack([-m[:3, 1], m[:3, 0], m[:3, 2], m[:3, 3], [size[1], size[0], focal]], 1)
        rows.append(np.concatenate([pose.reshape(-1), bounds]))
    np.save(root / "poses_bounds.npy", np.asarray(rows))
    _write_images(root / folder, [f"{i:03d}.png" for i in range(len(c2w))], size)


MODELS = [
    ("SIMPLE_PINHOLE", [20.0, 12.1, 7.9], [0, 0, 0, 0]),
    ("PINHOLE", [20.0, 21.0, 12.3, 7.8], [0, 0, 0, 0]),
    ("SIMPLE_RADIAL", [20.0, 12.1, 7.9, 0.08], [0.08, 0, 0, 0]),
    ("RADIAL", [20.0, 12.1, 7.9, 0.1, -0.05], [0.1, -0.05, 0, 0]),
    ("OPENCV", [20.0, 21.0, 12.3, 7.8, -0.1, 0.02, 0.005, -0.004], [-0.1, 0.02, 0.005, -0.004]),
]


@pytest.mark.parametrize("text", [False, True], ids=["bin", "txt"])
@pytest.mark.parametrize("model,params,dist", MODELS, ids=[m[0] for m in MODELS])
def test_colmap_known_point_projects_to_its_pixel(tmp_path, model, params, dist, text):
    """A world point's (distorted) pixel gives a ray that passes through the point, after the
    loader's OpenCV->OpenGL conversion, undistortion and normalisation."""
    c2w = _object_cameras(4)
    _colmap_capture(tmp_path, c2w, model, params, text=text)
    ds = load_dataset(tmp_path, "train", holdout=0)
    assert ds["format"] == "colmap" and ds["images"].shape == (4, H, W, 3)
    assert np.allclose(ds["distortion"][0].numpy(), dist)
    t = ds["transform"]
    k = np.asarray(ds["intrinsics"][0], dtype=np.float64)
    rng = np.random.default_rng(1)
    for i in range(4):
        for _ in range(5):
            x = np.array([1.0, -2.0, 0.5]) + rng.uniform(-0.8, 0.8, 3)
            u, v = _project(c2w[i], [*k], dist, x)
            px, py = torch.tensor([u, v], dtype=torch.float64).split(1)
            o, d = camera_rays(
                ds["c2w"].double(), ds["intrinsics"].double(), cam_idx=torch.tensor([i]),
                px=px, py=py, distortion=ds["distortion"].double(),
            )  # fmt: skip
            xn = t[:3, :3] @ x + t[:3, 3]
            rel = xn - o[0].numpy()
            off = rel - (rel @ d[0].numpy()) * d[0].numpy()  # distance of the point to the ray
            assert np.linalg.norm(off) < 1e-4 * np.linalg.norm(rel), (model, i)
            # float32 poses: the same pixel within a thousandth of a pixel-ray
    back = normalised_to_world((t[:3, :3] @ np.eye(3).T).T + t[:3, 3], t)
    assert np.allclose(back, np.eye(3), atol=1e-9)  # the transform is reversible


@pytest.mark.parametrize("text", [False, True], ids=["bin", "txt"])
@pytest.mark.parametrize("model,params,dist", MODELS[2:], ids=[m[0] for m in MODELS[2:]])
def test_reprojection_of_the_models_observations(tmp_path, model, params, dist, text, capsys):
    """`warpnerf data` on a COLMAP capture: observations that are the points' true projections
    (distorted) reproject within float64 rounding; a camera turned by 0.5 degrees shows up as
    about f * 0.5 degrees in the statistics; observations of ids the model lacks are left out."""
    c2w = _object_cameras(5)
    pts = np.array([1.0, -2.0, 0.5]) + np.random.default_rng(3).uniform(-0.8, 0.8, (40, 3))
    _colmap_capture(tmp_path / "ok", c2w, model, params, text=text, points=pts)
    rep = reprojection_errors(tmp_path / "ok")
    assert rep["observations"] == rep["used"] == 5 * 40 and rep["behind_camera"] == 0
    assert rep["max_px"] < 1e-6 and rep["colmap_mean_error_px"] == pytest.approx(0.5)
    # the observations of camera 2 come from that camera turned by 0.5 degrees about its y axis
    a = math.radians(0.5)
    turn = np.eye(4)
    turn[:3, :3] = [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]
    posed = c2w.copy()
    posed[2] = posed[2] @ turn
    _colmap_capture(tmp_path / "off", c2w, model, params, text=text, points=pts, posed=posed)
    rep = reprojection_errors(tmp_path / "off")
    f = params[0]
    assert rep["median_px"] < 1e-6  # four of five cameras exact
    assert rep["max_px"] == pytest.approx(f * a, rel=0.25)  # (distortion scales it a little)
    # through the CLI: the same statistics in the summary; a model without points: null
    assert main(["data", str(tmp_path / "off"), "--holdout", "0"]) == 0
    info = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert info["reprojection"]["max_px"] == pytest.approx(rep["max_px"])
    _colmap_capture(tmp_path / "none", c2w, model, params, text=text)
    assert reprojection_errors(tmp_path / "none") is None


def test_reprojection_skips_unknown_point_ids_and_counts_points_behind(tmp_path):
    c2w = _object_cameras(3)
    pts = np.array([1.0, -2.0, 0.5]) + np.random.default_rng(4).uniform(-0.5, 0.5, (10, 3))
    _colmap_capture(tmp_path, c2w, points=pts)
    sp = tmp_path / "sparse" / "0"
    cams, ims, _ = read_model(sp)
    ims[1].point3d_ids = ims[1].point3d_ids.copy()
    ims[1].point3d_ids[:3] = [-1, 999, 12345]  # no point, and ids the model does not hold
    ims[2].xys[4] = [np.nan, np.inf]  # a non-finite pixel: left out and counted
    ims[2].xys[5] = [-3.0, 1e12]  # outside the image: left out and counted
    behind = 2 * c2w[0, :3, 3] - np.array([1.0, -2.0, 0.5])  # behind camera 0, not 1, 2
    write_model(sp, cams, ims, np.concatenate([pts[:-1], behind[None]]))
    rep = reprojection_errors(tmp_path)
    assert rep["non_finite"] == 1 and rep["outside_image"] >= 1 and rep["behind_camera"] >= 1
    assert rep["observations"] + rep["outside_image"] == 3 * 10 - 4  # (3 ids, 1 NaN left out)
    assert np.isfinite(rep["median_px"])
    # a distorted camera: an observation far outside its image stays out of the undistortion
    cams[1].model, cams[1].params = "SIMPLE_RADIAL", np.array([20.0, 12.1, 7.9, 0.08])
    ims[3].xys[0] = [5000.0, 5000.0]
    write_model(sp, cams, ims, np.concatenate([pts[:-1], behind[None]]))
    assert reprojection_errors(tmp_path)["outside_image"] >= 2


def test_colmap_text_image_line_without_points_line_and_write_checks(tmp_path):
    """An images.txt whose last image line has no POINTS2D line after it loads (no points);
    write_model refuses observation pixels that do not match the point ids."""
    _colmap_capture(tmp_path, _object_cameras(3), text=True)
    p = tmp_path / "sparse" / "0" / "images.txt"
    p.write_text(p.read_text().rstrip("\n") + "\n")  # the last (empty) POINTS2D line dropped
    cams, ims, _ = read_model(tmp_path / "sparse" / "0")
    assert len(ims) == 3 and all(len(im.point3d_ids) == 0 for im in ims.values())
    ims[1].point3d_ids, ims[1].xys = np.array([1, 2]), np.zeros((3, 2))
    with pytest.raises(ValueError, match="xys"):
        write_model(tmp_path / "w", cams, ims)


def test_colmap_text_and_binary_agree_and_bounds_from_points(tmp_path):
    c2w = _object_cameras(6)
    pts = np.array([1.0, -2.0, 0.5]) + np.random.default_rng(2).uniform(-1, 1, (50, 3))
    _colmap_capture(tmp_path / "b", c2w, points=pts)
    _colmap_capture(tmp_path / "t", c2w, points=pts, text=True)
    cb, ib, pb = read_model(tmp_path / "b" / "sparse" / "0")
    ct, it, pt = read_model(tmp_path / "t" / "sparse" / "0")
    assert np.allclose(pb["xyz"], pt["xyz"]) and list(pb["ids"]) == list(pt["ids"])
    for i in ib:
        assert np.allclose(ib[i].qvec, it[i].qvec) and np.allclose(ib[i].tvec, it[i].tvec)
    a = capture_info(tmp_path / "b", holdout=0)
    b = capture_info(tmp_path / "t", holdout=0)
    assert a["near"] == pytest.approx(b["near"]) and a["far"] == pytest.approx(b["far"])
    # near/far bracket every point's depth from every camera (normalised units)
    s = a["scale"]
    dist = np.linalg.norm(pts[None] - c2w[:, None, :3, 3], axis=-1)
    assert a["near"] <= dist.min() * s and a["far"] >= 0.9 * dist.max() * s
    assert a["forward_facing"] is False and a["points"] == 50


def test_llff_and_colmap_agree_on_the_same_capture(tmp_path):
    """The beer-style case: an LLFF poses_bounds.npy made from the COLMAP model loads to the
    same normalised cameras and intrinsics."""
    c2w = _object_cameras(9)
    _colmap_capture(tmp_path, c2w, "SIMPLE_PINHOLE", [20.0, W / 2, H / 2])
    _llff_capture(tmp_path, c2w, 20.0, [2.0, 9.0], folder="unused")
    col = load_dataset(tmp_path, "val", fmt="colmap")
    llff = load_dataset(tmp_path, "val", fmt="llff")
    assert torch.allclose(col["c2w"], llff["c2w"], atol=1e-5)
    assert torch.allclose(col["intrinsics"], llff["intrinsics"])
    assert np.allclose(col["transform"], llff["transform"])
    assert load_dataset(tmp_path, "train")["format"] == "colmap"  # auto: COLMAP first
    # normalised frame: cameras around the origin at radius ~4, +z = the cameras' up (+y here)
    centres = load_dataset(tmp_path, "train", holdout=0)["c2w"][:, :3, 3]
    assert centres.norm(dim=-1).median() == pytest.approx(4.0, rel=1e-4)
    up = load_dataset(tmp_path, "train", holdout=0)["c2w"][:, :3, 1].mean(0)
    assert up[2] > 0.95 * up.norm()


def test_llff_forward_facing_ndc_and_folders(tmp_path):
    """LLFF axes, focal scaled to the chosen images_N folder, NeRF's recentring and scale, NDC."""
    c2w = _forward_cameras(9)
    full = (W * 4, H * 4)
    _llff_capture(tmp_path, c2w, 80.0, [10.0, 40.0], folder="images_4", size=full)
    _write_images(tmp_path / "images_8", [f"{i:03d}.png" for i in range(9)], (W // 2, H // 2))
    info = capture_info(tmp_path)
    assert info["format"] == "llff" and info["forward_facing"] and info["ndc"]
    assert info["images_folder"].endswith("images_4")  # smallest N when images/ is absent
    assert info["intrinsics"] == [80.0, 80.0, W * 2, H * 2]  # images_4 holds the poses' size
    assert info["splits"] == {"train": 7, "val": 2}
    ds8 = load_dataset(tmp_path, "train", downscale=8)
    assert ds8["width"] == W // 2 and ds8["intrinsics"][0, 0] == pytest.approx(10.0)
    ds = load_dataset(tmp_path, "train", holdout=0)
    assert ds["near"] == pytest.approx(0.9 / 0.75)  # min near scaled to 1 / 0.75, then * 0.9
    # recentred: mean camera looks down -z
    assert torch.allclose(ds["c2w"][:, :3, 2].mean(0), torch.tensor([0.0, 0, 1]), atol=0.02)
    # NDC: points of a world ray map onto the NDC ray; z = -near -> -1, z -> -inf gives 1
    o, d = camera_rays(ds["c2w"][:1].double(), ds["intrinsics"][:1].double(), W * 2, H * 2)
    on, dn = ndc_rays(o, d, ds["ndc"])
    assert torch.allclose(on[:, 2], torch.full_like(on[:, 2], -1.0), atol=1e-9)
    fx, fy, w, h = ds["ndc"]
    for t in (1.0, 3.0, 50.0):
        p = o + t * d
        pn = torch.stack(
            [-2 * fx / w * p[:, 0] / p[:, 2], -2 * fy / h * p[:, 1] / p[:, 2], 1 + 2 / p[:, 2]], -1
        )
        rel = pn - on
        off = rel - (rel * dn).sum(-1, keepdim=True) * dn
        assert off.norm(dim=-1).max() < 1e-9
        back = normalised_to_world(pn.numpy(), np.eye(4), ds["ndc"])
        assert np.allclose(back, p.numpy(), rtol=1e-9, atol=1e-9)


def test_holdout_every_8th_and_configurable(tmp_path):
    c2w = _object_cameras(17)
    _colmap_capture(tmp_path, c2w)
    val = load_dataset(tmp_path, "val")
    assert [p.split("_")[-1] for p in val["paths"]] == ["000.png", "008.png", "016.png"]
    assert len(load_dataset(tmp_path, "train")["paths"]) == 14
    assert len(load_dataset(tmp_path, "test", holdout=4)["paths"]) == 5
    assert len(load_dataset(tmp_path, "train", holdout=0)["paths"]) == 17


def test_cli_data_summary_and_training_on_a_forward_facing_capture(tmp_path, capsys):
    c2w = _forward_cameras(9)
    _llff_capture(tmp_path / "ff", c2w, 20.0, [10.0, 40.0])
    assert main(["data", str(tmp_path / "ff")]) == 0
    info = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert info["format"] == "llff" and info["splits"] == {"train": 7, "val": 2}
    assert info["ndc"] and info["image_size"] == [W, H]
    run = tmp_path / "run"
    args = ["train", "nerf", "--data", str(tmp_path / "ff"), "--out", str(run), "--field", "hash",
            "--iters", "3", "--batch", "64", "--val-every", "3", "--val-images", "1",
            "--hash-levels", "4", "--hash-log2-size", "10", "--grid-res", "16",
            "--quiet"]  # fmt: skip
    assert main(args) == 0
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["scene"]["format"] == "llff" and cfg["scene"]["ndc"] == [20.0, 20.0, W, H]
    assert math.isfinite(json.loads(capsys.readouterr().out.strip().splitlines()[-1])["val_psnr"])
    assert main(["eval", str(run), "--max-images", "1"]) == 0
    capsys.readouterr()
    assert main(["render", str(run), "--frames", "2", "--size", "12x8"]) == 0
    assert (run / "render_spiral" / "rgb_001.png").is_file()
    capsys.readouterr()
    mesh = ["mesh", str(run), "--out", str(tmp_path / "m.ply"), "--resolution", "16",
            "--level", "0.01", "--no-screenshot"]  # fmt: skip
    if main(mesh) == 0:  # a 3-step field may have no surface; when it has, units are the world's
        res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert all(math.isfinite(v) for v in res["bounds_min"] + res["bounds_max"])
        assert res["bounds_min"][2] < -7.5  # world units: beyond the NDC near plane 0.75 * 10


def _bad_model(tmp_path, what):
    c2w = _object_cameras(3)
    _colmap_capture(tmp_path, c2w)
    sp = tmp_path / "sparse" / "0"
    if what == "missing image":
        (tmp_path / "images" / "img_001.png").unlink()
    elif what == "truncated":
        (sp / "images.bin").write_bytes((sp / "images.bin").read_bytes()[:-5])
    elif what == "fisheye":
        data = bytearray((sp / "cameras.bin").read_bytes())
        struct.pack_into("<i", data, 12, 5)  # model id of camera 1 -> OPENCV_FISHEYE
        (sp / "cameras.bin").write_bytes(bytes(data))
    elif what == "size":
        _write_images(tmp_path / "images", ["img_002.png"], (W + 2, H))
    elif what == "camera":
        im = read_model(sp)[1]
        im[2].camera_id = 7
        write_model(sp, read_model(sp)[0], im)


@pytest.mark.parametrize(
    "what,needle",
    [
        ("missing image", "missing"),
        ("truncated", "truncated"),
        ("fisheye", "OPENCV_FISHEYE"),
        ("size", "differs"),
        ("camera", "camera 7"),
    ],
)
def test_colmap_bad_input_is_a_clear_error(tmp_path, what, needle, capsys):
    _bad_model(tmp_path, what)
    assert main(["data", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and "Traceback" not in err and len(err.splitlines()) == 1


@pytest.mark.parametrize(
    "arr,needle",
    [
        (np.zeros((3, 15)), "[N, 17]"),
        (np.full((3, 17), np.nan), "non-finite"),
        (None, "pose rows"),
        ("bounds", "near < far"),
    ],
)
def test_llff_bad_input_is_a_clear_error(tmp_path, arr, needle):
    c2w = _forward_cameras(3)
    _llff_capture(tmp_path, c2w, 20.0, [10.0, 40.0])
    if isinstance(arr, np.ndarray):
        np.save(tmp_path / "poses_bounds.npy", arr)
    elif arr is None:
        (tmp_path / "images" / "001.png").unlink()
    else:
        a = np.load(tmp_path / "poses_bounds.npy")
        a[1, 15:] = [5.0, 1.0]
        np.save(tmp_path / "poses_bounds.npy", a)
    with pytest.raises(UserError, match=needle.replace("[", r"\[").replace("]", r"\]")):
        load_dataset(tmp_path, "train")


def test_image_without_points_and_ndc_on_an_object_capture(tmp_path):
    """An image that sees no sparse point keeps finite bounds (from the others); --ndc on is
    refused for a capture that is not forward-facing; a non-invertible distortion is an error
    at load, not NaN rays."""
    from warpnerf.train.nerf import NeRFConfig

    pts = np.array([0.0, 0.0, -20.0]) + np.random.default_rng(3).uniform(-3, 3, (40, 3))
    _colmap_capture(tmp_path / "ff", _forward_cameras(5), points=pts)
    sp = tmp_path / "ff" / "sparse" / "0"
    cams, ims, _ = read_model(sp)
    ims[3].point3d_ids, ims[3].xys = np.zeros(0, np.int64), np.zeros((0, 2))
    write_model(sp, cams, ims, pts)
    info = capture_info(tmp_path / "ff", holdout=0)
    assert info["forward_facing"] and np.isfinite(info["transform"]).all()
    assert math.isfinite(info["near"]) and math.isfinite(info["far"])
    _colmap_capture(tmp_path / "obj", _object_cameras(5))
    with pytest.raises(UserError, match="forward-facing"):
        resolve_data(NeRFConfig(data=str(tmp_path / "obj"), field="hash", ndc="on"))
    _colmap_capture(tmp_path / "wide", _object_cameras(3), "RADIAL", [8.0, 12.0, 8.0, -0.3, 0.0])
    with pytest.raises(UserError, match="not converge"):
        capture_info(tmp_path / "wide")
