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

    from warpnerf.outputs import contact_sheet, write_image

    skipped = []
    frames = [np.asarray(iio.imread(f)) for f in a.frames]
    sheet = contact_sheet(frames, a.cols, a.every, skipped)
    for i in skipped:
        print(f"skipped {a.frames[i]}: size differs from {a.frames[0]}'s", file=sys.stderr)
    write_image(a.out, sheet)
    print(f"{a.out}: {len(frames) - len(skipped)} frames")
    return 0


if __name__ == "__main__":
    sys.exit(main())
