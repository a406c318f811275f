"""Datasets, point clouds, scenes and run configs are untrusted (issue 15, classes 6 and 9):
degenerate cameras, malformed COLMAP models, PLY files and JSON are refused with a one-line
UserError naming the file (and the camera, line or field) before anything is allocated for them
or trained on them. Property-based fuzz: random corruptions of valid files either load or raise
UserError, never another exception, a crash or a hang."""

from __future__ import annotations

import json
import math
import struct
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from warpnerf.cli import main
from warpnerf.data import load_dataset
from warpnerf.data.blender import load_blender
from warpnerf.data.colmap import read_model, write_model
from warpnerf.data.nerfstudio import load_nerfstudio
from warpnerf.errors import UserError
from warpnerf.fields.sdf_scene import SDFScene
from warpnerf.json_input import read_json
from warpnerf.mesh import read_ply_points
from warpnerf.train.box_fit import BoxFitConfig
from warpnerf.train.nerf_config import NeRFConfig
from warpnerf.train.sdf import SDFConfig

from .test_capture import _colmap_capture, _object_cameras
from .test_datasets import make_blender, make_nerfstudio

FUZZ = settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)


def _set_matrix(root, i, m):
    path = root / "transforms_train.json"
    js = json.loads(path.read_text())
    js["frames"][i]["transform_matrix"] = m
    path.write_text(json.dumps(js))


def _pose(i=0):
    from warpnerf.data.cameras import look_at

    return look_at((4.0, 1.0 + i, 1.0)).double().numpy()


# ------------------------------------------------------------------------------------ cameras


def _scaled(m):
    m[:3, :3] *= 2
    return m


def _mirrored(m):
    m[:3, 0] *= -1
    return m


def _zeroed(m):
    m[:3, :3] = 0
    return m


def _nan(m):
    m[1, 2] = float("nan")
    return m


def _far(m):
    m[:3, 3] = [1e9, 0, 0]
    return m


@pytest.mark.parametrize(
    "edit,words",
    [
        (_scaled, "not a rotation"),
        (_mirrored, "not a rotation"),
        (_zeroed, "not a rotation"),
        (_nan, "non-finite"),
        (_far, "from the origin"),
    ],
)
def test_degenerate_blender_pose_is_refused(tmp_path, edit, words):
    root = make_blender(tmp_path, n=3)
    _set_matrix(root, 1, edit(_pose(1)).tolist())
    with pytest.raises(UserError, match=words) as e:
        load_blender(root)
    assert "transforms_train.json" in str(e.value) and "frames[1]" in str(e.value)


def test_slightly_off_rotation_is_reorthonormalised_with_a_warning(tmp_path):
    root = make_blender(tmp_path, n=2)
    m = _pose(0)
    m[:3, :3] += 1e-3 * np.random.default_rng(0).normal(size=(3, 3))
    _set_matrix(root, 0, m.tolist())
    with pytest.warns(UserWarning, match="nearest rotation"):
        ds = load_blender(root)
    r = np.asarray(ds["c2w"][0, :3, :3], dtype=np.float64)
    assert np.abs(r @ r.T - np.eye(3)).max() < 1e-5 and np.linalg.det(r) > 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an exact file: no warning
        load_blender(make_blender(tmp_path / "exact", n=2))


@pytest.mark.parametrize("fov", [0.0, -0.5, math.pi, 1e300])
def test_absurd_field_of_view_is_refused(tmp_path, fov):
    root = make_blender(tmp_path, n=2)
    js = json.loads((root / "transforms_train.json").read_text())
    js["camera_angle_x"] = fov
    (root / "transforms_train.json").write_text(json.dumps(js))
    with pytest.raises(UserError, match="camera_angle_x"):
        load_blender(root)


@pytest.mark.parametrize(
    "top,words", [({"fl_x": 1e-4}, "field of view"), ({"fl_y": 0.0}, "fl_y"),
                  ({"w": 10**6}, "w")],
)  # fmt: skip
def test_absurd_nerfstudio_intrinsics_are_refused(tmp_path, top, words):
    root = make_nerfstudio(tmp_path, n=3, top=top)
    with pytest.raises(UserError, match=words):
        load_nerfstudio(root)


