"""Crops of the worst val views of two NeRF runs, before and after a change (issue 44): for each
view, the window where the "after" run errs most, shown as truth | before | after | |error| of
each (x4), with the view's PSNR of both runs.

    python experiments/recipe/worst_view_crops.py BEFORE_EVAL AFTER_EVAL --out crops.png
        [--views 3] [--window 96] [--labels before,after]

BEFORE_EVAL / AFTER_EVAL: `warpnerf eval` output folders (metrics.json and the val_NNN.png
panels, truth | prediction | depth side by side) of the same split; the views are the AFTER
run's lowest-PSNR ones (only views whose PNG both folders hold).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def read_panels(folder: Path, i: int, split: str = "val"):
    """(truth, prediction) float [H, W, 3] of one eval PNG (three panels side by side)."""
    import imageio.v3 as iio

    img = iio.imread(folder / f"{split}_{i:03d}.png")[..., :3].astype(np.float32) / 255.0
    w = img.shape[1] // 3
    return img[:, :w], img[:, w : 2 * w]


def worst_window(err: np.ndarray, size: int) -> tuple[int, int]:
    """(y, x) of the size x size window with the largest summed error (an integral image)."""
    h, w = err.shape
    size = min(size, h, w)
    c = np.pad(err.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    s = c[size:, size:] - c[:-size, size:] - c[size:, :-size] + c[:-size, :-size]
    y, x = np.unravel_index(int(np.argmax(s)), s.shape)
    return int(y), int(x)


def crops(before: Path, after: Path, views: int, window: int):
    """Rows of [truth, before, after, err before, err after] crops and their captions."""
    metrics_b = json.loads((before / "metrics.json").read_text())
    rows_b = {r["image"]: r["psnr"] for r in metrics_b["per_image"]}
    rows_a = json.loads((after / "metrics.json").read_text())["per_image"]
    have = [r for r in rows_a if (before / f"val_{r['image']:03d}.png").exists()
            and (after / f"val_{r['image']:03d}.png").exists()]  # fmt: skip
    out = []
    for r in sorted(have, key=lambda r: r["psnr"])[:views]:
        i = r["image"]
        gt, pb = read_panels(before, i)
        _, pa = read_panels(after, i)
        ea, eb = np.abs(pa - gt).mean(-1), np.abs(pb - gt).mean(-1)
        y, x = worst_window(ea, window)
        win = (slice(y, y + window), slice(x, x + window))
        grey = [np.repeat(np.clip(4.0 * e[win], 0, 1)[..., None], 3, -1) for e in (eb, ea)]
        tiles = [gt[win], pb[win], pa[win], *grey]
        out.append((tiles, f"val {i}: {rows_b.get(i, float('nan')):.2f} -> {r['psnr']:.2f} dB, "
                           f"window at ({x}, {y})"))  # fmt: skip
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--views", type=int, default=3)
    ap.add_argument("--window", type=int, default=96)
    ap.add_argument("--labels", default="before,after")
    a = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = crops(a.before, a.after, a.views, a.window)
    lb, la = a.labels.split(",")
    heads = ["truth", lb, la, f"|error| x4, {lb}", f"|error| x4, {la}"]
    fig, ax = plt.subplots(len(rows), 5, figsize=(12.5, 2.7 * len(rows)), squeeze=False)
    for k, (tiles, caption) in enumerate(rows):
        for c, t in enumerate(tiles):
            ax[k, c].imshow(t, interpolation="nearest")
            ax[k, c].set_xticks([])
            ax[k, c].set_yticks([])
            if k == 0:
                ax[k, c].set_title(heads[c], fontsize=9)
        ax[k, 0].set_ylabel(caption, fontsize=8)
    fig.tight_layout()
    fig.savefig(a.out, dpi=90)
    for _, caption in rows:
        print(caption)


if __name__ == "__main__":
    main()
