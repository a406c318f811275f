"""Reading a split's images in parallel, into one array."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

__all__ = ["read_all", "to_uint8"]

PROGRESS_FROM = 20  # a progress bar (on a terminal) from this many images on


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Values in [0, 1] as 8-bit (x 255, rounded to nearest; 8-bit sources come back exactly,
    composited RGBA within 0.5 / 255)."""
    return np.rint(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)


def read_all(items: list, read_one, check=None, desc: str = "loading images",
             dtype=np.float32) -> np.ndarray:  # fmt: skip
    """``read_one(item) -> float32 [h, w, 3]`` for every item, run in a thread pool (image
    decoding and resampling release the GIL), returned as one [N, h, w, 3] array of ``dtype``
    (float32, or uint8: :func:`to_uint8` of each image as it arrives, a quarter of the memory
    and no float copy of the split) filled as the images arrive in order (no stacked copy of the
    whole split). ``check(j, image)`` runs
    in order on the loading thread before image j is stored (size checks); the first item that
    fails, in order, raises its error, and the images not yet read are cancelled. A progress bar
    shows on a terminal for larger splits."""
    if not items:
        raise ValueError("read_all needs at least one item")
    workers = max(1, min(8, os.cpu_count() or 1, len(items)))
    bar = None
    if len(items) >= PROGRESS_FROM and os.environ.get("RANK", "0") in ("", "0"):  # (rank 0)
        from tqdm import tqdm

        bar = tqdm(total=len(items), desc=desc, unit="img", leave=False, disable=None)
    out = None
    pool = ThreadPoolExecutor(max_workers=workers)
    try:
        for j, img in enumerate(pool.map(read_one, items)):
            if check is not None:
                check(j, img)
            if out is None:
                out = np.empty((len(items), *img.shape), dtype=dtype)
            elif img.shape != out.shape[1:]:  # (the loaders' checks name the file first)
                raise ValueError(f"image {j} has shape {img.shape}, expected {out.shape[1:]}")
            out[j] = to_uint8(img) if out.dtype == np.uint8 else img
            if bar is not None:
                bar.update(1)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        if bar is not None:
            bar.close()
    return out
