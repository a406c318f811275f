"""One entry point for image datasets: finds the folder's format in the registry
(:mod:`warpnerf.data.dataset`) and calls its loader.

Detection asks the registered formats in order:

1. ``builtin``: the name "builtin" (the rendered scene of :mod:`warpnerf.data.synthetic`).
2. ``blender``: ``transforms_{split}.json``, or a ``transforms.json`` with ``camera_angle_x``
   and no nerfstudio camera fields.
3. ``nerfstudio``: a ``transforms.json`` with nerfstudio camera fields (``fl_x``, ``w``, ``h`` or
   ``camera_model``, at the top level or in ``frames[0]``).
4. ``colmap``: a COLMAP sparse model (``sparse/0``, ``sparse`` or the folder: ``cameras`` +
   ``images``, ``.bin`` or ``.txt``).
5. ``llff``: ``poses_bounds.npy``.
6. Otherwise a UserError naming the folder and what was looked for.

Formats without split files (a single ``transforms.json``, nerfstudio, COLMAP, LLFF) split by the
one hold-out rule, :func:`~warpnerf.data.dataset.holdout_indices`. ``fmt`` forces a format.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import UserError
from . import capture as _capture
from .blender import check_folder, data_root, has_nerfstudio_fields, read_transforms
from .dataset import HOLDOUT, REGISTRY, Dataset, FormatChoices, LoadRequest, is_capture

__all__ = ["load_dataset", "detect_format", "data_summary", "FORMATS"]


FORMATS = FormatChoices()  # --format's choices: "auto" + the registered folder formats, live


def detect_format(root, split: str = "train") -> str:
    """The registry name of the format of ``root`` (see the module docstring)."""
    if str(root) == "builtin" and "builtin" in REGISTRY:
        return "builtin"
    root = check_folder(root)
    for fmt in REGISTRY.values():
        if fmt.detect is not None and fmt.detect(root, split):
            return fmt.name
    path = root / "transforms.json"
    if path.is_file():
        read_transforms(path)  # a malformed file is named first
        if not has_nerfstudio_fields(path):
            raise UserError(
                f"{path}: no camera fields: needs 'camera_angle_x' (Blender) or "
                "'fl_x', 'fl_y', 'cx', 'cy', 'w', 'h' (nerfstudio)"
            )
    others = sorted(p.name for p in root.glob("transforms_*.json"))
    found = f" (found: {', '.join(others)})" if others else ""
    raise UserError(
        f"{root}: no transforms_{split}.json (Blender), transforms.json (nerfstudio), "
        f"COLMAP model (sparse/0/cameras.bin|txt) or poses_bounds.npy (LLFF) found{found}"
    )


def load_dataset(root, split: str = "train", fmt: str = "auto", **options) -> Dataset:
    """Loads one split of a Blender, nerfstudio, COLMAP or LLFF folder (whichever ``root`` holds)
    or of the built-in scene (``root = "builtin"``).

    Args:
        root: the dataset folder, or "builtin".
        split: "train", "val" or "test".
        fmt: "auto" (detect) or a format of ``FORMATS`` / the registry.
        options: those of :class:`~warpnerf.data.dataset.LoadRequest`: ``background`` (RGB that
            RGBA images are composited onto, white by default), ``downscale`` (integer area
            average; sizes not a multiple of it are cropped at the bottom / right; intrinsics
            divided by it), ``max_images`` (the first images of the split), ``holdout`` (every
            ``holdout``-th image is val/test in formats without split files; 0: none),
            ``builtin_size`` and ``device`` (the built-in scene).

    Returns:
        a :class:`~warpnerf.data.dataset.Dataset` (images [N, H, W, 3] float32 in [0, 1], c2w
        [N, 4, 4] OpenGL camera-to-world, intrinsics [N, 4] in pixels of the returned images,
        paths, format; COLMAP/LLFF add distortion, transform, near, far, ndc, indices; see
        :mod:`warpnerf.data.capture`).

    Raises:
        UserError: a bad argument or a missing / malformed file; the message names the file and
            the field.
    """
    req = LoadRequest.make(root, split, **options)  # before split names a file
    if fmt != "auto" and fmt not in REGISTRY:
        raise UserError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    return REGISTRY[detect_format(root, split) if fmt == "auto" else fmt].load(req)


def data_summary(root, fmt: str = "auto", downscale: int = 1, holdout: int = HOLDOUT,
                 allow_outside: bool = False) -> dict:  # fmt: skip
    """What ``warpnerf data`` prints: format, images per split, image size, intrinsics, near/far,
    camera centres' box (and for COLMAP/LLFF the scene transform, NDC use and points' box; for
    COLMAP the reprojection error of the model's observations through the loader's cameras).
    Loading each split validates the files (missing images, sizes, poses); ``allow_outside``:
    images named outside the folder are allowed (``--allow-outside-paths``)."""
    if fmt not in FORMATS:
        raise UserError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    root = Path(root) if str(root) == "builtin" else data_root(root)  # (an index file: its folder)
    fmt = detect_format(root) if fmt == "auto" else fmt
    if is_capture(fmt):
        info = _capture.capture_summary(root, fmt, downscale, holdout, allow_outside)
    else:
        info = {"format": fmt, "splits": {}}
    # the scene a run on it resolves: a folder's own (an exported capture's warpnerf_scene)
    carried = REGISTRY[fmt].scene(root) if REGISTRY[fmt].scene is not None else None
    for split in ("train", "val"):
        try:
            ds = load_dataset(root, split, fmt=fmt, downscale=downscale, holdout=holdout,
                              allow_outside=allow_outside)  # fmt: skip
        except UserError as e:
            if split == "val" and "empty" in str(e):
                info["splits"]["val"] = 0
                continue
            raise
        info["splits"][split] = len(ds)
        if split == "train" and not is_capture(fmt):
            centres = ds.c2w[:, :3, 3]
            # what a run on it resolves (train nerf --near/--far override it): the carried
            # scene's, the data's own range (the built-in scene's), else the NeRF-synthetic 2..6
            near = ds.near if ds.near is not None else 2.0
            far = ds.far if ds.far is not None else 6.0
            info.update(
                image_size=[ds.width, ds.height],
                intrinsics=[round(float(v), 4) for v in ds.intrinsics[0]],
                near=float(near),
                far=float(far),
                camera_centres_box=[
                    [round(float(v), 4) for v in centres.min(0).values],
                    [round(float(v), 4) for v in centres.max(0).values],
                ],
            )
            if carried is not None:
                info.update({k: carried[k] for k in ("near", "far", "aabb", "inner")
                             if k in carried})  # fmt: skip
    return info
