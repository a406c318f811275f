"""Blender / NeRF-synthetic style folders: transforms JSON + images, validated with clear errors.

Also holds the pieces every transforms-JSON loader shares (folder checks, JSON and field
validation, image reading, alpha compositing, area downscaling); the nerfstudio loader
(``nerfstudio.py``) reuses them. Options are checked once by
:class:`~warpnerf.data.dataset.LoadRequest`; the split of a single ``transforms.json`` is the one
hold-out rule (:func:`~warpnerf.data.dataset.holdout_indices`).

Downscaling by an integer ``d`` averages ``d x d`` pixel blocks (area average, after compositing).
When the image size is not a multiple of ``d`` the last rows / columns are cropped first (at the
bottom / right, so pixel coordinates keep their origin): the result is ``(W // d) x (H // d)`` and
the intrinsics are the full-resolution ones divided by ``d``.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch

from ..errors import UserError
from ..json_input import read_json
from ._paths import OPT_IN, outside_reason
from .cameras import check_intrinsics, check_poses
from .dataset import Dataset, LoadRequest, register_format
from .images import read_all, read_image

__all__ = ["load_blender", "find_transforms", "detect_blender", "data_root", "INDEX_FILES"]

_IMAGE_EXTS = (".png", ".jpg", ".jpeg")
_NERFSTUDIO_KEYS = ("fl_x", "w", "h", "camera_model")


def find_transforms(root: Path, split: str) -> Path:
    """``transforms_{split}.json`` if present, else ``transforms.json``; UserError if neither."""
    for name in (f"transforms_{split}.json", "transforms.json"):
        if (root / name).is_file():
            return root / name
    raise UserError(f"{root}: no transforms_{split}.json or transforms.json found")


# a format's own index file, which names its dataset's folder: given instead of the folder
# (``--data lego/transforms_train.json``), it stands for the folder that holds it
INDEX_FILES = ("transforms.json", "transforms_train.json", "transforms_val.json",
               "transforms_test.json", "poses_bounds.npy")  # fmt: skip


def data_root(path) -> Path:
    """The dataset folder ``path`` names: the path itself, or the folder of a format's index
    file given in its place (:data:`INDEX_FILES`: ``DIR/transforms.json`` -> ``DIR``). Any other
    file is a UserError asking for the folder; a path that does not exist comes back as it is
    (the loaders say it is not found). Every loader's folder goes through it."""
    p = Path(path)
    if p.is_file():
        if p.name in INDEX_FILES:
            return p.parent
        raise UserError(
            f"{p}: a file, not a dataset folder; give the dataset's folder (the one holding "
            "transforms*.json, the COLMAP model sparse/0/ or poses_bounds.npy)"
        )
    return p


def check_folder(root) -> Path:
    """``root`` as a Path (an index file: its folder, see :func:`data_root`); UserError unless it
    is a folder whose files can be listed and read."""
    root = data_root(root)
    if not root.is_dir():
        raise UserError(f"{root}: data folder not found")
    if not os.access(root, os.R_OK | os.X_OK):
        raise UserError(f"{root}: data folder not readable (permission denied)")
    return root


def has_nerfstudio_fields(path: Path) -> bool:
    """Whether a ``transforms.json`` carries nerfstudio camera fields (``fl_x``, ``w``, ``h`` or
    ``camera_model``, at the top level or in ``frames[0]``)."""
    js, frames = read_transforms(path)
    return any(k in js or k in frames[0] for k in _NERFSTUDIO_KEYS)


def detect_blender(root: Path, split: str) -> bool:
    """``transforms_{split}.json``, or a ``transforms.json`` with Blender's ``camera_angle_x``
    and no nerfstudio camera fields."""
    if (root / f"transforms_{split}.json").is_file():
        return True
    path = root / "transforms.json"
    return (
        path.is_file()
        and not has_nerfstudio_fields(path)
        and "camera_angle_x" in read_transforms(path)[0]
    )


