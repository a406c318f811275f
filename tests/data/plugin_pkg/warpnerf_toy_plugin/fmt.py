"""The ``toynpz`` dataset format: a folder holding ``scene.toynpz.npz`` with ``images`` [N, H,
W, 3] uint8, ``c2w`` [N, 4, 4] (OpenGL), ``intrinsics`` [N, 4] and ``near_far`` [2]; every
``holdout``-th image is val/test. The entry point names :func:`register` (a callable)."""

from __future__ import annotations

import numpy as np
import torch

from warpnerf.data import Dataset, register_format
from warpnerf.errors import UserError

FILE = "scene.toynpz.npz"


def detect(root, split) -> bool:
    return (root / FILE).is_file()


def load(req) -> Dataset:
    if req.downscale != 1:
        raise UserError(f"{req.root}: the toynpz format has no --downscale")
    with np.load(req.root / FILE, allow_pickle=False) as z:
        images, c2w, k, nf = z["images"], z["c2w"], z["intrinsics"], z["near_far"]
    idx = req.select(len(images), req.root / FILE)
    images = torch.from_numpy(images[idx])
    if not req.uint8:
        images = images.float() / 255
    return Dataset(images=images, c2w=torch.from_numpy(c2w[idx]).float(),
                   intrinsics=torch.from_numpy(k[idx]).float(), format="toynpz",
                   split=req.split, near=float(nf[0]), far=float(nf[1]))  # fmt: skip


def register() -> None:
    register_format("toynpz", load, detect)
