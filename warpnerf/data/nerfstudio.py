"""nerfstudio ``transforms.json`` folders (pinhole cameras), validated with clear errors.

Format: top-level intrinsics ``fl_x, fl_y, cx, cy`` (pixels) and image size ``w, h``, optional
``camera_model`` and distortion ``k1, k2, k3, k4, p1, p2``; ``frames[]`` with ``file_path``
(relative to the folder, with extension), ``transform_matrix`` (camera-to-world, OpenGL convention,
as nerfstudio stores it) and optional per-frame overrides of any intrinsic, size, distortion or
camera-model field. Only undistorted pinhole cameras are loaded: ``camera_model`` absent,
``"PINHOLE"`` or ``"OPENCV"`` with every distortion coefficient absent or zero.

Cameras are checked as the Blender loader checks them (:func:`warpnerf.data.cameras.check_poses`,
:func:`~warpnerf.data.cameras.check_intrinsics`): every frame's intrinsics and size (at most
65536 pixels a side, focal lengths in (0, 1e8] pixels, field of view below about 179.8 degrees)
before any image is read; the selected frames' poses finite, with rotations within 1e-4 of
orthonormal used as they are, within 0.05 replaced by the nearest rotation (a UserWarning), and
refused otherwise (degenerate, scaled, mirrored); camera centres within 1e6 of the origin.
Every ``file_path`` must stay inside the folder (also through symlinks) unless
``allow_outside=True`` (``--allow-outside-paths``), as in the Blender loader.

Split rule (nerfstudio folders have no split files): when every frame names its ``split``
("train", "val" or "test"; what `warpnerf export cameras` writes), a split is those frames
(``test``, when no frame is named so, is ``val``); otherwise the one hold-out rule
(:func:`~warpnerf.data.dataset.holdout_indices`) in the order of ``frames``: by default ``val``
and ``test`` are the frames with index ``i % 8 == 0`` and ``train`` all the others.

A folder exported from a COLMAP/LLFF run (not NDC) carries the run's scene settings in
``warpnerf_scene`` (near, far, aabb and the contracted scene's inner cube, in the normalised
frame its poses are in): a run on it resolves them as a capture's (:func:`exported_scene`), so it
trains as the capture it came from.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import UserError
from .blender import (
    check_folder,
    check_number,
    has_nerfstudio_fields,
    load_frames,
    make_dataset,
    read_transforms,
)
from .cameras import check_intrinsics, scene_bounds_problem
from .dataset import Dataset, LoadRequest, register_format

__all__ = ["load_nerfstudio", "detect_nerfstudio", "exported_scene", "CAMERA_MODELS",
           "DISTORTION_FIELDS"]  # fmt: skip

CAMERA_MODELS = ("PINHOLE", "OPENCV")
DISTORTION_FIELDS = ("k1", "k2", "k3", "k4", "p1", "p2")
_REQUIRED = ("fl_x", "fl_y", "cx", "cy", "w", "h")


def _field(js: dict, frame: dict, i: int, key: str):
    """(value, name for messages) of ``key``: the frame's override, else the top-level value."""
    if key in frame:
        return frame[key], f"frames[{i}].{key}"
    return js.get(key), key


def _frame_camera(js: dict, frame: dict, i: int, path) -> tuple[list[float], tuple[int, int]]:
    """([fx, fy, cx, cy], (h, w)) of frames[i] after overrides; rejects non-pinhole cameras."""
    model, name = _field(js, frame, i, "camera_model")
    if model is not None and (not isinstance(model, str) or model.upper() not in CAMERA_MODELS):
        raise UserError(
            f"{path}: field '{name}' = {model!r}: camera model not supported (only PINHOLE, or "
            "OPENCV without distortion; undistort the images first, e.g. with ns-process-data)"
        )
    for key in DISTORTION_FIELDS:
        v, name = _field(js, frame, i, key)
        if v is not None and check_number(v, name, path, positive=False) != 0.0:
            raise UserError(
                f"{path}: field '{name}' = {v!r}: non-zero lens distortion is not supported "
                "(pinhole cameras only); undistort the images first"
            )
    vals = {}
    for key in _REQUIRED:
        v, name = _field(js, frame, i, key)
        if v is None:
            raise UserError(
                f"{path}: field '{key}' missing (needed at the top level or in frames[{i}]; "
                f"nerfstudio format needs {', '.join(_REQUIRED)})"
            )
        positive, integer = key not in ("cx", "cy"), key in ("w", "h")
        vals[key] = check_number(v, name, path, positive=positive, integer=integer)
    k = [vals["fl_x"], vals["fl_y"], vals["cx"], vals["cy"]]
    hw = (int(vals["h"]), int(vals["w"]))
    check_intrinsics([k], hw[::-1], path, lambda _: f"frames[{i}] (fl_x, fl_y, cx, cy, w, h)")
    return k, hw


