"""Fit an analytic box (center, side lengths) to images by gradient descent through the Warp
compositing path: random ray batches across all images, MSE, Adam."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import torch

from ..fields.sdf_volume import SDFVolume
from ..ops import generate_rays, random_pixels
from ..render import render_rays, render_views

__all__ = ["BoxFitConfig", "fit_box", "render_box_views"]


@dataclass
class BoxFitConfig:
    iters: int = 400
    batch: int = 4096  # rays per step, drawn uniformly across all images
    n_samples: int = 64  # stratified samples per ray (jittered while fitting)
    near: float = 0.0
    far: float = 5.0
    lr: float = 0.02  # Adam, decayed exponentially to lr * lr_final_ratio
    lr_final_ratio: float = 0.1
    beta: float = 0.05
    alpha: float = 1.0
    background: float = 0.0  # black, as the seed's box task
    seed: int = 0

    def to_dict(self):
        return asdict(self)

    def render_kwargs(self) -> dict:
        """The box task's compositing settings for render_rays / render_views."""
        return {"n_samples": self.n_samples, "mode": "alpha", "background": self.background}


def render_box_views(volume, c2w, intrinsics, width, height, cfg: BoxFitConfig):
    """Renders every camera with the box task's settings: rgb [N, H, W, 3], depth [N, H, W]."""
    out = render_views(
        c2w, intrinsics, width, height, cfg.near, cfg.far, volume, **cfg.render_kwargs()
    )
    return out["rgb"], out["depth"]


def fit_box(
    images,
    c2w,
    intrinsics,
    cfg: BoxFitConfig,
    init_center=(0.0, 0.0, 0.0),
    init_sides=(1.0, 1.0, 1.0),
    progress: bool = False,
    log_every: int = 0,
):
    """Optimises a rainbow box's center and side lengths so its renders match ``images``.

    Args:
        images: [N, H, W, 3] ground-truth colours in [0, 1].
        c2w: [N, 4, 4] camera-to-world (OpenGL); intrinsics: [N, 4] (fx, fy, cx, cy).

    Returns:
        dict with center, side_lengths, final_loss (mean of the last 10 steps), losses, seconds,
        and the fitted ``volume``.
    """
    n_img, h, w, _ = images.shape
    volume = SDFVolume(
        "box",
        center=tuple(init_center),
        side_lengths=tuple(init_sides),
        alpha=cfg.alpha,
        beta=cfg.beta,
    ).to(images.device)
    opt = torch.optim.Adam(volume.parameters(), lr=cfg.lr)
    gamma = cfg.lr_final_ratio ** (1.0 / max(cfg.iters, 1))
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma)
    gen = torch.Generator().manual_seed(cfg.seed)
    flat_images = images.reshape(-1, 3)
    losses = []
    t0 = time.perf_counter()
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.iters, desc="fit box", unit="step", leave=False, disable=None)
    for step in range(cfg.iters):
        cam, px, py, flat = random_pixels(
            n_img, w, h, cfg.batch, generator=gen, device=images.device
        )
        o, d = generate_rays(c2w, intrinsics, cam_idx=cam, px=px, py=py)
        out = render_rays(
            o,
            d,
            cfg.near,
            cfg.far,
            volume,
            perturb=True,
            seed=cfg.seed * 100003 + step,
            **cfg.render_kwargs(),
        )
        loss = torch.mean((out["rgb"] - flat_images[flat]) ** 2)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        with torch.no_grad():
            volume.side_lengths.clamp_(min=1e-3)
        losses.append(loss.item())
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{losses[-1]:.2e}")
        if log_every and (step % log_every == 0 or step == cfg.iters - 1):
            c = [round(v, 4) for v in volume.center.tolist()]
            s = [round(v, 4) for v in volume.side_lengths.tolist()]
            print(f"step {step:5d} loss {losses[-1]:.3e} center {c} sides {s}")
    if bar is not None:
        bar.close()
    return {
        "center": volume.center.detach().tolist(),
        "side_lengths": volume.side_lengths.detach().tolist(),
        "final_loss": float(sum(losses[-10:]) / len(losses[-10:])) if losses else float("nan"),
        "losses": losses,
        "seconds": time.perf_counter() - t0,
        "volume": volume,
    }


def run_box_fit_on_folder(
    data, out, cfg: BoxFitConfig, device: str = "cpu", frames: int = 40, progress: bool = False
):
    """The seed's box task on a Blender-format folder: images alpha-composited on black, fits the
    rainbow box, writes ``result.json``, ``config.json`` and (frames > 0) a spiral video of the fit.

    Returns {"center": [x, y, z], "side_lengths": [a, b, c], "final_loss": float}.
    """
    from pathlib import Path

    from ..data.blender import load_blender
    from ..io import write_json

    ds = load_blender(data, split="train", background=(cfg.background,) * 3)
    dev = torch.device(device)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "config.json", cfg.to_dict() | {"data": str(data), "device": device})
    fit = fit_box(
        ds["images"].to(dev), ds["c2w"].to(dev), ds["intrinsics"].to(dev), cfg, progress=progress
    )
    volume = fit.pop("volume")
    result = {k: fit[k] for k in ("center", "side_lengths", "final_loss")}
    write_json(out / "result.json", result | {"seconds": fit["seconds"], "losses": fit["losses"]})
    if frames > 0:
        from ..demo import write_spiral

        write_spiral(volume, out, frames, min(ds["width"], 256), cfg)
    return result
