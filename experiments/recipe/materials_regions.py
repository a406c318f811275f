"""Where a materials run's val error lies (issue 44's missed 33.5 dB): each pixel labelled by the
analytic shape its centre ray hits first (the eight spheres, the ground disk, or nothing), then per
shape the share of the pixels, the PSNR over its pixels, the share of the summed squared error and
the image PSNR if that shape's pixels were exact (what a perfect model of it alone would give).

    python experiments/recipe/materials_regions.py EVAL --data ../shared/data/materials
        [--split val] [--json F]

EVAL: a `warpnerf eval` output folder of a materials run (metrics.json and the val_NNN.png
panels, truth | prediction | depth side by side); the cameras come from the data set's
transforms_<split>.json (Blender convention, pixel centres at (i + 0.5, j + 0.5)).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from worst_view_crops import read_panels  # noqa: E402  (the eval PNGs' panels, one reader)

BACKGROUND = "background"
RIM = "disk rim"  # the ground disk's outer band (hit radius > RIM_FROM): its edge seen edge-on
RIM_FROM = 1.45


def pixel_rays(c2w, angle_x: float, width: int, height: int):
    """Origins and unit directions [H * W, 3] (float64 numpy) through the pixels' centres, rows
    first: the library's camera rays (:func:`warpnerf.data.cameras.camera_rays`) of a Blender
    camera (focal from ``camera_angle_x``, principal point at the centre). The kernel runs on
    the GPU where there is one (the GPU machines' Warp ships without its CPU compiler)."""
    import torch

    from warpnerf.data.cameras import camera_rays

    dev = "cuda" if torch.cuda.is_available() else "cpu"
    focal = 0.5 * width / math.tan(0.5 * angle_x)
    intr = torch.tensor(
        [[focal, focal, 0.5 * width, 0.5 * height]], dtype=torch.float32, device=dev
    )
    c2w = torch.as_tensor(np.asarray(c2w), dtype=torch.float32, device=dev)[None]
    o, d = camera_rays(c2w, intr, width, height)
    o, d = o.cpu(), d.cpu().double()
    d = d / d.norm(dim=-1, keepdim=True)
    return o.double().numpy(), d.numpy()


def pixel_labels(c2w, angle_x: float, width: int, height: int) -> np.ndarray:
    """[H, W] index into ``names()`` of the shape each pixel's centre ray hits first (the disk's
    outer band its own label; the last index: nothing)."""
    import torch

    from warpnerf.data.materials_truth import MATERIALS_NAMES, materials_depth, materials_shape_ids

    o, d = pixel_rays(c2w, angle_x, width, height)
    t = materials_depth(torch.from_numpy(np.ascontiguousarray(o)), torch.from_numpy(d)).numpy()
    hit = np.isfinite(t)
    lab = np.empty(t.shape, dtype=np.int64)
    p = o[hit] + t[hit, None] * d[hit]
    ids = materials_shape_ids(p)
    ids[(ids == len(MATERIALS_NAMES) - 1) & (np.hypot(p[:, 0], p[:, 1]) > RIM_FROM)] = (
        len(names()) - 2
    )
    lab[hit] = ids
    lab[~hit] = len(names()) - 1
    return lab.reshape(height, width)


def names() -> list:
    from warpnerf.data.materials_truth import MATERIALS_NAMES

    return [*MATERIALS_NAMES, RIM, BACKGROUND]


def noise_residual(img: np.ndarray, lab: np.ndarray):
    """(squared residual [n], label [n]) of the pixels whose 3x3 neighbourhood lies on one shape:
    the pixel minus the mean of its 8 neighbours, squared and averaged over RGB, times 8/9. For
    independent noise of variance s^2 on a locally flat image its mean is s^2 (the path tracer's
    noise, which no model of the scene can predict); shading that varies within 3 pixels adds to
    it, so it bounds the noise from above."""
    h, w = lab.shape
    nb = np.zeros_like(img[1:-1, 1:-1])
    same = np.ones((h - 2, w - 2), dtype=bool)
    c = lab[1:-1, 1:-1]
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                nb += img[1 + dy : h - 1 + dy, 1 + dx : w - 1 + dx]
                same &= lab[1 + dy : h - 1 + dy, 1 + dx : w - 1 + dx] == c
    r = ((img[1:-1, 1:-1] - nb / 8.0) ** 2).mean(-1) * (8.0 / 9.0)
    return r[same], c[same]


def regions(eval_dir: Path, data: Path, split: str = "val") -> dict:
    """Per-shape figures over every view of ``split`` that ``eval_dir`` holds."""
    meta = json.loads((data / f"transforms_{split}.json").read_text())
    angle, frames = float(meta["camera_angle_x"]), meta["frames"]
    k = len(names())
    sq, count, pixels, views = np.zeros(k), np.zeros(k), 0, 0
    noise, noise_n = np.zeros(k), np.zeros(k)
    for i, frame in enumerate(frames):
        if not (eval_dir / f"{split}_{i:03d}.png").exists():
            continue
        gt, pred = read_panels(eval_dir, i, split)
        gt, pred = gt.astype(np.float64), pred.astype(np.float64)
        h, w = gt.shape[:2]
        lab = pixel_labels(frame["transform_matrix"], angle, w, h).reshape(-1)
        err = ((pred - gt) ** 2).mean(-1).reshape(-1)  # (the mean over RGB, as eval's PSNR)
        sq += np.bincount(lab, weights=err, minlength=k)
        r, rl = noise_residual(gt, lab.reshape(h, w))
        noise += np.bincount(rl, weights=r, minlength=k)
        noise_n += np.bincount(rl, minlength=k)
        count += np.bincount(lab, minlength=k)
        pixels, views = pixels + lab.size, views + 1
    if not views:
        raise SystemExit(f"{eval_dir}: no {split}_NNN.png of the split's views")
    total = sq.sum()
    rows = []
    for s, name in enumerate(names()):
        mse = sq[s] / count[s] if count[s] else float("nan")
        rest = (total - sq[s]) / pixels
        rows.append({
            "shape": name, "pixel_share": count[s] / pixels,
            "psnr": -10 * math.log10(mse) if count[s] and mse > 0 else float("nan"),
            "error_share": sq[s] / total if total > 0 else 0.0,
            "psnr_if_exact": -10 * math.log10(rest) if rest > 0 else float("inf"),
            "noise_psnr": (-10 * math.log10(noise[s] / noise_n[s])
                           if noise_n[s] and noise[s] > 0 else float("nan")),
        })  # fmt: skip
    return {"eval": str(eval_dir), "split": split, "views": views,
            "psnr_pooled": -10 * math.log10(total / pixels) if total > 0 else float("inf"),
            "rows": rows}  # fmt: skip


def table(res: dict) -> str:
    md = [f"{res['views']} views, pooled PSNR {res['psnr_pooled']:.2f} dB",
          "| shape | pixels | PSNR on it | its truth's noise (bound) | share of the squared error "
          "| image PSNR if it were exact |", "|---|---|---|---|---|---|"]  # fmt: skip
    for r in sorted(res["rows"], key=lambda r: -r["error_share"]):
        md.append(f"| {r['shape']} | {100 * r['pixel_share']:.1f} % | {r['psnr']:.2f} | "
                  f"{r['noise_psnr']:.2f} | "
                  f"{100 * r['error_share']:.1f} % | {r['psnr_if_exact']:.2f} |")  # fmt: skip
    return "\n".join(md)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("eval", type=Path)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    res = regions(a.eval, a.data, a.split)
    if a.json:
        a.json.write_text(json.dumps(res, indent=1))
    print(table(res))
    return res


if __name__ == "__main__":
    main()
