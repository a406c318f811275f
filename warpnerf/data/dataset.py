"""What every dataset loader returns, what it is asked for, the format registry, and the one
hold-out rule.

- :class:`Dataset`: one split of a scene as tensors (images, cameras, intrinsics, lens distortion,
  near/far, the world -> normalised transform, the NDC camera) plus its names and format.
- :class:`LoadRequest`: the loader options (split, background, downscale, max_images, holdout),
  validated once; every format's loader takes one and nothing else.
- :func:`register_format` / :data:`REGISTRY`: format name -> (detect, load). ``load_dataset``
  (:mod:`warpnerf.data.loading`) asks each registered format, in registration order, whether a
  folder is its kind, then calls its loader. A new format is one module with a ``detect`` and a
  ``load`` plus one ``register_format`` line (docs/ARCHITECTURE.md), as the built-in ones are;
  an outside package's comes through the ``warpnerf.formats`` entry points.
- :func:`holdout_indices`: the split rule of every format without split files (nerfstudio, a
  single ``transforms.json``, COLMAP, LLFF): with ``holdout = k``, images ``i % k == 0`` (file /
  sorted-name order) are val and test, the others train; ``holdout = 0`` puts every image in
  every split.
"""

from __future__ import annotations

import dataclasses
import numbers
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..errors import UserError
from ..plugins import Registry, add_entry

__all__ = [
    "Dataset",
    "LoadRequest",
    "Format",
    "REGISTRY",
    "register_format",
    "is_capture",
    "capture_formats",
    "holdout_indices",
    "HOLDOUT",
    "SPLITS",
]

SPLITS = ("train", "val", "test")
HOLDOUT = 8  # every 8th image is held out (the LLFF convention, also used by nerfstudio)

_TENSORS = ("images", "alpha", "c2w", "intrinsics", "distortion")


@dataclass
class Dataset:
    """One split of a scene.

    Attributes:
        images: [N, H, W, 3] float32 in [0, 1] (RGBA composited onto the requested background),
            or uint8 (the values x 255) when loaded with ``uint8=True``.
        c2w: [N, 4, 4] float32 camera-to-world, OpenGL convention (x right, y up, looking -z).
        intrinsics: [N, 4] float32 (fx, fy, cx, cy) in pixels of the returned images.
        paths: the image files (empty for the built-in scene).
        format: the format's registry name ("blender", "nerfstudio", "colmap", "llff", "builtin").
        split: "train", "val" or "test".
        distortion: [N, 4] (k1, k2, p1, p2) for COLMAP/LLFF, else None.
        transform: [4, 4] float64 world -> normalised frame of a COLMAP/LLFF capture, else None.
        near, far: the scene's depth range when the format knows it, else None.
        ndc: None, or [fx, fy, W, H] of the NDC camera of a forward-facing capture.
        indices: the images' positions in the whole capture (COLMAP/LLFF), else None.
        keypoints: COLMAP captures with sparse points (not NDC): the split's observations of
            them, {"cam" [K] int64, "px", "py" [K] float32 pixels, "xyz" [K, 3] float32
            normalised}, on the CPU; else None.
        alpha: [N, H, W] the images' alpha (same dtype as ``images``: float32 in [0, 1] or
            uint8), area-downscaled like them, when asked for (``LoadRequest.alpha``) and the
            files have an alpha channel; else None. ``images`` stay composited onto the
            request's background ``b``, so the pixel over another background ``c`` is
            ``images + (1 - alpha) * (c - b)`` (exact: compositing and the area average are
            linear).

    Code written against the dict the loaders used to return keeps working: ``ds["images"]``,
    ``ds.get("distortion")``, ``"ndc" in ds`` (true when the value is not None).
    """

    images: torch.Tensor
    c2w: torch.Tensor
    intrinsics: torch.Tensor
    paths: list = field(default_factory=list)
    format: str = "blender"
    split: str = "train"
    distortion: torch.Tensor | None = None
    transform: np.ndarray | None = None
    near: float | None = None
    far: float | None = None
    ndc: list | None = None
    indices: list | None = None
    keypoints: dict | None = None
    alpha: torch.Tensor | None = None

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    def __len__(self) -> int:
        return int(self.images.shape[0])

    def to(self, device, images: bool = True) -> Dataset:
        """The same split with its tensors on ``device`` (self when they are there already);
        ``images=False`` leaves the images where they are (host-resident training images)."""
        moved = {
            k: getattr(self, k).to(device)
            for k in _TENSORS
            if getattr(self, k) is not None
            and getattr(self, k).device != torch.device(device)
            and (images or k not in ("images", "alpha"))
        }
        return dataclasses.replace(self, **moved) if moved else self

    # The mapping view kept for code written against the old dict.
    def keys(self) -> list[str]:
        names = [f.name for f in dataclasses.fields(self)] + ["width", "height"]
        return [k for k in names if getattr(self, k) is not None]

    def __getitem__(self, key: str):
        if key not in self.keys():
            raise KeyError(key)
        return getattr(self, key)

    def __contains__(self, key) -> bool:
        return key in self.keys()

    def get(self, key: str, default=None):
        return self[key] if key in self else default


