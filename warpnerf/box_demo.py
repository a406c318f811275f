"""The main job (``warpnerf demo``): a built-in analytic scene, end to end.

Renders a rainbow box from 24 cameras, recovers the box's center and side lengths from those
images by gradient descent through the Warp compositing kernels, then renders the fitted box along
a spiral (colour and depth video) and scores it on held-out views. Writes images, videos and
``metrics.json`` to the output folder (all atomically).
"""

from __future__ import annotations

import time
from pathlib import Path

import torch

from .data.cameras import intrinsics_from_fov, orbit_views
from .fields.sdf_volume import SDFVolume
from .metrics import psnr
from .outputs import write_image, write_json
from .train.box_fit import (
    SPIRAL_FOV_X,
    SPIRAL_RADIUS,
    BoxFitConfig,
    fit_box,
    render_box_views,
    write_spiral,
)
from .train.provenance import output_provenance

__all__ = ["GT_BOX", "CAMERA_RADIUS", "FOV_X", "run_demo", "write_spiral"]

GT_BOX = {"center": (0.15, -0.1, 0.2), "side_lengths": (1.2, 0.8, 0.6)}
FOV_X = SPIRAL_FOV_X  # radians
CAMERA_RADIUS = SPIRAL_RADIUS


def run_demo(
    out,
    iters: int = 300,
    size: int = 64,
    n_views: int = 24,
    frames: int = 40,
    video_size: int = 128,
    device: str = "cpu",
    progress: bool = True,
    seed: int = 0,
):
    """Runs the main job and returns its metrics (also written to ``out/metrics.json``)."""
    t_start = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    dev = torch.device(device)
    cfg = BoxFitConfig(iters=iters, seed=seed)
    gt = SDFVolume("box", **GT_BOX, beta=cfg.beta).to(dev)
    train_cams = orbit_views(n_views, radius=CAMERA_RADIUS).to(dev)
    val_cams = orbit_views(8, radius=CAMERA_RADIUS, seed=1).to(dev)
    k = intrinsics_from_fov(size, size, FOV_X).to(dev)
    images, _ = render_box_views(gt, train_cams, k.expand(n_views, 4), size, size, cfg)
    fit = fit_box(images, train_cams, k.expand(n_views, 4), cfg, progress=progress)
    volume = fit.pop("volume")
    kv = k.expand(val_cams.shape[0], 4)
    val_gt, _ = render_box_views(gt, val_cams, kv, size, size, cfg)
    val_fit, _ = render_box_views(volume, val_cams, kv, size, size, cfg)
    diff = (val_fit - val_gt).abs().mul(5.0).clamp(0, 1)
    write_image(out / "val_gt_fit_diff.png", torch.cat([val_gt[0], val_fit[0], diff[0]], 1))
    write_image(out / "train_views.png", torch.cat(list(images[:6]), 1))
    write_spiral(volume, out, frames, video_size, cfg)
    center_err = max(abs(a - b) for a, b in zip(fit["center"], GT_BOX["center"]))
    side_err = max(abs(a - b) for a, b in zip(fit["side_lengths"], GT_BOX["side_lengths"]))
    metrics = {
        "task": "fit a rainbow SDF box (center, side lengths) to 24 rendered views",
        "gt": {k_: list(v) for k_, v in GT_BOX.items()},
        "center": fit["center"],
        "side_lengths": fit["side_lengths"],
        "center_max_abs_error": center_err,
        "side_max_abs_error": side_err,
        "val_psnr": psnr(val_fit, val_gt),
        "final_loss": fit["final_loss"],
        "loss_first": fit["losses"][0] if fit["losses"] else None,
        "fit_seconds": fit["seconds"],
        "total_seconds": time.perf_counter() - t_start,
        "device": str(dev),
        "config": cfg.to_dict()
        | {"size": size, "n_views": n_views, "frames": frames, "video_size": video_size},
        "provenance": output_provenance(dev),  # (the software and device, as eval's metrics)
    }
    write_json(out / "metrics.json", metrics)
    return metrics