def test_cli_refuses_a_degenerate_camera_in_one_line(tmp_path, capsys):
    """Before: a zero rotation trained to NaN and exited 0."""
    root = make_blender(tmp_path, n=3)
    make_blender(tmp_path, n=2, split="val")
    _set_matrix(root, 2, _zeroed(_pose(2)).tolist())
    rc = main(["train", "nerf", "--data", str(root), "--out", str(tmp_path / "r"), "--iters", "2",
               "--quiet"])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "Traceback" not in err and len(err.splitlines()) == 1
    assert "not a rotation" in err and not (tmp_path / "r" / "checkpoint.pt").exists()


# ------------------------------------------------------------------------------------- COLMAP


def _model(tmp_path, text=False, points=True):
    pts = np.random.default_rng(0).normal(size=(5, 3)) if points else None
    _colmap_capture(tmp_path, _object_cameras(3), text=text, points=pts)
    return tmp_path / "sparse" / "0"


def test_duplicate_image_names_are_refused(tmp_path):
    sp = _model(tmp_path)
    cams, ims, pts = read_model(sp)
    ims[2].name = ims[1].name
    write_model(sp, cams, ims)
    with pytest.raises(UserError, match="appears twice"):
        read_model(sp)


def test_image_names_must_stay_inside_the_images_folder(tmp_path):
    sp = _model(tmp_path)
    cams, ims, _ = read_model(sp)
    for name in ("../../etc/passwd", "/abs.png"):
        ims[1].name = name
        write_model(sp, cams, ims)
        with pytest.raises(UserError, match="relative path"):
            read_model(sp)


def test_duplicate_ids_in_text_models_are_refused(tmp_path):
    sp = _model(tmp_path, text=True)
    lines = (sp / "cameras.txt").read_text().splitlines()
    cam = next(x for x in lines if x and not x.startswith("#"))
    (sp / "cameras.txt").write_text("\n".join(lines + [cam]) + "\n")
    with pytest.raises(UserError, match="camera id 1 appears twice"):
        read_model(sp)


@pytest.mark.parametrize("bad", ["nan", "inf", "1e300"])
def test_non_finite_or_absurd_sparse_points_are_refused(tmp_path, bad):
    """Before: a NaN point made a NaN scene box."""
    sp = _model(tmp_path, text=True)
    lines = (sp / "points3D.txt").read_text().splitlines()
    i = next(i for i, x in enumerate(lines) if x and not x.startswith("#"))
    f = lines[i].split()
    f[2] = bad
    lines[i] = " ".join(f)
    (sp / "points3D.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(UserError, match="3D point"):
        read_model(sp)


def test_malformed_text_fields_name_the_line(tmp_path):
    sp = _model(tmp_path, text=True)
    lines = (sp / "images.txt").read_text().splitlines()
    i = next(i for i, x in enumerate(lines) if x and not x.startswith("#"))
    lines[i + 1] = "1.0 2.0 notanid"
    (sp / "images.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(UserError, match=r"images.txt:\d+"):
        read_model(sp)


def test_binary_count_beyond_the_file_is_refused_before_allocating(tmp_path):
    for name in ("points3D.bin", "images.bin", "cameras.bin"):
        sp = _model(tmp_path / name)
        data = bytearray((sp / name).read_bytes())
        struct.pack_into("<Q", data, 0, 2**60)
        (sp / name).write_bytes(bytes(data))
        with pytest.raises(UserError, match="bytes left"):
            read_model(sp)


def _reads_or_refuses(sparse) -> None:
    """A corrupted COLMAP model is read, or refused with a UserError: nothing else escapes."""
    try:
        read_model(sparse)
    except UserError:
        pass


@FUZZ
@given(data=st.data())
def test_fuzz_colmap_binary(tmp_path_factory, data):
    sp = _model(tmp_path_factory.mktemp("cb"))
    name = data.draw(st.sampled_from(["cameras.bin", "images.bin", "points3D.bin"]))
    raw = bytearray((sp / name).read_bytes())
    for _ in range(data.draw(st.integers(1, 6))):
        pos = data.draw(st.integers(0, len(raw) - 1))
        raw[pos] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(raw)))
    (sp / name).write_bytes(bytes(raw[:cut] if data.draw(st.booleans()) else raw))
    _reads_or_refuses(sp)