def _positive_int(v) -> bool:
    return isinstance(v, numbers.Integral) and not isinstance(v, bool) and v >= 1


@dataclass(frozen=True)
class LoadRequest:
    """The options of every loader, validated by :meth:`make`.

    Attributes:
        root: the dataset folder (or "builtin").
        split: "train", "val" or "test".
        background: RGB that RGBA images are composited onto.
        downscale: integer area-average factor; sizes not a multiple of it are cropped at the
            bottom / right; intrinsics are divided by it.
        max_images: keep the first ``max_images`` images of the split (None: all).
        holdout: the hold-out period of :func:`holdout_indices` (0: none) for formats without
            split files.
        builtin_size: image size of the built-in scene.
        device: where the built-in scene is rendered (files are always read to the CPU).
        uint8: images as 8-bit values (x / 255 is the image; a quarter of float32's memory;
            RGBA composites rounded to 1/255), e.g. a large training split kept in host memory.
        allow_outside: let the dataset's files name images outside its folder (absolute paths,
            ``..``, symlinks out of it); refused by default (``--allow-outside-paths``).
        alpha: also return the images' alpha (:attr:`Dataset.alpha`) when the files have one.
    """

    root: Path
    split: str = "train"
    background: tuple = (1.0, 1.0, 1.0)
    downscale: int = 1
    max_images: int | None = None
    holdout: int = HOLDOUT
    builtin_size: int = 48
    device: str = "cpu"
    uint8: bool = False
    allow_outside: bool = False
    alpha: bool = False

    @classmethod
    def make(cls, root, split: str = "train", **options) -> LoadRequest:
        """A validated request; a bad option is a UserError naming it and the expected form."""
        unknown = sorted(set(options) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise TypeError(f"unknown loader option(s): {', '.join(unknown)}")
        req = cls(Path(root), split, **options)
        if req.split not in SPLITS:
            raise UserError(f"split must be one of {', '.join(SPLITS)}, got {req.split!r}")
        if not _positive_int(req.downscale):
            raise UserError(f"downscale must be a positive integer, got {req.downscale!r}")
        if req.max_images is not None and not _positive_int(req.max_images):
            raise UserError(
                f"max_images must be None or a positive integer, got {req.max_images!r}"
            )
        if not isinstance(req.holdout, numbers.Integral) or req.holdout < 0 or req.holdout == 1:
            raise UserError(f"holdout must be 0 (none) or >= 2, got {req.holdout!r}")
        if not isinstance(req.uint8, bool):
            raise UserError(f"uint8 must be True or False, got {req.uint8!r}")
        if not isinstance(req.alpha, bool):
            raise UserError(f"alpha must be True or False, got {req.alpha!r}")
        if not isinstance(req.allow_outside, bool):
            raise UserError(f"allow_outside must be True or False, got {req.allow_outside!r}")
        if not _positive_int(req.builtin_size):
            raise UserError(f"builtin_size must be a positive integer, got {req.builtin_size!r}")
        try:
            bg = np.asarray(req.background, dtype=np.float32).reshape(-1)
        except (TypeError, ValueError):
            bg = np.zeros(0, np.float32)
        if bg.size == 1:
            bg = bg.repeat(3)
        if bg.size != 3 or not np.isfinite(bg).all():
            raise UserError(
                f"background must be 3 finite numbers (RGB in [0, 1]), got {req.background!r}"
            )
        return dataclasses.replace(req, background=tuple(float(v) for v in bg))

    @property
    def bg(self) -> np.ndarray:
        """The background as a float32 [3] array."""
        return np.asarray(self.background, dtype=np.float32)

    def select(self, n: int, where) -> list[int]:
        """The indices of this request's split among ``n`` images in a file without split files
        (the hold-out rule), cut to ``max_images``."""
        return holdout_indices(n, self.split, self.holdout, where)[: self.max_images]


def holdout_indices(n: int, split: str, every: int, where) -> list[int]:
    """The one hold-out rule: ``every = k >= 2``: val/test are the images ``i % k == 0``, train
    the others; ``every = 0``: every split is all ``n`` images. UserError (naming ``where``) when
    the split comes out empty."""
    if every == 0:
        return list(range(n))
    held = split != "train"
    idx = [i for i in range(n) if (i % every == 0) == held]
    if not idx:
        raise UserError(
            f"{where}: split '{split}' is empty: {n} image(s), and with holdout {every} val/test "
            f"are the images i % {every} == 0 and train the others (holdout 0: no hold-out)"
        )
    return idx


@dataclass(frozen=True)
class Format:
    """A dataset format: ``detect(root: Path, split) -> bool`` says whether a folder is of this
    format (None: only chosen by name); ``load(LoadRequest) -> Dataset`` loads one split;
    ``capture``: a posed photo capture (COLMAP, LLFF) whose scene settings (transform, near/far,
    box, NDC) are read from the data (:func:`warpnerf.data.capture.capture_info`); ``folder``:
    a format of data folders, one of ``--format``'s choices (the built-in scene is not);
    ``scene(root) -> dict | None``: scene settings a folder of this format carries itself (a
    capture exported by `warpnerf export cameras`: near, far, aabb in its normalised frame),
    which a run then resolves as a capture's."""

    name: str
    load: Callable[[LoadRequest], Dataset]
    detect: Callable[[Path, str], bool] | None = None
    capture: bool = False
    folder: bool = True
    scene: Callable[[Path], dict | None] | None = None


# The built-in formats register in their own modules (blender.py, nerfstudio.py, capture.py:
# colmap and llff; synthetic.py: the built-in scene), an outside package's through the
# "warpnerf.formats" entry points (warpnerf/plugins.py), loaded when the registry is first read.
REGISTRY: dict[str, Format] = Registry("warpnerf.formats")


def register_format(name: str, load, detect=None, capture: bool = False,
                    folder: bool = True, scene=None) -> Format:  # fmt: skip
    """Adds a format to the registry (detection asks formats in registration order)."""
    fmt = Format(name, load, detect, bool(capture), bool(folder), scene)
    if name == "auto" or not add_entry(REGISTRY, name, fmt):
        raise ValueError(f"format {name!r} is already registered")
    return fmt


def carries_scene(name: str) -> bool:
    """Whether a run's saved scene may name format ``name``: a capture format, or one whose
    folders carry their own scene settings (``Format.scene``)."""
    fmt = REGISTRY.get(name)
    return fmt is not None and (fmt.capture or fmt.scene is not None)


class FormatChoices(Sequence):
    """``--format``'s choices, read from the registry whenever asked: "auto" and every
    registered folder format in detection order (a format registered after import is one too).
    A sequence of names: ``in``, iteration, ``len`` and indexing, as argparse and messages use
    them."""

    def names(self) -> tuple:
        return ("auto",) + tuple(n for n, f in REGISTRY.items() if f.folder)

    def __iter__(self):
        return iter(self.names())

    def __contains__(self, name) -> bool:
        return name in self.names()

    def __len__(self) -> int:
        return len(self.names())

    def __getitem__(self, i):
        return self.names()[i]

    def __repr__(self) -> str:
        return repr(self.names())

    def __eq__(self, other) -> bool:
        return tuple(self) == tuple(other) if isinstance(other, (tuple, list, Sequence)) else False

    def __hash__(self):
        return id(self)

    def __add__(self, other):
        return self.names() + tuple(other)


def is_capture(name: str) -> bool:
    """Whether the registered format ``name`` is a posed photo capture (``Format.capture``)."""
    fmt = REGISTRY.get(name)
    return fmt is not None and fmt.capture


def capture_formats() -> tuple:
    """The names of the registered capture formats."""
    return tuple(n for n, f in REGISTRY.items() if f.capture)
