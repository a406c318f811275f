"""One entry point for image datasets: detects the folder's format and calls its loader.

Detection, in order:

1. ``transforms_{split}.json`` present: Blender / NeRF-synthetic (``load_blender``).
2. ``transforms.json`` present: nerfstudio (``load_nerfstudio``) when it carries nerfstudio camera
   fields (``fl_x``, ``w``, ``h`` or ``camera_model``, at the top level or in ``frames[0]``),
   else Blender when it has ``camera_angle_x``. A single file has no splits, so both use the
   hold-out rule: val/test = frames ``i % 8 == 0``, train = the others.
3. A COLMAP sparse model (``sparse/0``, ``sparse`` or the folder: ``cameras`` + ``images``,
   ``.bin`` or ``.txt``): ``load_capture`` (colmap).
4. ``poses_bounds.npy``: ``load_capture`` (llff).
5. Otherwise a UserError naming the folder and what was looked for.

``fmt`` forces one of ``FORMATS`` instead.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import UserError
from .blender import _check_args, _check_folder, _read_json, load_blender
from .capture import HOLDOUT, detect_capture, load_capture
from .nerfstudio import load_nerfstudio

__all__ = ["load_dataset", "detect_format", "FORMATS"]

FORMATS = ("auto", "blender", "nerfstudio", "colmap", "llff")

_NERFSTUDIO_KEYS = ("fl_x", "w", "h", "camera_model")


def detect_format(root, split: str = "train") -> str:
    """The format of the folder ``root``: "blender", "nerfstudio", "colmap" or "llff" (see the
    module docstring)."""
    root = _check_folder(root)
    if (root / f"transforms_{split}.json").is_file():
        return "blender"
    path = root / "transforms.json"
    if not path.is_file():
        capture = detect_capture(root)
        if capture is not None:
            return capture
        others = sorted(p.name for p in root.glob("transforms_*.json"))
        found = f" (found: {', '.join(others)})" if others else ""
        raise UserError(
            f"{root}: no transforms_{split}.json (Blender), transforms.json (nerfstudio), "
            f"COLMAP model (sparse/0/cameras.bin|txt) or poses_bounds.npy (LLFF) found{found}"
        )
    js, frames = _read_json(path)
    if any(k in js or k in frames[0] for k in _NERFSTUDIO_KEYS):
        return "nerfstudio"
    if "camera_angle_x" in js:
        return "blender"
    raise UserError(
        f"{path}: no camera fields: needs 'camera_angle_x' (Blender) or "
        "'fl_x', 'fl_y', 'cx', 'cy', 'w', 'h' (nerfstudio)"
    )


def load_dataset(
    root,
    split: str = "train",
    background=(1.0, 1.0, 1.0),
    downscale: int = 1,
    max_images: int | None = None,
    fmt: str = "auto",
    holdout: int = HOLDOUT,
) -> dict:
    """Loads a Blender, nerfstudio, COLMAP or LLFF folder, whichever ``root`` holds.

    Args:
        root: the dataset folder.
        split: "train", "val" or "test".
        background: RGB that RGBA images are composited onto (white by default).
        downscale: integer area-average factor; sizes not a multiple of it are cropped at the
            bottom / right; intrinsics are divided by it.
        max_images: keep the first ``max_images`` frames of the split.
        fmt: "auto" (detect) or a format of ``FORMATS``.
        holdout: COLMAP/LLFF: every ``holdout``-th image (sorted names, from the first) is
            val/test, the rest train; 0 = no hold-out (every split is all images).

    Returns:
        dict with images [N, H, W, 3] float32 in [0, 1], c2w [N, 4, 4] float32 (OpenGL
        camera-to-world), intrinsics [N, 4] float32 (fx, fy, cx, cy in pixels of the returned
        images), width, height, paths (list of str), format. COLMAP/LLFF add distortion
        [N, 4] (k1, k2, p1, p2), transform [4, 4] (world -> normalised, float64), near, far,
        ndc (None or the NDC camera (fx, fy, W, H)); see :mod:`warpnerf.data.capture`.

    Raises:
        UserError: a bad argument or a missing / malformed file; the message names the file and
            the field.
    """
    _check_args(split, background, downscale, max_images)  # before split names a file
    if fmt not in FORMATS:
        raise UserError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if fmt == "auto":
        fmt = detect_format(root, split)
    if fmt in ("colmap", "llff"):
        bg = (background,) * 3 if isinstance(background, (int, float)) else background
        return load_capture(root, split, bg, downscale, max_images, fmt, holdout)
    if fmt == "nerfstudio":
        return load_nerfstudio(root, split, background, downscale, max_images)
    return load_blender(root, split, background, downscale, max_images, holdout=True)


def data_summary(root, fmt: str = "auto", downscale: int = 1, holdout: int = HOLDOUT) -> dict:
    """What ``warpnerf data`` prints: format, images per split, image size, intrinsics, near/far,
    camera centres' box (and for COLMAP/LLFF the scene transform, NDC use and points' box).
    Loading each split validates the files (missing images, sizes, poses)."""
    if fmt not in FORMATS:
        raise UserError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    root = Path(root)
    fmt = detect_format(root) if fmt == "auto" else fmt
    if fmt in ("colmap", "llff"):
        from .capture import capture_info

        info = capture_info(root, fmt, downscale, holdout)
    else:
        info = {"format": fmt, "splits": {}}
    for split in ("train", "val"):
        try:
            ds = load_dataset(root, split, downscale=downscale, fmt=fmt, holdout=holdout)
        except UserError as e:
            if split == "val" and "empty" in str(e):
                info["splits"]["val"] = 0
                continue
            raise
        info["splits"][split] = len(ds["paths"])
        if split == "train" and fmt not in ("colmap", "llff"):
            centres = ds["c2w"][:, :3, 3]
            info.update(
                image_size=[ds["width"], ds["height"]],
                intrinsics=[round(float(v), 4) for v in ds["intrinsics"][0]],
                near=2.0,  # the NeRF-synthetic convention (train nerf --near/--far override)
                far=6.0,
                camera_centres_box=[
                    [round(float(v), 4) for v in centres.min(0).values],
                    [round(float(v), 4) for v in centres.max(0).values],
                ],
            )
    return info
