"""Blender / NeRF-synthetic style folders: transforms JSON + images, validated with clear errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from ..errors import UserError

__all__ = ["load_blender", "find_transforms"]


def find_transforms(root: Path, split: str) -> Path:
    for name in (f"transforms_{split}.json", "transforms.json"):
        if (root / name).is_file():
            return root / name
    raise UserError(f"{root}: no transforms_{split}.json or transforms.json found")


def _number(js, key, path, positive=True):
    v = js.get(key)
    if (
        not isinstance(v, (int, float))
        or isinstance(v, bool)
        or not math.isfinite(v)
        or (positive and v <= 0)
    ):
        raise UserError(
            f"{path}: field '{key}' must be a {'positive ' if positive else ''}number, got {v!r}"
        )
    return float(v)


def _matrix(frame, i, path):
    m = frame.get("transform_matrix")
    try:
        arr = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape not in ((4, 4), (3, 4)) or not np.isfinite(arr).all():
        raise UserError(
            f"{path}: frames[{i}].transform_matrix must be a finite 4x4 (or 3x4) list "
            "of numbers (camera-to-world, OpenGL convention)"
        )
    if arr.shape == (3, 4):
        arr = np.vstack([arr, [0.0, 0.0, 0.0, 1.0]])
    return arr


def _read_image(root: Path, file_path, i, path):
    if not isinstance(file_path, str) or not file_path:
        raise UserError(f"{path}: frames[{i}].file_path must be a non-empty string")
    p = root / file_path
    candidates = [p] if p.suffix.lower() in (".png", ".jpg", ".jpeg") else []
    candidates += [p.with_name(p.name + ext) for ext in (".png", ".jpg", ".jpeg")]
    img_path = next((c for c in candidates if c.is_file()), None)
    if img_path is None:
        raise UserError(
            f"{path}: frames[{i}].file_path: image {p} not found (.png added when "
            "the path has no extension)"
        )
    import imageio.v3 as iio

    try:
        img = np.asarray(iio.imread(img_path))
    except Exception as e:  # imageio raises many types for corrupt files
        raise UserError(f"{img_path}: cannot read image ({e})") from None
    if img.ndim == 2:
        img = img[..., None].repeat(3, -1)
    if img.ndim != 3 or img.shape[-1] not in (3, 4):
        raise UserError(f"{img_path}: expected an RGB or RGBA image, got shape {img.shape}")
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    return img.astype(np.float32) / scale, img_path


def load_blender(
    root,
    split: str = "train",
    background=(1.0, 1.0, 1.0),
    downscale: int = 1,
    max_images: int | None = None,
):
    """Loads a Blender-format folder.

    Reads ``transforms_{split}.json`` (or ``transforms.json``): ``camera_angle_x`` (horizontal FOV,
    radians) or ``fl_x``/``fl_y`` (+ optional ``cx``/``cy``) in pixels, and ``frames[]`` with
    ``file_path`` (extension optional) and ``transform_matrix`` (camera-to-world, OpenGL). RGBA
    images are composited onto ``background``.

    Returns:
        dict with images [N, H, W, 3] float32, c2w [N, 4, 4] float32, intrinsics [N, 4]
        (fx, fy, cx, cy), width, height, paths.
    """
    root = Path(root)
    if not root.is_dir():
        raise UserError(f"{root}: data folder not found")
    path = find_transforms(root, split)
    try:
        js = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise UserError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(js, dict):
        raise UserError(f"{path}: expected a JSON object with 'frames'")
    frames = js.get("frames")
    if not isinstance(frames, list) or not frames or not all(isinstance(f, dict) for f in frames):
        raise UserError(f"{path}: field 'frames' must be a non-empty list of objects")
    if "camera_angle_x" not in js and "fl_x" not in js:
        raise UserError(f"{path}: needs 'camera_angle_x' (radians) or 'fl_x'/'fl_y' (pixels)")
    if downscale < 1 or int(downscale) != downscale:
        raise UserError(f"downscale must be a positive integer, got {downscale}")
    frames = frames[:max_images] if max_images else frames
    bg = np.asarray(background, dtype=np.float32).reshape(-1)
    images, mats, paths = [], [], []
    first = None
    for i, fr in enumerate(frames):
        img, ip = _read_image(root, fr.get("file_path"), i, path)
        first = first or img.shape[:2]
        if img.shape[:2] != first:
            raise UserError(
                f"{ip}: size {img.shape[1]}x{img.shape[0]} differs from the first "
                f"image's {first[1]}x{first[0]}"
            )
        if img.shape[-1] == 4:
            a = img[..., 3:]
            img = img[..., :3] * a + bg * (1.0 - a)
        if downscale > 1:
            h, w = img.shape[0] // downscale * downscale, img.shape[1] // downscale * downscale
            img = img[:h, :w].reshape(h // downscale, downscale, w // downscale, downscale, 3)
            img = img.mean((1, 3))
        images.append(img.astype(np.float32))
        mats.append(_matrix(fr, i, path))
        paths.append(str(ip))
    h, w = images[0].shape[:2]
    full_w, full_h = w * downscale, h * downscale
    if "fl_x" in js:
        fx = _number(js, "fl_x", path)
        fy = _number(js, "fl_y", path) if "fl_y" in js else fx
        cx = _number(js, "cx", path, positive=False) if "cx" in js else 0.5 * full_w
        cy = _number(js, "cy", path, positive=False) if "cy" in js else 0.5 * full_h
    else:
        fov = _number(js, "camera_angle_x", path)
        if fov >= math.pi:
            raise UserError(f"{path}: camera_angle_x must be below pi radians, got {fov}")
        fx = fy = 0.5 * full_w / math.tan(0.5 * fov)
        cx, cy = 0.5 * full_w, 0.5 * full_h
    k = torch.tensor([fx, fy, cx, cy], dtype=torch.float32) / downscale
    return {
        "images": torch.from_numpy(np.stack(images)),
        "c2w": torch.from_numpy(np.stack(mats)).float(),
        "intrinsics": k.expand(len(images), 4).clone(),
        "width": w,
        "height": h,
        "paths": paths,
    }
