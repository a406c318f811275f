"""One entry point for image datasets: detects the folder's format and calls its loader.

Detection, in order:

1. ``transforms_{split}.json`` present: Blender / NeRF-synthetic (``load_blender``).
2. ``transforms.json`` present: nerfstudio (``load_nerfstudio``) when it carries nerfstudio camera
   fields (``fl_x``, ``w``, ``h`` or ``camera_model``, at the top level or in ``frames[0]``),
   else Blender when it has ``camera_angle_x``. A single file has no splits, so both use the
   hold-out rule: val/test = frames ``i % 8 == 0``, train = the others.
3. Otherwise a UserError naming the folder and what was looked for.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import UserError
from .blender import _check_args, _read_json, load_blender
from .nerfstudio import load_nerfstudio

__all__ = ["load_dataset", "detect_format"]

_NERFSTUDIO_KEYS = ("fl_x", "w", "h", "camera_model")


def detect_format(root, split: str = "train") -> str:
    """The format of the folder ``root``: "blender" or "nerfstudio" (see the module docstring)."""
    root = Path(root)
    if not root.is_dir():
        raise UserError(f"{root}: data folder not found")
    if (root / f"transforms_{split}.json").is_file():
        return "blender"
    path = root / "transforms.json"
    if not path.is_file():
        others = sorted(p.name for p in root.glob("transforms_*.json"))
        found = f" (found: {', '.join(others)})" if others else ""
        raise UserError(
            f"{root}: no transforms_{split}.json (Blender) or transforms.json (nerfstudio) "
            f"found{found}"
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
) -> dict:
    """Loads a Blender or nerfstudio folder, whichever ``root`` holds.

    Args:
        root: the dataset folder.
        split: "train", "val" or "test".
        background: RGB that RGBA images are composited onto (white by default).
        downscale: integer area-average factor; sizes not a multiple of it are cropped at the
            bottom / right; intrinsics are divided by it.
        max_images: keep the first ``max_images`` frames of the split.

    Returns:
        dict with images [N, H, W, 3] float32 in [0, 1], c2w [N, 4, 4] float32 (OpenGL
        camera-to-world), intrinsics [N, 4] float32 (fx, fy, cx, cy in pixels of the returned
        images), width, height, paths (list of str), format ("blender" or "nerfstudio").

    Raises:
        UserError: a bad argument or a missing / malformed file; the message names the file and
            the field.
    """
    _check_args(split, background, downscale, max_images)  # before split names a file
    fmt = detect_format(root, split)
    if fmt == "nerfstudio":
        return load_nerfstudio(root, split, background, downscale, max_images)
    return load_blender(root, split, background, downscale, max_images, holdout=True)
