"""Blender loader validation and atomic writers."""

import json
import os

import numpy as np
import pytest

from warpnerf.data import load_blender
from warpnerf.errors import UserError
from warpnerf.outputs import atomic_path, write_json

from ._scene import write_box_folder


@pytest.fixture(scope="module")
def box_folder(tmp_path_factory):
    root = tmp_path_factory.mktemp("boxdata")
    write_box_folder(root, n_views=3, size=16)
    return root


def test_loader_reads_generated_folder(box_folder):
    ds = load_blender(box_folder, holdout=0, background=(0, 0, 0))
    assert ds["images"].shape == (3, 16, 16, 3) and ds["c2w"].shape == (3, 4, 4)
    fx = 0.5 * 16 / np.tan(0.35)
    assert np.allclose(ds["intrinsics"][0].numpy(), [fx, fx, 8, 8], rtol=1e-6)
    white = load_blender(box_folder, holdout=0, background=(1, 1, 1))["images"]
    assert float(white.mean()) > float(ds["images"].mean())  # alpha compositing applied
    half = load_blender(box_folder, holdout=0, downscale=2)
    assert half["images"].shape == (3, 8, 8, 3)
    assert np.allclose(half["intrinsics"][0].numpy(), [fx / 2, fx / 2, 4, 4], rtol=1e-6)


def _write(root, obj):
    root.mkdir(parents=True, exist_ok=True)
    (root / "transforms.json").write_text(obj if isinstance(obj, str) else json.dumps(obj))


@pytest.mark.parametrize(
    "content, needle",
    [
        ("{not json", "not valid JSON"),
        ({"camera_angle_x": 0.5}, "'frames'"),
        (
            {"frames": [{"file_path": "a", "transform_matrix": np.eye(4).tolist()}]},
            "camera_angle_x",
        ),
        (
            {
                "camera_angle_x": -1,
                "frames": [{"file_path": "train/r_0", "transform_matrix": np.eye(4).tolist()}],
            },
            "camera_angle_x",
        ),
        (
            {
                "camera_angle_x": 0.5,
                "frames": [{"file_path": "missing", "transform_matrix": np.eye(4).tolist()}],
            },
            "not found",
        ),
        (
            {
                "camera_angle_x": 0.5,
                "frames": [{"file_path": "train/r_0", "transform_matrix": [[1, 2], [3, 4]]}],
            },
            "frames[0].transform_matrix",
        ),
    ],
)
def test_loader_errors_name_file_and_field(tmp_path, box_folder, content, needle):
    root = tmp_path / "bad"
    (root / "train").mkdir(parents=True)
    (root / "train" / "r_0.png").write_bytes((box_folder / "train" / "r_0.png").read_bytes())
    _write(root, content)
    with pytest.raises(UserError) as e:
        load_blender(root, holdout=0)
    assert needle in str(e.value) and "transforms.json" in str(e.value)


def test_loader_missing_folder_and_corrupt_image(tmp_path):
    with pytest.raises(UserError, match="not found"):
        load_blender(tmp_path / "nope")
    (tmp_path / "img.png").write_bytes(b"not a png")
    _write(
        tmp_path,
        {
            "camera_angle_x": 0.5,
            "frames": [{"file_path": "img.png", "transform_matrix": np.eye(4).tolist()}],
        },
    )
    with pytest.raises(UserError, match="cannot read image"):
        load_blender(tmp_path, holdout=0)


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "m.json"
    write_json(target, {"a": 1})
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            with open(tmp, "w") as f:
                f.write("half")
            raise RuntimeError("crash mid-write")
    assert json.loads(target.read_text()) == {"a": 1}
    assert sorted(os.listdir(tmp_path)) == [".warpnerf-files.json", "m.json"]  # + the manifest