@FUZZ
@given(data=st.data())
def test_fuzz_colmap_text(tmp_path_factory, data):
    sp = _model(tmp_path_factory.mktemp("ct"), text=True)
    name = data.draw(st.sampled_from(["cameras.txt", "images.txt", "points3D.txt"]))
    words = (sp / name).read_text().split(" ")
    junk = st.sampled_from(["nan", "-1", "0", "1e400", "x", "", "\n", "99999999999999999999",
                            "../a.png", "PINHOLE", "3"])  # fmt: skip
    for _ in range(data.draw(st.integers(1, 4))):
        words[data.draw(st.integers(0, len(words) - 1))] = data.draw(junk)
    (sp / name).write_text(" ".join(words))
    _reads_or_refuses(sp)


@FUZZ
@given(data=st.data())
def test_fuzz_transforms_json(tmp_path_factory, data):
    root = make_blender(tmp_path_factory.mktemp("tj"), n=2, w=4, h=4)
    js = json.loads((root / "transforms_train.json").read_text())
    value = data.draw(
        st.recursive(
            st.none() | st.booleans() | st.floats() | st.integers() | st.text(max_size=5),
            lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=3), c, max_size=3),
            max_leaves=8,
        )
    )
    where = data.draw(st.sampled_from(["top", "frame", "matrix", "row"]))
    if where == "top":
        js[data.draw(st.sampled_from(["camera_angle_x", "frames", "fl_x", "w"]))] = value
    elif where == "frame":
        js["frames"][0][data.draw(st.sampled_from(["file_path", "transform_matrix"]))] = value
    elif where == "matrix":
        js["frames"][1]["transform_matrix"][data.draw(st.integers(0, 3))] = value
    else:
        js["frames"][1]["transform_matrix"][0][data.draw(st.integers(0, 3))] = value
    (root / "transforms_train.json").write_text(json.dumps(js))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            load_dataset(root, "train")
    except UserError:
        pass


# --------------------------------------------------------------------------- JSON, PLY, scenes


def test_json_nesting_size_and_encoding(tmp_path):
    p = tmp_path / "x.json"
    p.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(UserError, match="nested too deeply"):
        read_json(p)
    p.write_bytes(b'{"a": "\xff\xfe"}')
    with pytest.raises(UserError, match="UTF-8"):
        read_json(p)
    p.write_text('{"a": 1}')
    with pytest.raises(UserError, match="larger than"):
        read_json(p, max_bytes=4)
    with pytest.raises(UserError, match="no such file"):
        read_json(tmp_path / "missing.json")


def test_deeply_nested_transforms_and_scene_files(tmp_path):
    deep = '{"frames": ' + "[" * 100_000 + "]" * 100_000 + "}"
    root = make_blender(tmp_path, n=2)
    (root / "transforms_train.json").write_text(deep)
    with pytest.raises(UserError, match="transforms_train.json"):
        load_blender(root)
    (tmp_path / "scene.json").write_text(deep)
    with pytest.raises(UserError, match="scene.json"):
        SDFScene.load(tmp_path / "scene.json")


def _ply(n=4, fmt="binary_little_endian", count=None, body=None):
    head = (f"ply\nformat {fmt} 1.0\nelement vertex {count if count is not None else n}\n"
            "property float x\nproperty float y\nproperty float z\nend_header\n")  # fmt: skip
    pts = np.arange(3 * n, dtype="<f4").reshape(n, 3)
    if body is None:
        body = pts.tobytes() if fmt != "ascii" else "\n".join(
            " ".join(map(str, r)) for r in pts.tolist()).encode() + b"\n"  # fmt: skip
    return head.encode() + body