def read_transforms(path: Path) -> tuple[dict, list]:
    """Parses a transforms file: a JSON object whose 'frames' is a non-empty list of objects."""
    js = read_json(path, "transforms file")
    if not isinstance(js, dict):
        raise UserError(f"{path}: expected a JSON object with 'frames'")
    frames = js.get("frames")
    if not isinstance(frames, list) or not frames or not all(isinstance(f, dict) for f in frames):
        raise UserError(f"{path}: field 'frames' must be a non-empty list of objects")
    return js, frames


def check_number(v, field: str, path, positive: bool = True, integer: bool = False) -> float:
    """``v`` as a float, or UserError naming ``path`` and ``field`` (finite; > 0; integral)."""
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    ok = ok and (not positive or v > 0) and (not integer or float(v).is_integer())
    if not ok:
        what = ("positive " if positive else "") + ("integer" if integer else "number")
        raise UserError(f"{path}: field '{field}' must be a {what}, got {v!r}")
    return float(v)


def _matrix(frame, i, path) -> np.ndarray:
    """frames[i].transform_matrix as a float64 [4, 4] (3x4 accepted) camera-to-world."""
    m = frame.get("transform_matrix")
    try:
        arr = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError):
        arr = None
    if m is None:
        got = "missing"
    elif arr is None:
        got = "not a list of numbers"
    elif arr.shape not in ((4, 4), (3, 4)):
        got = f"shape {list(arr.shape)}"
    elif not np.isfinite(arr).all():
        got = "non-finite values"
    else:
        got = None
    if got is not None:
        raise UserError(
            f"{path}: frames[{i}].transform_matrix must be a finite 4x4 (or 3x4) list "
            f"of numbers (camera-to-world, OpenGL convention); got {got}"
        )
    if arr.shape == (3, 4):
        arr = np.vstack([arr, [0.0, 0.0, 0.0, 1.0]])
    if np.abs(arr[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-4:
        raise UserError(
            f"{path}: frames[{i}].transform_matrix last row must be [0, 0, 0, 1], got "
            f"{arr[3].tolist()} (a transposed matrix?)"
        )
    return arr


def _read_image(root: Path, file_path, i, path, allow_outside=False) -> tuple[np.ndarray, Path]:
    """frames[i].file_path as float32 [H, W, 3|4] in [0, 1]; '.png' tried when no extension.
    The path must stay inside ``root`` (also after symlinks) unless ``allow_outside``."""
    if not isinstance(file_path, str) or not file_path:
        raise UserError(f"{path}: frames[{i}].file_path must be a non-empty string")
    if not allow_outside:
        _confine(root, file_path, None, i, path)
    p = root / file_path
    candidates = [p] if p.suffix.lower() in _IMAGE_EXTS else []
    candidates += [p.with_name(p.name + ext) for ext in _IMAGE_EXTS]
    img_path = next((c for c in candidates if c.is_file()), None)
    if img_path is None:
        raise UserError(
            f"{path}: frames[{i}].file_path: image {p} not found (.png added when "
            "the path has no extension)"
        )
    if not allow_outside:
        _confine(root, file_path, img_path, i, path)
    return read_image(img_path, f"frames[{i}].file_path in {path}"), img_path


def _confine(root: Path, file_path: str, img_path, i, path) -> None:
    why = outside_reason(root, file_path, img_path)
    if why is not None:
        raise UserError(
            f"{path}: frames[{i}].file_path {file_path!r} {why}, outside the dataset folder "
            f"{root} (pass {OPT_IN} to use images outside it)"
        )


def composite_rgba(img: np.ndarray, bg: np.ndarray) -> np.ndarray:
    """RGBA (straight alpha) over ``bg``: rgb * a + bg * (1 - a); RGB passes through."""
    if img.shape[-1] == 4:
        a = img[..., 3:]
        img = img[..., :3] * a + bg * (1.0 - a)
    return img


def area_downscale(img: np.ndarray, d: int) -> np.ndarray:
    """Mean over d x d blocks after cropping the bottom / right to a multiple of d."""
    if d == 1:
        return img
    h, w = img.shape[0] // d, img.shape[1] // d
    return img[: h * d, : w * d].reshape(h, d, w, d, img.shape[-1]).mean((1, 3))


def load_frames(root, path, frames, indices, req: LoadRequest, sizes=None):
    """Reads, validates, composites and downscales frames[indices].

    ``sizes`` (optional): the declared (h, w) of each selected frame, checked against the file.
    Returns images [N, h, w, 3] float32 array, c2w [N, 4, 4] float64 array, paths, (H, W) at
    full resolution.
    """
    mats = [_matrix(frames[i], i, path) for i in indices]
    mats = check_poses(mats, path, lambda j: f"frames[{indices[j]}].transform_matrix")
    bg, downscale = req.bg, req.downscale
    raws = {}  # j -> (the file's (h, w), its path), filled by the reading threads
    alphas = {}  # j -> whether the file has an alpha channel (req.alpha)

    def read_one(j):
        i = indices[j]
        img, ip = _read_image(root, frames[i].get("file_path"), i, path, req.allow_outside)
        raws[j] = (img.shape[:2], ip)
        hw = img.shape[:2]
        if hw[0] < downscale or hw[1] < downscale:  # (checked for the first in order below)
            return img[:0, :0, :3]
        rgb = composite_rgba(img, bg)
        if req.alpha:  # the alpha as a fourth channel (1 without one), split off by make_dataset
            a = img[..., 3:] if img.shape[-1] == 4 else np.ones_like(img[..., :1])
            alphas[j] = img.shape[-1] == 4
            rgb = np.concatenate([rgb, a], -1)
        return area_downscale(rgb, downscale).astype(np.float32)

    first = None

    def check(j, _img):
        nonlocal first
        i = indices[j]
        hw, ip = raws[j]
        if sizes is not None and hw != tuple(sizes[j]):
            raise UserError(
                f"{ip}: image is {hw[1]}x{hw[0]} (w x h) but {path} frames[{i}] expects "
                f"w x h = {sizes[j][1]}x{sizes[j][0]} (fields 'w', 'h')"
            )
        if first is None:
            first = (hw, ip)
            if hw[0] < downscale or hw[1] < downscale:
                raise UserError(
                    f"downscale {downscale} is larger than the image {ip} ({hw[1]}x{hw[0]})"
                )
        elif hw != first[0]:
            raise UserError(
                f"{ip}: size {hw[1]}x{hw[0]} differs from {first[1]}'s {first[0][1]}x"
                f"{first[0][0]} (frames[{i}] in {path}); all images of a split must have one size"
            )

    images = read_all(list(range(len(indices))), read_one, check,
                      dtype=np.uint8 if req.uint8 else np.float32)  # fmt: skip
    paths = [str(raws[j][1]) for j in range(len(indices))]
    if req.alpha and not any(alphas.values()):  # no file has alpha: none to keep
        images = np.ascontiguousarray(images[..., :3])
    return images, mats, paths, first[0]


def make_dataset(req: LoadRequest, images, c2w, intrinsics, paths, fmt: str) -> Dataset:
    """A transforms-JSON loader's arrays as a :class:`Dataset` (``images`` [N, H, W, 4]: the
    last channel is the alpha, see :attr:`Dataset.alpha`)."""
    alpha = None
    if images.shape[-1] == 4:
        alpha = torch.from_numpy(np.ascontiguousarray(images[..., 3]))
        images = images[..., :3]
    return Dataset(
        alpha=alpha,
        images=torch.from_numpy(np.ascontiguousarray(images)),
        c2w=torch.from_numpy(c2w).float(),
        intrinsics=torch.as_tensor(intrinsics, dtype=torch.float32),
        paths=paths,
        format=fmt,
        split=req.split,
    )


def load_blender(root, split: str = "train", **options) -> Dataset:
    """Loads a Blender-format (NeRF-synthetic) folder.

    Reads ``transforms_{split}.json`` (or ``transforms.json``, split by the hold-out rule
    :func:`warpnerf.data.dataset.holdout_indices`): ``camera_angle_x`` (horizontal FOV,
    radians; focal = 0.5 W / tan(0.5 camera_angle_x), principal point at the centre) or
    ``fl_x``/``fl_y`` (+ optional ``cx``/``cy``) in pixels, and ``frames[]`` with ``file_path``
    (no extension: ``.png`` is added; ``.png``/``.jpg`` accepted) and ``transform_matrix``
    (camera-to-world, OpenGL). RGBA images are composited onto ``background``; ``downscale`` is an
    area average (see the module docstring for the crop rule).

    Cameras are checked before any image is read (:func:`warpnerf.data.cameras.check_poses`):
    finite matrices; rotations orthonormal with determinant +1, used as they are up to
    max |R R^T - I| = 1e-4, replaced by the nearest rotation with a UserWarning up to 0.05, and
    refused beyond (degenerate, scaled or mirrored); camera centres within 1e6 of the origin.
    Intrinsics (:func:`~warpnerf.data.cameras.check_intrinsics`): ``camera_angle_x`` in (0, pi),
    focal lengths in (0, 1e8] pixels, field of view below about 179.8 degrees.

    Every ``file_path`` must stay inside ``root``: relative, without ``..``, and resolving
    (through symlinks) inside the folder, unless ``allow_outside=True``
    (``--allow-outside-paths``). Images are read with bounded decoding
    (:func:`warpnerf.data.images.read_image`: PNG or JPEG, size checked from the header, the
    first frame only, colour modes converted to RGB(A)).

    ``options`` are those of :class:`~warpnerf.data.dataset.LoadRequest` (background,
    downscale, max_images, holdout, allow_outside). Returns a
    :class:`~warpnerf.data.dataset.Dataset`.
    """
    return _load(LoadRequest.make(root, split, **options))


def _load(req: LoadRequest) -> Dataset:
    root = check_folder(req.root)
    path = find_transforms(root, req.split)
    js, frames = read_transforms(path)
    if "camera_angle_x" not in js and "fl_x" not in js:
        raise UserError(f"{path}: needs 'camera_angle_x' (radians) or 'fl_x'/'fl_y' (pixels)")
    if path.name == "transforms.json":
        indices = req.select(len(frames), path)
    else:
        indices = list(range(len(frames)))[: req.max_images]
    # Intrinsics are validated before reading any image.
    if "fl_x" in js:
        fx = check_number(js["fl_x"], "fl_x", path)
        fy = check_number(js["fl_y"], "fl_y", path) if "fl_y" in js else fx
    else:
        fov = check_number(js["camera_angle_x"], "camera_angle_x", path)
        if fov >= math.pi:
            raise UserError(f"{path}: field 'camera_angle_x' must be in (0, pi) radians, got {fov}")
    downscale = req.downscale
    images, c2w, paths, (full_h, full_w) = load_frames(root, path, frames, indices, req)
    if "fl_x" in js:
        cx = check_number(js["cx"], "cx", path, positive=False) if "cx" in js else 0.5 * full_w
        cy = check_number(js["cy"], "cy", path, positive=False) if "cy" in js else 0.5 * full_h
    else:
        fx = fy = 0.5 * full_w / math.tan(0.5 * fov)
        cx, cy = 0.5 * full_w, 0.5 * full_h
    fields = "fields 'fl_x', 'fl_y', 'cx', 'cy'" if "fl_x" in js else "field 'camera_angle_x'"
    check_intrinsics([[fx, fy, cx, cy]], (full_w, full_h), path, lambda _: fields)
    k = np.array([fx, fy, cx, cy], dtype=np.float64) / downscale
    return make_dataset(req, images, c2w, np.tile(k, (len(paths), 1)), paths, "blender")


register_format("blender", _load, detect_blender)
