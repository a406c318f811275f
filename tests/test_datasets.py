"""Dataset loading: Blender and nerfstudio folders, the dispatcher, split rule and clear errors.

Every dataset here is generated in tmp_path (tiny PNGs + JSON); the last test also reads the real
``../shared/data`` scenes when they are present.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from warpnerf.data import (
    Dataset,
    detect_format,
    holdout_indices,
    load_blender,
    load_dataset,
    load_nerfstudio,
    look_at,
    register_format,
)
from warpnerf.errors import UserError

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
FOV = 0.7


def _c2w(i: int) -> list:
    a = 2 * math.pi * i / 7
    return look_at((4 * math.cos(a), 4 * math.sin(a), 1.0)).double().tolist()


def _png(path: Path, img: np.ndarray) -> None:
    import imageio.v3 as iio

    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, img.astype(np.uint8))


def _pattern(w: int, h: int, i: int, channels: int = 3) -> np.ndarray:
    """A deterministic uint8-valued [h, w, channels] image, different per frame."""
    rng = np.random.default_rng(i)
    img = rng.integers(0, 256, (h, w, channels))
    if channels == 4:
        img[..., 3] = 255
    return img


def make_blender(root: Path, n=3, w=12, h=8, split="train", ext="", rgba=True) -> Path:
    frames = []
    for i in range(n):
        name = f"{split}/r_{i}"
        _png(root / f"{name}.png", _pattern(w, h, i, 4 if rgba else 3))
        frames.append({"file_path": f"./{name}{ext}", "transform_matrix": _c2w(i)})
    js = {"camera_angle_x": FOV, "frames": frames}
    (root / f"transforms_{split}.json").write_text(json.dumps(js))
    return root


def make_nerfstudio(root: Path, n=10, w=12, h=8, top=None, per_frame=None, rgba=False) -> Path:
    """nerfstudio folder with ``n`` RGB frames; ``top`` / ``per_frame[i]`` update the JSON."""
    frames = []
    for i in range(n):
        _png(root / "images" / f"frame_{i:05d}.png", _pattern(w, h, i, 4 if rgba else 3))
        fr = {"file_path": f"images/frame_{i:05d}.png", "transform_matrix": _c2w(i)}
        fr.update((per_frame or {}).get(i, {}))
        frames.append(fr)
    js = {"camera_model": "OPENCV", "fl_x": 10.0, "fl_y": 11.0, "cx": 6.2, "cy": 3.9}
    js.update({"w": w, "h": h, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": frames})
    js.update(top or {})
    js = {k: v for k, v in js.items() if v is not None}  # None in `top` removes a field
    (root / "transforms.json").write_text(json.dumps(js))
    return root


# ------------------------------------------------------------------------------------ Blender


def test_blender_shapes_intrinsics_and_compositing(tmp_path):
    root = make_blender(tmp_path, n=3, w=12, h=8)
    img = np.zeros((8, 12, 4), np.uint8)
    img[..., 0], img[..., 3] = 255, 0  # red, fully transparent ...
    img[0, 0, 3] = 255  # ... except one opaque pixel
    img[0, 1, 3] = 102  # and one at alpha 0.4
    _png(root / "train" / "r_0.png", img)
    ds = load_dataset(root)
    assert ds["format"] == "blender" and ds["width"] == 12 and ds["height"] == 8
    assert ds["images"].shape == (3, 8, 12, 3) and ds["images"].dtype.is_floating_point
    assert ds["c2w"].shape == (3, 4, 4) and ds["intrinsics"].shape == (3, 4)
    assert np.allclose(ds["c2w"][1].numpy(), _c2w(1), atol=1e-6)
    f = 0.5 * 12 / math.tan(0.5 * FOV)
    assert np.allclose(ds["intrinsics"].numpy(), [[f, f, 6.0, 4.0]] * 3, rtol=1e-6)
    assert ds["paths"][2].endswith("r_2.png")
    im = ds["images"][0].numpy()
    assert np.allclose(im[0, 0], [1, 0, 0]) and np.allclose(im[5, 5], [1, 1, 1])
    assert np.allclose(im[0, 1], [1, 0.6, 0.6], atol=1e-6)  # rgb * a + bg * (1 - a)
    black = load_dataset(root, background=(0, 0, 0))["images"][0].numpy()
    assert np.allclose(black[5, 5], 0) and np.allclose(black[0, 1], [0.4, 0, 0], atol=1e-6)
    assert float(ds["images"].min()) >= 0 and float(ds["images"].max()) <= 1


def test_blender_extension_in_file_path_and_val_split(tmp_path):
    make_blender(tmp_path, n=2, split="val", ext=".png", rgba=False)
    ds = load_dataset(tmp_path, split="val")
    assert ds["images"].shape == (2, 8, 12, 3)
    assert np.allclose(ds["images"][1].numpy() * 255, _pattern(12, 8, 1), atol=1e-3)
    with pytest.raises(UserError, match="transforms_train.json"):
        load_dataset(tmp_path, split="train")  # found: transforms_val.json, but no train split


def test_downscale_area_average_crops_and_scales_intrinsics(tmp_path):
    make_blender(tmp_path, n=1, w=10, h=7, rgba=False)
    full = load_dataset(tmp_path)["images"][0].numpy()
    ds = load_dataset(tmp_path, downscale=2)
    assert ds["images"].shape == (1, 3, 5, 3) and (ds["width"], ds["height"]) == (5, 3)
    block = full[2:4, 4:6].mean((0, 1))  # output pixel (1, 2) = mean of its 2x2 block
    assert np.allclose(ds["images"][0, 1, 2].numpy(), block, atol=1e-6)
    f = 0.5 * 10 / math.tan(0.5 * FOV)
    # Intrinsics come from the full 10x7 image (centre 5, 3.5), not from the cropped 10x6.
    assert np.allclose(ds["intrinsics"][0].numpy(), [f / 2, f / 2, 2.5, 1.75], rtol=1e-6)


def test_single_blender_transforms_json_uses_holdout_rule(tmp_path):
    make_blender(tmp_path, n=10)
    (tmp_path / "transforms_train.json").rename(tmp_path / "transforms.json")
    assert len(load_dataset(tmp_path, "train")["paths"]) == 8
    assert [Path(p).name for p in load_dataset(tmp_path, "val")["paths"]] == ["r_0.png", "r_8.png"]
    # one hold-out rule: load_blender splits a single file as load_dataset does; 0 = no hold-out
    assert [Path(p).name for p in load_blender(tmp_path, "val").paths] == ["r_0.png", "r_8.png"]
    assert len(load_blender(tmp_path, "val", holdout=0)) == 10
    assert len(load_dataset(tmp_path, "val", holdout=5).paths) == 2  # r_0, r_5


# --------------------------------------------------------------------------------- nerfstudio


def test_nerfstudio_loads_shapes_intrinsics(tmp_path):
    make_nerfstudio(tmp_path, n=10, w=12, h=8)
    ds = load_dataset(tmp_path)
    assert ds["format"] == "nerfstudio" and (ds["width"], ds["height"]) == (12, 8)
    assert ds["images"].shape == (8, 8, 12, 3) and ds["c2w"].shape == (8, 4, 4)
    assert np.allclose(ds["intrinsics"].numpy(), [[10.0, 11.0, 6.2, 3.9]] * 8, rtol=1e-6)
    assert np.allclose(ds["c2w"][0].numpy(), _c2w(1), atol=1e-6)  # frame 0 is held out
    assert np.allclose(ds["images"][0].numpy() * 255, _pattern(12, 8, 1), atol=1e-3)
    half = load_nerfstudio(tmp_path, downscale=2)
    assert half["images"].shape == (8, 4, 6, 3)
    assert np.allclose(half["intrinsics"][0].numpy(), [5.0, 5.5, 3.1, 1.95], rtol=1e-6)


def test_nerfstudio_rgba_and_pinhole_without_camera_model(tmp_path):
    make_nerfstudio(tmp_path, n=2, rgba=True, top={"camera_model": None, "k1": None})
    img = np.zeros((8, 12, 4), np.uint8)
    _png(tmp_path / "images" / "frame_00000.png", img)  # transparent
    ds = load_dataset(tmp_path, split="val", background=(0.25, 0.5, 0.75))
    assert np.allclose(ds["images"][0].numpy(), [0.25, 0.5, 0.75])
    make_nerfstudio(tmp_path, n=2, top={"camera_model": "PINHOLE"})
    assert load_dataset(tmp_path, split="test")["format"] == "nerfstudio"


def test_nerfstudio_split_rule(tmp_path):
    make_nerfstudio(tmp_path, n=17)
    idx = {
        s: [int(Path(p).stem.split("_")[1]) for p in load_dataset(tmp_path, s)["paths"]]
        for s in ("train", "val", "test")
    }
    assert idx["val"] == idx["test"] == [0, 8, 16]
    assert idx["train"] == [i for i in range(17) if i % 8 != 0]
    assert len(load_dataset(tmp_path, "train", max_images=3)["paths"]) == 3
    make_nerfstudio(tmp_path / "one", n=1)
    with pytest.raises(UserError, match="split 'train' is empty"):
        load_dataset(tmp_path / "one")


def test_nerfstudio_per_frame_overrides(tmp_path):
    per_frame = {
        i: {"fl_x": 20.0 + i, "fl_y": 21.0 + i, "cx": 6.0, "cy": 4.0, "w": 12, "h": 8}
        for i in range(4)
    }
    per_frame[2].update(cx=5.5, k1=0.0, camera_model="PINHOLE")
    top = {k: None for k in ("fl_x", "fl_y", "cx", "cy", "w", "h")}  # all per frame
    make_nerfstudio(tmp_path, n=4, top=top, per_frame=per_frame)
    k = load_dataset(tmp_path)["intrinsics"].numpy()  # frames 1, 2, 3
    assert np.allclose(k, [[21, 22, 6, 4], [22, 23, 5.5, 4], [23, 24, 6, 4]])
    # A frame's override beats the top-level value, also for the image size.
    make_nerfstudio(tmp_path / "b", n=2, top={"w": 99, "h": 99}, per_frame={0: {"w": 12, "h": 8}})
    assert load_dataset(tmp_path / "b", "val")["images"].shape == (1, 8, 12, 3)


# ------------------------------------------------------------------------------------ errors


def _raises(root, *needles, **kw):
    with pytest.raises(UserError) as e:
        load_dataset(root, **kw)
    msg = str(e.value)
    for n in needles:
        assert n in msg, (n, msg)
    return msg


def test_error_missing_folder_and_transforms(tmp_path):
    _raises(tmp_path / "nope", "nope", "not found")
    _raises(tmp_path, str(tmp_path), "transforms_train.json", "transforms.json")
    make_blender(tmp_path / "b", n=1)
    (tmp_path / "b" / "transforms_train.json").unlink()
    with pytest.raises(UserError, match="no transforms.json"):
        load_nerfstudio(tmp_path / "b")


@pytest.mark.parametrize("fmt", ["blender", "nerfstudio"])
def test_error_invalid_json(tmp_path, fmt):
    name = "transforms_train.json" if fmt == "blender" else "transforms.json"
    (tmp_path / name).write_text('{"frames": [}')
    _raises(tmp_path, name, "not valid JSON")


@pytest.mark.parametrize(
    "top, per_frame, field",
    [
        ({"fl_x": None}, None, "'fl_x' missing"),
        ({"h": None}, None, "'h' missing"),
        ({"cy": "3"}, None, "field 'cy' must be a number"),
        ({"w": 12.5}, None, "field 'w' must be a positive integer"),
        ({"fl_y": -1}, None, "field 'fl_y' must be a positive number"),
        ({"frames": []}, None, "field 'frames'"),
        (None, {3: {"transform_matrix": None}}, "frames[3].transform_matrix"),
        (None, {3: {"file_path": None}}, "frames[3].file_path"),
        (None, {3: {"fl_x": 0}}, "field 'frames[3].fl_x' must be a positive number"),
    ],
)
def test_error_nerfstudio_missing_or_invalid_fields(tmp_path, top, per_frame, field):
    pf = {i: {k: v for k, v in d.items() if v is not None} for i, d in (per_frame or {}).items()}
    make_nerfstudio(tmp_path, n=4, top=top, per_frame=pf)
    if per_frame:  # None in per_frame removes the field
        js = json.loads((tmp_path / "transforms.json").read_text())
        for i, d in per_frame.items():
            for k, v in d.items():
                if v is None:
                    del js["frames"][i][k]
        (tmp_path / "transforms.json").write_text(json.dumps(js))
    _raises(tmp_path, "transforms.json", field)


@pytest.mark.parametrize(
    "field, value, needle",
    [
        ("camera_angle_x", None, "camera_angle_x"),
        ("camera_angle_x", 4.0, "camera_angle_x"),
        ("frames", {"a": 1}, "'frames'"),
    ],
)
def test_error_blender_missing_or_invalid_fields(tmp_path, field, value, needle):
    make_blender(tmp_path, n=2)
    path = tmp_path / "transforms_train.json"
    js = json.loads(path.read_text())
    js.pop(field) if value is None else js.update({field: value})
    path.write_text(json.dumps(js))
    _raises(tmp_path, "transforms_train.json", needle)


@pytest.mark.parametrize(
    "matrix, needle",
    [
        ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], "shape [3, 3]"),
        ([1, 2, 3], "shape [3]"),
        ("eye", "not a list of numbers"),
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0]], "not a list of numbers"),
        (np.eye(4).tolist()[:3] + [[1.0, 2.0, 3.0, 1.0]], "last row must be [0, 0, 0, 1]"),
        ([[float("nan")] * 4] * 3 + [[0, 0, 0, 1]], "non-finite"),
    ],
)
@pytest.mark.parametrize("fmt", ["blender", "nerfstudio"])
def test_error_bad_matrix(tmp_path, fmt, matrix, needle):
    if fmt == "blender":
        make_blender(tmp_path, n=3)
        path = tmp_path / "transforms_train.json"
    else:
        make_nerfstudio(tmp_path, n=3)
        path = tmp_path / "transforms.json"
    js = json.loads(path.read_text())
    js["frames"][2]["transform_matrix"] = matrix
    path.write_text(json.dumps(js))  # NaN is written as the (Python-accepted) token NaN
    _raises(tmp_path, path.name, "frames[2].transform_matrix", needle)


def test_error_wrong_and_mixed_image_size(tmp_path):
    make_nerfstudio(tmp_path, n=3)
    _png(tmp_path / "images" / "frame_00002.png", _pattern(10, 8, 0))
    _raises(tmp_path, "frame_00002.png", "transforms.json", "frames[2]", "10x8", "12x8")
    make_nerfstudio(tmp_path, n=3, per_frame={2: {"w": 10}})  # declared sizes differ
    _raises(tmp_path, "transforms.json", "frames[2]", "'w'", "one size")
    make_blender(tmp_path / "b", n=3)
    _png(tmp_path / "b" / "train" / "r_2.png", _pattern(10, 8, 0, 4))
    _raises(tmp_path / "b", "r_2.png", "transforms_train.json", "frames[2]", "one size")


@pytest.mark.parametrize("model", ["OPENCV_FISHEYE", "EQUIRECTANGULAR", "SIMPLE_RADIAL", 3])
def test_error_unknown_camera_model(tmp_path, model):
    make_nerfstudio(tmp_path, n=2, top={"camera_model": model})
    _raises(tmp_path, "transforms.json", "'camera_model'", repr(model), "not supported")


@pytest.mark.parametrize(
    "top, per_frame, field",
    [
        ({"k1": 0.05}, None, "field 'k1' = 0.05"),
        ({"p2": -0.001}, None, "field 'p2' = -0.001"),
        ({"k4": 1e-3, "camera_model": "PINHOLE"}, None, "field 'k4' = 0.001"),
        (None, {1: {"k2": 0.2}}, "field 'frames[1].k2' = 0.2"),
        (None, {1: {"camera_model": "OPENCV_FISHEYE"}}, "'frames[1].camera_model'"),
    ],
)
def test_error_nonzero_distortion(tmp_path, top, per_frame, field):
    make_nerfstudio(tmp_path, n=2, top=top, per_frame=per_frame)
    _raises(tmp_path, "transforms.json", field, "not supported", split="val")
    _raises(tmp_path, "transforms.json", field)


def test_error_image_not_found_and_unreadable(tmp_path):
    make_nerfstudio(tmp_path, n=3)
    (tmp_path / "images" / "frame_00001.png").unlink()
    _raises(tmp_path, "transforms.json", "frames[1].file_path", "frame_00001.png", "not found")
    (tmp_path / "images" / "frame_00001.png").write_bytes(b"not a png")
    _raises(tmp_path, "frame_00001.png", "frames[1].file_path", "cannot read image")


@pytest.mark.parametrize(
    "kw, needle",
    [
        ({"downscale": 0}, "downscale must be a positive integer"),
        ({"downscale": 1.5}, "downscale must be a positive integer"),
        ({"downscale": "2"}, "downscale must be a positive integer"),
        ({"downscale": 9}, "downscale 9 is larger than the image"),
        ({"max_images": 0}, "max_images"),
        ({"split": "training"}, "split must be one of"),
        ({"background": (1, 1)}, "background"),
    ],
)
@pytest.mark.parametrize("fmt", ["blender", "nerfstudio"])
def test_error_bad_arguments(tmp_path, fmt, kw, needle):
    make_blender(tmp_path, n=1) if fmt == "blender" else make_nerfstudio(tmp_path, n=2)
    _raises(tmp_path, needle, **kw)


# ------------------------------------------------- the typed dataset, the registry, one rule


def test_dataset_is_typed_and_keeps_the_dict_view(tmp_path):
    ds = load_dataset(make_nerfstudio(tmp_path, n=10), "val")
    assert isinstance(ds, Dataset) and ds.format == "nerfstudio" and ds.split == "val"
    assert len(ds) == 2 and (ds.height, ds.width) == (8, 12) and ds.images.shape == (2, 8, 12, 3)
    assert ds.distortion is None and ds.near is None and ds.ndc is None
    # code written against the old dict keeps working
    assert ds["images"] is ds.images and ds["width"] == 12 and ds.get("distortion") is None
    assert "images" in ds and "ndc" not in ds and "distortion" not in ds.keys()
    with pytest.raises(KeyError):
        ds["transform"]
    assert ds.to("cpu") is ds  # nothing to move
    assert ds.to(torch.device("cpu")) is ds


@pytest.mark.parametrize("every", [0, 2, 3, 8])
def test_one_holdout_rule_for_every_format_without_split_files(tmp_path, every):
    """A single transforms.json (Blender), nerfstudio and load_dataset split the same frames."""
    blender = make_blender(tmp_path / "b", n=10)
    (blender / "transforms_train.json").rename(blender / "transforms.json")
    ns = make_nerfstudio(tmp_path / "ns", n=10)
    for split in ("train", "val", "test"):
        want = holdout_indices(10, split, every, "x")
        names = [
            [int(Path(p).stem.split("_")[-1]) for p in ds.paths]
            for ds in (
                load_dataset(blender, split, holdout=every),
                load_blender(blender, split, holdout=every),
                load_dataset(ns, split, holdout=every),
                load_nerfstudio(ns, split, holdout=every),
            )
        ]
        assert names == [want] * 4, (split, every)
    held = set(holdout_indices(10, "val", every, "x"))
    assert held == (set(range(10)) if every == 0 else {i for i in range(10) if i % every == 0})


def test_holdout_rule_refuses_bad_periods_and_empty_splits(tmp_path):
    ns = make_nerfstudio(tmp_path, n=3)
    for bad in (1, -1, 2.5):
        with pytest.raises(UserError, match="holdout must be 0"):
            load_dataset(ns, "train", holdout=bad)
    with pytest.raises(UserError, match="split 'val' is empty"):
        holdout_indices(0, "val", 8, "here")
    with pytest.raises(TypeError, match="unknown loader option"):
        load_dataset(ns, "train", bakground=1.0)


def test_a_new_format_is_one_loader_and_one_registry_line(tmp_path, monkeypatch):
    """register_format: detection asks the new format, load_dataset calls its loader."""
    from warpnerf.data import dataset as dataset_mod

    monkeypatch.setattr(dataset_mod, "REGISTRY", dict(dataset_mod.REGISTRY))
    import warpnerf.data.loading as datasets_mod

    monkeypatch.setattr(datasets_mod, "REGISTRY", dataset_mod.REGISTRY)
    seen = []

    def load(req):
        seen.append(req)
        n = 3
        return Dataset(
            images=torch.zeros(n, 4, 5, 3),
            c2w=torch.eye(4).expand(n, 4, 4).clone(),
            intrinsics=torch.tensor([[5.0, 5.0, 2.5, 2.0]]).expand(n, 4).clone(),
            format="toy",
            split=req.split,
        )

    register_format("toy", load, lambda root, split: (root / "scene.toy").is_file())
    (tmp_path / "scene.toy").write_text("")
    assert detect_format(tmp_path) == "toy"
    ds = load_dataset(tmp_path, "val", downscale=2, holdout=0)
    assert ds.format == "toy" and (ds.width, ds.height) == (5, 4)
    assert seen[0].split == "val" and seen[0].downscale == 2 and seen[0].holdout == 0
    with pytest.raises(ValueError, match="already registered"):
        register_format("toy", load)
    # the registry is the only list of formats: --format's choices and the config's check follow
    from warpnerf.cli.parser import build_parser
    from warpnerf.data import FORMATS
    from warpnerf.train.nerf_config import NeRFConfig

    assert "toy" in FORMATS and list(FORMATS)[-1] == "toy" and "builtin" not in FORMATS
    args = build_parser().parse_args(["train", "nerf", "--out", "x", "--format", "toy"])
    assert args.data_format == "toy"
    NeRFConfig(data_format="toy").check_values()


def test_builtin_scene_is_a_registered_format():
    ds = load_dataset("builtin", "val", builtin_size=8, max_images=2)
    assert ds.format == "builtin" and ds.images.shape == (2, 8, 8, 3)
    assert (ds.near, ds.far) == (1.0, 4.0) and ds.paths == []
    assert detect_format("builtin") == "builtin"


# --------------------------------------------------------------------------------- real data


@pytest.mark.parametrize(
    "scene, size, radius", [("lego", 400, 4.0311), ("materials", 200, 4.0)], ids=str
)
def test_real_blender_scenes(scene, size, radius):
    root = SHARED / scene
    if not (root / "transforms_val.json").is_file():
        pytest.skip(f"{root} not present")
    ds = load_dataset(root, "val", downscale=4, max_images=2)
    n = size // 4
    assert ds["format"] == "blender" and ds["images"].shape == (2, n, n, 3)
    f = 0.5 * size / math.tan(0.5 * 0.6911112070083618) / 4
    assert np.allclose(ds["intrinsics"].numpy(), [[f, f, n / 2, n / 2]] * 2, rtol=1e-5)
    im = ds["images"]
    corners = im[:, [0, 0, -1, -1], [0, -1, 0, -1]]  # [2, 4, 3], empty background
    assert float(corners.mean()) > 0.98
    centres = ds["c2w"][:, :3, 3].norm(dim=-1)
    assert np.allclose(centres.numpy(), radius, atol=1e-3)
    # Cameras look at the origin: the -z axis points from the centre towards it.
    fwd = -ds["c2w"][:, :3, 2]
    assert float((fwd * -ds["c2w"][:, :3, 3] / centres[:, None]).sum(-1).min()) > 0.99


def test_capture_formats_are_a_property_of_the_registry():
    """Which formats are posed photo captures (scene settings read from the data) is the
    registry's ``capture`` trait, not a list of names; a saved config's scene must name one."""
    from warpnerf.data.dataset import REGISTRY, capture_formats, is_capture

    assert set(capture_formats()) == {"colmap", "llff"}
    assert is_capture("colmap") and is_capture("llff")
    assert not any(is_capture(n) for n in ("blender", "nerfstudio", "builtin", "auto", "nope"))
    assert all(REGISTRY[n].capture for n in capture_formats())