@pytest.mark.parametrize(
    "content,words",
    [
        (b"PLY?\n", "does not start"),
        (_ply(count=10**12), "vertices of 12 bytes declared"),
        (_ply(count=2**70), "not a count"),
        (_ply(count="-3"), "not a count"),
        (_ply()[:-5], "truncated"),
        (_ply(body=np.array([[0, float("nan"), 0]] * 4, "<f4").tobytes()), "non-finite"),
        (_ply(fmt="ascii", body=b"1 2\n"), "vertices declared|has 2 values"),
        (_ply(fmt="ebcdic"), "format"),
    ],
    ids=["magic", "huge", "too-many-digits", "negative", "truncated", "nan", "ascii-row", "format"],
)
def test_bad_ply_files_are_a_user_error(tmp_path, content, words):
    p = tmp_path / "c.ply"
    p.write_bytes(content)
    with pytest.raises(UserError, match=words) as e:
        read_ply_points(p)
    assert str(p) in str(e.value)


def test_good_ply_files_still_load(tmp_path):
    for fmt in ("binary_little_endian", "ascii"):
        (tmp_path / "c.ply").write_bytes(_ply(fmt=fmt))
        pts, nrm = read_ply_points(tmp_path / "c.ply")
        assert pts.shape == (4, 3) and nrm is None and pts[3, 2] == 11


@FUZZ
@given(data=st.data())
def test_fuzz_ply(tmp_path_factory, data):
    raw = bytearray(_ply(fmt=data.draw(st.sampled_from(["binary_little_endian", "ascii"]))))
    for _ in range(data.draw(st.integers(1, 5))):
        raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
    p = tmp_path_factory.mktemp("ply") / "f.ply"
    p.write_bytes(bytes(raw[: data.draw(st.integers(0, len(raw)))]))
    try:
        read_ply_points(p)
    except UserError:
        pass


# ------------------------------------------------------------------------------------ configs

_JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=6),
    lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=3), c, max_size=3),
    max_leaves=6,
)


@pytest.mark.parametrize(
    "cls,field,value,words",
    [
        (NeRFConfig, "iters", "100", "'iters' must be an integer"),
        (NeRFConfig, "lr", True, "'lr' must be a finite number"),
        (NeRFConfig, "lr", float("nan"), "'lr'"),
        (NeRFConfig, "seed", 2**70, "'seed'"),
        (NeRFConfig, "seed", -1, "seed"),
        (NeRFConfig, "field", "triangle", "field"),
        (NeRFConfig, "near", 3.0, "near"),  # with far 2.0 below
        (NeRFConfig, "nonsense", 1, "unknown field"),
        (SDFConfig, "width", 64.5, "'width'"),
        (SDFConfig, "device", "tpu", "device"),
        (BoxFitConfig, "batch", 0, "batch"),
        (BoxFitConfig, "far", float("inf"), "far"),
    ],
)
def test_config_from_dict_names_the_field(cls, field, value, words):
    d = {field: value}
    if field == "near":
        d["far"] = 2.0
    with pytest.raises(UserError, match=words) as e:
        cls.from_dict(d, "RUN/config.json")
    assert "RUN/config.json" in str(e.value)


@FUZZ
@given(kind=st.sampled_from(["nerf", "sdf", "box"]), data=st.data())
def test_fuzz_config_fields(kind, data):
    cls = {"nerf": NeRFConfig, "sdf": SDFConfig, "box": BoxFitConfig}[kind]
    d = cls().to_dict()
    for k in ("model", "data", "device") if kind == "box" else ():
        d.pop(k, None)
    name = data.draw(st.sampled_from(sorted(d)))
    d[name] = data.draw(_JSON)
    try:
        cfg = cls.from_dict(d, "config.json")
    except UserError:
        return
    assert isinstance(cfg, cls)