def detect_nerfstudio(root: Path, split: str) -> bool:
    """A ``transforms.json`` with nerfstudio camera fields (and no ``transforms_{split}.json``)."""
    path = root / "transforms.json"
    return (
        not (root / f"transforms_{split}.json").is_file()
        and path.is_file()
        and has_nerfstudio_fields(path)
    )


def load_nerfstudio(root, split: str = "train", **options) -> Dataset:
    """Loads a nerfstudio folder (``transforms.json``, pinhole cameras; see the module docstring).

    ``options`` are those of :class:`~warpnerf.data.dataset.LoadRequest` (background: RGB that
    RGBA images are composited onto, RGB images are used as they are; downscale; max_images;
    holdout: the split rule). Returns a :class:`~warpnerf.data.dataset.Dataset`.
    """
    return _load(LoadRequest.make(root, split, **options))


def _load(req: LoadRequest) -> Dataset:
    root = check_folder(req.root)
    path = root / "transforms.json"
    if not path.is_file():
        raise UserError(f"{root}: no transforms.json found (nerfstudio format)")
    js, frames = read_transforms(path)
    # Every frame's camera is checked (JSON only, cheap), whichever split is loaded.
    cams = [_frame_camera(js, fr, i, path) for i, fr in enumerate(frames)]
    indices = _split_indices(frames, req, path)
    cams = [cams[i] for i in indices]
    sizes = [hw for _, hw in cams]
    for i, hw in zip(indices, sizes):
        if hw != sizes[0]:
            raise UserError(
                f"{path}: frames[{i}] has w x h = {hw[1]}x{hw[0]} but frames[{indices[0]}] has "
                f"{sizes[0][1]}x{sizes[0][0]} (fields 'w', 'h'); all images of a split must "
                "have one size"
            )
    images, c2w, paths, _ = load_frames(root, path, frames, indices, req, sizes)
    k = np.array([c for c, _ in cams], dtype=np.float64) / req.downscale
    return make_dataset(req, images, c2w, k, paths, "nerfstudio")


SPLITS = ("train", "val", "test")


def _split_indices(frames: list, req: LoadRequest, path) -> list:
    """The frames of the request's split: by their ``split`` fields when every frame has one,
    else by the hold-out rule; cut to ``max_images``."""
    named = [fr.get("split") for fr in frames]
    if not all(isinstance(n, str) and n in SPLITS for n in named):
        if any("split" in fr for fr in frames):
            raise UserError(f"{path}: field 'split' must be one of {', '.join(SPLITS)} in every "
                            "frame, or in none")  # fmt: skip
        return req.select(len(frames), path)
    want = req.split if req.split in named or req.split != "test" else "val"
    idx = [i for i, n in enumerate(named) if n == want]
    if not idx:
        raise UserError(f"{path}: no frame has split '{req.split}'")
    return idx[: req.max_images]


def exported_scene(root) -> dict | None:
    """The scene settings of a folder exported from a capture run (``warpnerf_scene`` in its
    transforms.json: near, far, aabb, optionally inner; the poses are in the normalised frame
    already, so the transform is the identity), or None. UserError for a malformed block."""
    path = Path(root) / "transforms.json"
    if not path.is_file():
        return None
    js, _ = read_transforms(path)
    sc = js.get("warpnerf_scene")
    if sc is None:
        return None
    keys = {"near", "far", "aabb", "inner"}
    if not isinstance(sc, dict) or not {"near", "far", "aabb"} <= set(sc) <= keys:
        raise UserError(f"{path}: field 'warpnerf_scene' must be an object with near, far, aabb "
                        "(and optionally inner)")  # fmt: skip
    vals = {k: check_number(sc[k], f"warpnerf_scene.{k}", path, positive=k != "near") for k in sc}
    problem = scene_bounds_problem(vals["near"], vals["far"], vals["aabb"], vals.get("inner"))
    if problem is not None:  # (the rule of a run's saved scene)
        raise UserError(f"{path}: field 'warpnerf_scene.{problem[0]}' {problem[1]}")
    return {"format": "nerfstudio", "transform": np.eye(4).tolist(), "ndc": None, **vals}


register_format("nerfstudio", _load, detect_nerfstudio, scene=exported_scene)
