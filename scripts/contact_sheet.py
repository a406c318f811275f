"""Tile PNG frames into one image (device runs return few files: one sheet instead of many).

    python3 scripts/contact_sheet.py OUT.png FRAME.png [FRAME.png ...] [--cols 4] [--every 2]

Frames are decimated by ``--every`` pixels (nearest) and tiled row-major, ``--cols`` per row;
frames of another size than the first are skipped with a message."""

from __future__ import annotations

import argparse
import sys

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("frames", nargs="+")
    ap.add_argument("--cols", type=int, default=4)
    ap.add_argument("--every", type=int, default=2)
    a = ap.parse_args(argv)
    import imageio.v3 as iio

    from warpnerf.outputs import write_image

    tiles = []
    for f in a.frames:
        img = np.asarray(iio.imread(f))
        img = img[..., None].repeat(3, -1) if img.ndim == 2 else img[..., :3]
        img = img[:: a.every, :: a.every]
        if tiles and img.shape != tiles[0].shape:
            print(f"skipped {f}: size {img.shape} differs from {tiles[0].shape}", file=sys.stderr)
            continue
        tiles.append(img.astype(np.uint8))
    cols = max(1, min(a.cols, len(tiles)))
    rows = -(-len(tiles) // cols)
    h, w = tiles[0].shape[:2]
    sheet = np.full((rows * h, cols * w, 3), 255, np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, cols)
        sheet[r * h : (r + 1) * h, c * w : (c + 1) * w] = t
    write_image(a.out, sheet)
    print(f"{a.out}: {len(tiles)} frames, {cols}x{rows}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
