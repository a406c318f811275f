"""Tiny generated scenes for tests (no ../shared data needed)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from warpnerf.box_demo import GT_BOX
from warpnerf.data import intrinsics_from_fov, orbit_views
from warpnerf.fields import SDFVolume
from warpnerf.train import BoxFitConfig, render_box_views


def write_box_folder(
    root: Path, n_views=12, size=32, fov=0.7, radius=3.0, name="transforms.json", rgba=True
) -> dict:
    """Renders the reference box into a Blender-format folder (RGBA PNG, alpha = opacity)."""
    import imageio.v3 as iio

    root.mkdir(parents=True, exist_ok=True)
    (root / "train").mkdir(exist_ok=True)
    cfg = BoxFitConfig()
    gt = SDFVolume("box", **GT_BOX)
    cams = orbit_views(n_views, radius=radius)
    k = intrinsics_from_fov(size, size, fov).expand(n_views, 4)
    from warpnerf.render import render_views

    out = render_views(
        cams,
        k,
        size,
        size,
        cfg.near,
        cfg.far,
        gt,
        n_samples=cfg.n_samples,
        mode="alpha",
        background=0.0,
    )
    frames = []
    for i in range(n_views):
        a = out["opacity"][i].clamp(0, 1)
        # Premultiplied colour over black -> straight colour for an RGBA PNG.
        rgb = torch.where(a[..., None] > 1e-6, out["rgb"][i] / a[..., None].clamp_min(1e-6), 0.0)
        img = torch.cat([rgb.clamp(0, 1), a[..., None]], -1) if rgba else out["rgb"][i]
        iio.imwrite(root / "train" / f"r_{i}.png", (img.numpy() * 255 + 0.5).astype(np.uint8))
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": cams[i].tolist()})
    (root / name).write_text(json.dumps({"camera_angle_x": fov, "frames": frames}))
    images, _ = render_box_views(gt, cams, k, size, size, cfg)
    return {"images": images, "c2w": cams, "intrinsics": k}
