"""Evaluation (PSNR/SSIM per image, side-by-side PNGs) and camera-path videos of a NeRF run."""

from __future__ import annotations

import math
import statistics
import time
from pathlib import Path

import torch

from ..data.camera_path import MAX_FRAMES
from ..data.cameras import MAX_DEPTH, camera_rays, camera_target, look_at
from ..errors import UserError, check_fits
from ..io import (
    check_foreign,
    depth_to_uint8,
    make_folder,
    output_lock,
    remove_own,
    to_uint8,
    write_image,
    write_json,
    write_video,
)
from ..metrics import psnr, ssim
from ..ops.bridge import INT32_MAX
from .loop import snapshot_name
from .nerf import (
    CHECKPOINT,
    depth_scale,
    load_data,
    load_run,
    render_dataset_image,
    render_rays_of,
    surface_depth,
    with_refined_poses,
)

__all__ = [
    "sphere_traced_rays_of",
    "evaluate_run",
    "evaluate_geometry",
    "materials_reference",
    "materials_depth",
    "sphere_depth",
    "depth_error",
    "render_run",
    "camera_path",
    "train_and_evaluate",
]

# NeRFConfig fields that only affect rendering, so evaluation may override them, and the ranges
# of the numbers among them (rays at once and sample counts index in int32; a float32 distance)
RENDER_SETTINGS = ("chunk", "march_step", "round_samples", "render_half")
RENDER_RANGES = {"chunk": (1, INT32_MAX), "march_step": (1e-9, MAX_DEPTH),
                 "round_samples": (0, INT32_MAX)}  # fmt: skip
SSIM_SETTINGS = "Gaussian 11x11, sigma 1.5, K1 0.01, K2 0.03, valid region, mean over RGB"


def _depth_image(depth, opacity, scale):
    """The visible surface's depth normalised by ``scale`` (clipped to 1), as RGB uint8."""
    surf = surface_depth(depth, opacity)
    return torch.from_numpy(depth_to_uint8(surf, scale)).unsqueeze(-1).expand(*surf.shape, 3)


RENDERERS = ("volume", "sphere")  # eval / render --renderer: volume rendering, sphere tracing


def _sdf_fields() -> str:
    from ..fields.model import fields_with

    return ", ".join(fields_with(geometry="sdf"))


def _check_renderer(renderer: str, model, cfg) -> None:
    if renderer not in RENDERERS:
        raise UserError(f"--renderer must be one of {', '.join(RENDERERS)}, got {renderer!r}")
    if renderer == "sphere" and model.kind != "sdf":
        raise UserError(f"--renderer sphere needs an SDF run ({_sdf_fields()}), not {cfg.field} "
                        "(a density field has no surface to trace)")  # fmt: skip


def sphere_traced_rays_of(model, cfg, o, d, chunk=None, normals=False, **trace):
    """Renders rays of an SDF run by sphere tracing its field (:func:`warpnerf.render.
    render_sphere_traced`) inside the run's box, hit tolerance 1e-3 box half-sizes unless
    ``trace`` (its keywords) says otherwise; ``chunk`` None: the sphere tracer's own (memory
    grows with rays, not samples)."""
    from ..render import SPHERE_CHUNK, render_sphere_traced

    trace.setdefault("eps", 1e-3 * cfg.aabb)
    return render_sphere_traced(
        model.field, o, d, cfg.near, cfg.far, aabb=cfg.aabb_box(), background=cfg.background,
        normals=normals, chunk=chunk or SPHERE_CHUNK, **trace,
    )  # fmt: skip


def evaluate_run(
    run,
    split: str = "val",
    device: str | None = None,
    max_images: int = 0,
    out_dir=None,
    snapshot: float | None = None,
    renderer: str = "volume",
    progress: bool = False,
    **render,
):
    """Renders every image of ``split``; writes metrics.json and gt | prediction | depth PNGs under
    RUN/eval_{split}/ (or ``out_dir``). Returns the metrics dict; ``render_ms`` is each image's
    rendering time alone (device synchronised before and after; metrics and PNGs excluded).
    ``render`` overrides the run's rendering settings (:data:`RENDER_SETTINGS`: rays at once,
    and for grid runs the marching step, round size, float16 MLPs), e.g. for the
    speed-versus-error sweep. ``snapshot``: the run's snapshot at that many training seconds
    (``train --snapshots``) instead of its last checkpoint. ``renderer="sphere"`` (SDF runs)
    sphere-traces the surface instead (:func:`sphere_traced_rays_of`; default folder
    RUN/eval_{split}_sphere/; metrics add the mean marching steps and hit fraction).
    ``progress``: images done on stderr (:class:`~warpnerf.train.progress.Progress`)."""
    # every number the command takes, before any work (the kernels' limits)
    if split not in ("train", "val", "test"):
        raise UserError(f"--split must be train, val or test, got {split!r}")
    if max_images < 0:
        raise UserError(f"--max-images must be >= 0, got {max_images}")
    for key, value in render.items():
        if key not in RENDER_SETTINGS:
            raise TypeError(f"evaluate_run: unknown rendering setting {key!r}")
        lo, hi = RENDER_RANGES.get(key, (None, None))
        if value is not None and lo is not None and not lo <= value <= hi:
            raise UserError(f"--{key.replace('_', '-')} must be in [{lo:g}, {hi:g}], got {value}")
    cfg, model, ckpt = load_run(run, device, snapshot)
    _check_renderer(renderer, model, cfg)
    grid = model.grid
    for key, value in render.items():
        if value is None:
            continue
        if key != "chunk" and grid is None:
            raise UserError(f"--{key.replace('_', '-')} needs a run with an occupancy grid")
        setattr(cfg, key, type(getattr(cfg, key))(value))
    cfg.check_values()  # (with the run's own: --chunk x samples a ray within int32 offsets)
    if grid is not None:
        grid.dt = cfg.march_step
    ds = load_data(cfg, split, cfg.images_on)  # (large splits stay in host memory)
    ds = with_refined_poses(model, ds, split)
    sub = f"eval_{split}" + ("_sphere" if renderer == "sphere" else "")
    out_dir = Path(out_dir) if out_dir else Path(run) / sub
    n = ds.images.shape[0] if not max_images else min(max_images, ds.images.shape[0])
    if out_dir == Path(run) / sub:  # a folder warpnerf makes in the run: a real one, no link
        make_folder(out_dir, "evaluation folder")
    with output_lock(out_dir, "evaluation folder"):
        names = ["metrics.json"] + [f"{split}_{i:03d}.png" for i in range(n)]
        check_foreign([out_dir / x for x in names])  # another program's files stay untouched
        # a previous, possibly larger, evaluation's images (only those warpnerf wrote)
        remove_own(out_dir, sorted({p.name for p in out_dir.glob(f"{split}_*.png")} - set(names)))
        sphere = (render.get("chunk") or True) if renderer == "sphere" else None
        which = CHECKPOINT if snapshot is None else snapshot_name(float(snapshot))
        return _evaluate(cfg, model, ckpt, grid, ds, split, n, out_dir, sphere, which,
                         progress)  # fmt: skip


def _evaluate(cfg, model, ckpt, grid, ds, split, n, out_dir, sphere=None, which=CHECKPOINT,
              progress=False):  # fmt: skip
    """``sphere``: None (volume rendering), else sphere tracing (the --chunk given, or True);
    ``which``: the checkpoint file evaluated (metrics.json names it, its step, and the software
    and device of the evaluation: :func:`~warpnerf.train.provenance.environment`)."""
    from .nerf import dataset_rays
    from .progress import Progress
    from .provenance import command_now, environment

    with_ssim = min(ds.height, ds.width) >= 11  # the 11x11 window must fit
    rows, t0 = [], time.perf_counter()
    sync = torch.cuda.synchronize if cfg.device.startswith("cuda") else (lambda: None)
    bar = Progress(n, f"eval {split}", unit="image", enabled=progress)
    for i in range(n):
        sync()
        tr = time.perf_counter()
        if sphere:
            o, d = dataset_rays(cfg, ds, image=i)
            out = sphere_traced_rays_of(model, cfg, o, d, chunk=None if sphere is True else sphere)
            rgb, depth, opacity = (out[k].reshape(ds.height, ds.width, -1).squeeze(-1)
                                   for k in ("rgb", "depth", "opacity"))  # fmt: skip
        else:
            rgb, depth, opacity = render_dataset_image(model, cfg, ds, i)
        sync()
        render_ms = 1e3 * (time.perf_counter() - tr)
        gt = ds.images[i].to(rgb.device)
        rows.append(
            {
                "image": i,
                "psnr": psnr(rgb, gt),
                "ssim": ssim(rgb, gt) if with_ssim else None,
                "render_ms": render_ms,
            }
        )
        if sphere:  # marching steps per pixel, fraction of pixels on the surface
            rows[-1].update(sphere_iters=float(out["iters"].float().mean()),
                            sphere_hits=out["n_hit"] / max(o.shape[0], 1))  # fmt: skip
        side = [
            to_uint8(gt.cpu()),
            to_uint8(rgb.cpu()),
            _depth_image(
                depth.cpu(), opacity.cpu(), depth_scale(cfg, depth.cpu(), opacity.cpu()) or cfg.far
            ).numpy(),
        ]
        write_image(
            out_dir / f"{split}_{i:03d}.png",
            torch.cat([torch.as_tensor(x) for x in side], 1).numpy(),
        )
        bar.update()
    bar.close()
    metrics = {
        "split": split,
        "step": ckpt["step"],  # the checkpoint's
        "checkpoint": which,
        "n_images": n,
        "psnr": sum(r["psnr"] for r in rows) / max(n, 1),
        "ssim": sum(r["ssim"] for r in rows) / max(n, 1) if with_ssim else None,
        "ssim_settings": SSIM_SETTINGS if with_ssim else "not computed: images under 11x11",
        "seconds_per_image": (time.perf_counter() - t0) / max(n, 1),
        "render_ms_median": statistics.median(r["render_ms"] for r in rows) if rows else None,
        **{k: getattr(cfg, k) if k == "chunk" or grid else None for k in RENDER_SETTINGS},
        "renderer": "sphere" if sphere else "volume",
        "per_image": rows,
        "provenance": {**command_now(), **environment(cfg.device)},
    }
    if sphere:
        for k in ("sphere_iters", "sphere_hits"):
            metrics[k] = sum(r[k] for r in rows) / max(n, 1)
    write_json(out_dir / "metrics.json", metrics)
    return metrics


def camera_path(c2w: torch.Tensor, kind: str, frames: int) -> torch.Tensor:
    """[frames, 4, 4] cameras around the training cameras' target: centre = the point nearest to
    all optical axes, radius = their mean distance to it, up = their mean up vector; "orbit" keeps
    their mean elevation, "spiral" swings it by +-15 degrees."""
    if kind not in PATHS:
        raise UserError(f"--path must be spiral or orbit, got {kind!r}")
    c2w = c2w.double().cpu()
    o, centre = c2w[:, :3, 3], camera_target(c2w)
    up = torch.nn.functional.normalize(c2w[:, :3, 1].mean(0), dim=0)
    rel = o - centre
    radius = float(rel.norm(dim=-1).mean())
    elev = float(torch.asin((torch.nn.functional.normalize(rel, dim=-1) @ up).clamp(-1, 1)).mean())
    a = torch.nn.functional.normalize(
        torch.linalg.cross(up, torch.tensor([0.3, 0.2, 0.9], dtype=torch.float64)), dim=0
    )
    b = torch.linalg.cross(up, a)
    mats = []
    for f in range(frames):
        s = f / frames
        el = elev + (math.radians(15) * math.sin(2 * math.pi * s) if kind == "spiral" else 0.0)
        az = 2 * math.pi * s
        direction = math.cos(el) * (math.cos(az) * a + math.sin(az) * b) + math.sin(el) * up
        mats.append(look_at(centre + radius * direction, centre, up, dtype=torch.float64))
    return torch.stack(mats).float()


PATHS = ("spiral", "orbit")  # the built-in camera paths of `render --path`


@torch.no_grad()
def render_run(run, path: str = "spiral", frames: int | None = None, size=None, device=None, fps=20,
               renderer: str = "volume", progress: bool = False):  # fmt: skip
    """Colour and depth videos (mp4 + gif) and PNG frames along a camera path, under
    RUN/render_{path}/ (RUN/render_{path}_sphere/ with ``renderer="sphere"``: SDF runs'
    surfaces sphere-traced). ``size`` = (W, H), default the training resolution. ``path``:
    "spiral", "orbit" or a camera-path file saved by the viewer (its keyframes, field of view,
    frame count and the near/far the viewer rendered each keyframe with; ``frames`` overrides
    the count; output in RUN/render_{file stem}/). ``progress``: frames done on stderr
    (:class:`~warpnerf.train.progress.Progress`)."""
    check_video_numbers(frames, size)  # before any work
    cfg, model, _ = load_run(run, device)
    _check_renderer(renderer, model, cfg)
    user_path = None
    if path not in PATHS:
        from ..data.camera_path import load_camera_path

        user_path = load_camera_path(path)
        frames = frames or user_path.frames
    frames = frames or 40
    train = load_data(cfg, "train")
    w0, h0 = train.width, train.height
    if user_path is not None:  # the viewer's field of view and aspect, the training height
        w, h = size or (max(1, round(h0 * user_path.aspect)), h0)
    else:
        w, h = size or (w0, h0)
    if size is None:  # the training images' size: within the videos' limits too
        check_video_numbers(frames, (w, h), "the training images' size (pass --size WxH)")
    kinds = ("rgb", "depth", "geometry") if model.kind == "sdf" else ("rgb", "depth")
    # per frame: rays and outputs on the device (~64 B a pixel), the kept uint8 frames on the host
    check_fits(64.0 * w * h, cfg.device, f"rendering {w}x{h} frames")
    check_fits(3.0 * w * h * frames * len(kinds), "cpu", f"keeping {frames} frames of {w}x{h}")
    windows = None  # per frame (near, far): a viewer's path renders with the viewer's
    if user_path is not None:
        k = user_path.intrinsics(w, h).to(train.intrinsics)
        cams = user_path.cameras(frames).to(cfg.device)
        windows = _path_windows(user_path, frames, model, cfg, train)
    else:
        k = train.intrinsics[0].clone()
        k[[0, 2]] *= w / w0
        k[[1, 3]] *= h / h0
        if cfg.ndc_camera() is not None:  # forward-facing: stay in front, as the captures did
            from ..data.cameras import forward_facing_spiral

            cams = forward_facing_spiral(train.c2w, frames).float().to(cfg.device)
        else:
            cams = camera_path(train.c2w, path, frames).to(cfg.device)
    name = path if user_path is None else Path(path).stem
    out_dir = Path(run) / (f"render_{name}" + ("_sphere" if renderer == "sphere" else ""))
    names = [f"{kind}_{f:03d}.png" for kind in kinds for f in range(frames)]
    names += [f"{kind}.{x}" for kind in kinds for x in ("gif", "mp4")]
    make_folder(out_dir, "render folder")  # (a link to another folder is refused)
    with output_lock(out_dir, "render folder"):
        check_foreign([out_dir / x for x in names])
        return _render_frames(cfg, model, cams, k, w, h, frames, fps, out_dir, renderer,
                              windows, progress)  # fmt: skip


# what `render` writes: an mp4 (H.264 in yuv420p, even sides: at least 2 pixels a side; x264
# takes at most 16384) and a GIF (at most 65535 a side); ffmpeg's own picture-size limit,
# (w + 128) (h + 128) < 2^28, holds up to 2^26 pixels
VIDEO_SIDES = (2, 16384)
MAX_VIDEO_PIXELS = 1 << 26


def check_video_numbers(frames: int | None, size, what: str = "--size") -> None:
    """UserError unless ``frames`` (None: the default) is a count in [1, MAX_FRAMES] (the
    camera path's own bound) and ``size`` (W, H) (None: the training size) fits the videos
    `render` writes: each side in :data:`VIDEO_SIDES`, at most :data:`MAX_VIDEO_PIXELS`."""
    if frames is not None and not (isinstance(frames, int) and 1 <= frames <= MAX_FRAMES):
        raise UserError(f"--frames must be in [1, {MAX_FRAMES}], got {frames}")
    if size is None:
        return
    (w, h), (lo, hi) = size, VIDEO_SIDES
    if not (lo <= w <= hi and lo <= h <= hi and w * h <= MAX_VIDEO_PIXELS):
        raise UserError(f"{what}: {w}x{h} is beyond the videos' limits: each side in "
                        f"[{lo}, {hi}] and at most {MAX_VIDEO_PIXELS} pixels (the mp4's "
                        "encoder)")  # fmt: skip


def _path_windows(user_path, frames: int, model, cfg, train):
    """[frames, 2] (near, far) of a viewer camera path's frames: those saved with its keyframes
    (interpolated), else (files saved before they were) the viewer's rule
    (:func:`~warpnerf.data.camera_path.window_rule`) at each frame's position; None for
    forward-facing (NDC) runs, which the viewer renders with the run's own range."""
    import numpy as np

    from ..data.camera_path import window_rule

    if cfg.ndc_camera() is not None:
        return None
    saved = user_path.frame_windows(frames)
    if saved is not None:
        return saved
    rule = window_rule(with_refined_poses(model, train, "train").c2w, cfg.near, cfg.far)
    return np.array([rule(c[:3, 3]) for c in user_path.cameras(frames).double().numpy()])


def frames_per_batch(w: int, h: int, frames: int, chunk: int | None) -> int:
    """How many frames of ``w`` x ``h`` render together: as many as fill one rendering chunk
    (at least one). Small frames (the CPU preset's 32x32: 1024 rays) rendered one at a time
    make every step of the pipeline a tiny batch (the SDF view's sphere tracing: ~60 dependent
    steps a frame, each a few dozen small ops), and on a CPU that per-call cost, not the
    arithmetic, was most of the time; each ray's result does not depend on the other rays of
    its call, so the frames are the same."""
    if not chunk:
        return 1
    return max(1, min(frames, int(chunk) // max(w * h, 1)))


def _render_frames(cfg, model, cams, k, w, h, frames, fps, out_dir, renderer="volume",
                   windows=None, progress=False):  # fmt: skip
    import copy

    from .progress import Progress

    rgbs, depths, geo, t0, scale = [], [], [], time.perf_counter(), None
    # frames rendered together (:func:`frames_per_batch`); one at a time with per-frame near/far
    per = 1 if windows is not None else frames_per_batch(w, h, frames, cfg.chunk)
    bar = Progress(frames, "render", unit="frame", enabled=progress)
    with bar:
        for f0 in range(0, frames, per):
            fs = range(f0, min(f0 + per, frames))
            rays = [camera_rays(cams[f], k, w, h, ndc=cfg.ndc_camera()) for f in fs]
            o, d = (torch.cat(x) for x in zip(*rays))
            fc = cfg
            if windows is not None:  # this frame's near/far (a viewer's camera path)
                fc = copy.copy(cfg)
                fc.near, fc.far = float(windows[f0][0]), float(windows[f0][1])
            if renderer == "sphere":
                out = sphere_traced_rays_of(model, fc, o, d)
            else:
                out = render_rays_of(model, fc, o, d, chunk=cfg.chunk)
            if model.kind == "sdf":  # geometry: sphere-trace the learned SDF, Lambert-shaded
                shaded = _geometry_image(model.coarse, cfg, o, d)
            for i, f in enumerate(fs):
                px = slice(i * w * h, (i + 1) * w * h)
                rgb = to_uint8(out["rgb"][px].reshape(h, w, 3).cpu())
                dep = out["depth"][px].reshape(h, w).cpu()
                opa = out["opacity"][px].reshape(h, w).cpu()
                if scale is None:  # the first frame that shows a surface sets it for the video
                    scale = depth_scale(cfg, dep, opa)
                dep = _depth_image(dep, opa, scale or cfg.far).numpy()
                write_image(out_dir / f"rgb_{f:03d}.png", rgb)
                write_image(out_dir / f"depth_{f:03d}.png", dep)
                rgbs.append(rgb)
                depths.append(dep)
                if model.kind == "sdf":
                    geo.append(to_uint8(shaded[px].reshape(h, w, 3)))
                    write_image(out_dir / f"geometry_{f:03d}.png", geo[-1])
                bar.update()
    mp4 = True
    for name, seq in (("rgb", rgbs), ("depth", depths), ("geometry", geo)):
        if not seq:
            continue
        write_video(out_dir / f"{name}.gif", seq, fps=fps)
        try:
            write_video(out_dir / f"{name}.mp4", seq, fps=fps)
        except ImportError as e:  # imageio-ffmpeg is a dependency; tolerate machines without it
            mp4 = False
            print(f"warning: no {name}.mp4 ({e})")
    return {
        "mp4": mp4,
        "frames": frames,
        "size": [w, h],
        "seconds": time.perf_counter() - t0,
        "out": str(out_dir),
        "renderer": renderer,
    }


@torch.no_grad()
def _geometry_image(field, cfg, o, d):
    """Shaded normals of the SDF's zero level set (grey albedo, white background) [n, 3]."""
    from ..ops import ray_aabb_intersect
    from ..render import render_chunks
    from ..trace import shade, sphere_trace_fn

    t0, t1, hit = ray_aabb_intersect(o, d, cfg.aabb_box())
    t1 = torch.where(hit, t1, t0)
    grey = torch.tensor([[0.8, 0.8, 0.8]], device=o.device)

    def chunk_fn(sl):
        tr = sphere_trace_fn(field.sdf, o[sl], d[sl], t0[sl], t1[sl], eps=1e-3 * cfg.aabb,
                             max_iters=128)  # fmt: skip
        return shade(tr, d[sl], grey, light=None).cpu()

    return render_chunks(o.shape[0], cfg.chunk, chunk_fn)


def train_and_evaluate(cfg, run, split: str = "val", max_images: int = 0, progress=False):
    """Trains a fresh run, evaluates it on ``split``; returns a summary dict (PSNR, SSIM, time,
    parameter count) for the demos' tables."""
    from .nerf import train_nerf

    hist = train_nerf(cfg, run, progress=progress, log=lambda *a: None)
    m = evaluate_run(run, split, max_images=max_images)
    _, model, _ = load_run(run)
    n_params = sum(p.numel() for p in model.parameters())  # a shared network counts once
    return {
        "psnr": m["psnr"],
        "ssim": m["ssim"],
        "train_seconds": hist["seconds"][-1],
        "steps": hist["step"][-1],
        "parameters": n_params,
        "run": str(run),
    }


# The materials scene's analytic geometry (its data README): 8 spheres of radius 0.32 at
# z = 0.32, x in {-1.05, -0.35, 0.35, 1.05}, y in {-0.4, 0.4}; a ground disk of radius 1.6 at z = 0.
MATERIALS_SPHERES = [(x, y, 0.32) for y in (-0.4, 0.4) for x in (-1.05, -0.35, 0.35, 1.05)]
MATERIALS_RADIUS, MATERIALS_DISK = 0.32, 1.6
# A closed SDF must give the infinitely thin disk some thickness: its underside (below this z)
# has no counterpart in the reference and is left out of the accuracy.
MATERIALS_BELOW = -0.1


def materials_reference(n: int, seed: int = 0):
    """n points uniformly (by area) on the materials scene's analytic spheres and disk [n, 3]."""
    import numpy as np

    rng = np.random.default_rng(seed)
    r0, rd = MATERIALS_RADIUS, MATERIALS_DISK
    a_sph, a_disk = 8 * 4 * math.pi * r0 * r0, math.pi * rd * rd
    n_s = int(n * a_sph / (a_sph + a_disk))
    d = rng.normal(size=(n_s, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sph = np.asarray(MATERIALS_SPHERES)[rng.integers(0, 8, n_s)] + r0 * d
    r, th = rd * np.sqrt(rng.random(n - n_s)), rng.random(n - n_s) * 2 * math.pi
    disk = np.stack([r * np.cos(th), r * np.sin(th), np.zeros_like(r)], 1)
    return np.concatenate([sph, disk]).astype(np.float32)


def sphere_depth(o: torch.Tensor, d: torch.Tensor, centers, radius: float) -> torch.Tensor:
    """Distance along unit rays to the first of the spheres, inf on a miss: the smallest
    positive root of |o + t d - c|^2 = r^2.

    Args:
        o: [n_rays, 3] origins (outside the spheres).
        d: [n_rays, 3] unit directions.
        centers: [k, 3] sphere centres.
        radius: their radius.

    Returns:
        t [n_rays].
    """
    t_best = torch.full(o.shape[:1], math.inf, dtype=o.dtype, device=o.device)
    for c in torch.as_tensor(centers, dtype=o.dtype).reshape(-1, 3).to(o.device):
        oc = o - c
        b = (oc * d).sum(-1)
        disc = b * b - (oc * oc).sum(-1) + radius * radius
        t = -b - torch.sqrt(disc.clamp_min(0))
        t_best = torch.where((disc > 0) & (t > 0) & (t < t_best), t, t_best)
    return t_best


def materials_depth(o: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Distance along unit rays [n_rays, 3] to the materials scene's first analytic surface (its
    spheres, or the ground disk z = 0 of radius 1.6), inf on a miss [n_rays]."""
    t_sph = sphere_depth(o, d, MATERIALS_SPHERES, MATERIALS_RADIUS)
    with torch.no_grad():
        t = -o[:, 2] / d[:, 2]  # (inf / nan for rays parallel to the disk: no hit below)
    p = o + t.unsqueeze(-1) * d
    hit = (t > 0) & (p[:, 0] ** 2 + p[:, 1] ** 2 <= MATERIALS_DISK**2)
    return torch.where(hit & (t < t_sph), t, t_sph)


@torch.no_grad()
def depth_error(model, cfg, ds, depth_fn, views: int = 10, min_opacity: float = 0.5) -> dict:
    """Mean and median |rendered depth - true depth| over the pixels of the first ``views``
    images of ``ds`` (0: all) that the reference hits and the run renders opaque.

    Each image is rendered with the run's own renderer; its surface depth is expected depth /
    opacity, compared where ``depth_fn(o, d)`` (true distance along the unit rays, inf on a
    miss) is finite and the opacity exceeds ``min_opacity``. Units: the rays' (the data's world
    units for Blender-format runs).

    Returns:
        {"depth_error_mean", "depth_error_median" (None without such pixels), "depth_pixels",
        "depth_views"}.
    """
    from .nerf import dataset_rays

    n = ds.images.shape[0] if not views else min(views, ds.images.shape[0])
    errs = []
    for i in range(n):
        _, depth, opacity = render_dataset_image(model, cfg, ds, i)
        o, d = dataset_rays(cfg, ds, image=i)
        t_true = depth_fn(o.double(), d.double())  # (unit directions)
        depth, opacity = depth.reshape(-1), opacity.reshape(-1)
        ok = torch.isfinite(t_true) & (opacity > min_opacity)
        surface = depth[ok] / opacity[ok]
        errs.append((surface.double() - t_true[ok]).abs().cpu())
    e = torch.cat(errs) if errs else torch.zeros(0, dtype=torch.float64)
    return {
        "depth_error_mean": float(e.mean()) if e.numel() else None,
        "depth_error_median": float(e.median()) if e.numel() else None,
        "depth_pixels": int(e.numel()),
        "depth_views": n,
    }


def _surface_distances(v, f, ref, points, cfg, below=None) -> dict:
    """Accuracy / completeness / Chamfer of the mesh (points sampled on it, mapped to the data's
    world units) against the reference points; mesh points with z < ``below`` left out."""
    import numpy as np

    from ..mesh import sample_surface
    from .sdf import chamfer

    m = sample_surface(v, f, points, seed=0)
    if cfg.scene is not None:
        from ..data.capture import normalised_to_world

        m = normalised_to_world(m, cfg.scene["transform"], cfg.ndc_camera())
        m = m[np.isfinite(m).all(1)]
    if below is not None:
        m = m[m[:, 2] >= below]
    if len(m) == 0:
        return {"accuracy": None, "completeness": None, "chamfer": None, "mesh_faces": len(f),
                "surface_points": 0}  # fmt: skip
    dev = torch.device(cfg.device)
    acc, comp = chamfer(torch.as_tensor(m, dtype=torch.float32, device=dev),
                        torch.as_tensor(ref, dtype=torch.float32, device=dev))  # fmt: skip
    return {"accuracy": acc, "completeness": comp, "chamfer": 0.5 * (acc + comp),
            "mesh_faces": int(len(f)), "surface_points": int(len(m))}  # fmt: skip


# the shapes' names, the spheres in MATERIALS_SPHERES' order
MATERIALS_NAMES = ("gold", "copper", "aluminium", "red plastic", "blue plastic", "green diffuse",
                   "glass", "purple paint", "disk")  # fmt: skip


def materials_shape_ids(points):
    """[n] index into :data:`MATERIALS_NAMES` of the analytic shape nearest to each point."""
    import numpy as np

    p = np.asarray(points, dtype=np.float64)
    c = np.asarray(MATERIALS_SPHERES)
    d_sph = np.abs(np.linalg.norm(p[:, None] - c[None], axis=-1) - MATERIALS_RADIUS)  # [n, 8]
    rho = np.linalg.norm(p[:, :2], axis=-1)
    d_disk = np.hypot(p[:, 2], np.maximum(rho - MATERIALS_DISK, 0.0))
    return np.argmin(np.concatenate([d_sph, d_disk[:, None]], 1), 1)


def materials_visible(points, c2w, intrinsics, width: int, height: int, chunk: int = 2048,
                      device="cpu"):  # fmt: skip
    """[n] bool: which analytic surface points [n, 3] of the materials scene at least one camera
    sees (c2w [k, 4, 4], OpenGL convention; intrinsics [k, 4] fx, fy, cx, cy in pixels of
    ``width`` x ``height`` images): the point projects into the image and no sphere nor the disk
    crosses the segment from the camera to it (up to 1e-4 of its length before the point). The
    analytic counterpart of DTU's observation masks: surface no training view shows (the disk
    under the spheres, their undersides) cannot be reconstructed from the images."""
    import numpy as np

    p = torch.as_tensor(np.asarray(points), dtype=torch.float64, device=device)
    cams = torch.as_tensor(np.asarray(c2w), dtype=torch.float64, device=device)[:, :3]
    k = torch.as_tensor(np.asarray(intrinsics), dtype=torch.float64, device=device)  # [k, 4]
    o = cams[:, :, 3]  # [k, 3]
    end = 1.0 - 1e-4
    seen = torch.zeros(len(p), dtype=torch.bool, device=device)
    for s in range(0, len(p), chunk):
        v = p[s : s + chunk][None] - o[:, None]  # [k, m, 3]: camera -> point, t in [0, 1]
        c = torch.einsum("kji,kmj->kmi", cams[:, :, :3], v)  # in the camera frame
        z = (-c[..., 2]).clamp_min(1e-12)
        u = k[:, None, 2] + k[:, None, 0] * c[..., 0] / z
        w = k[:, None, 3] - k[:, None, 1] * c[..., 1] / z
        ok = (c[..., 2] < 0) & (u >= 0) & (u <= width) & (w >= 0) & (w <= height)
        a = (v * v).sum(-1)
        for centre in MATERIALS_SPHERES:  # |o + t v - centre| = r for some t in (0, end)
            q = o[:, None] - torch.tensor(centre, dtype=torch.float64, device=device)
            b = (v * q).sum(-1)
            disc = b * b - a * ((q * q).sum(-1) - MATERIALS_RADIUS**2)
            r = disc.clamp_min(0).sqrt()
            t1, t2 = (-b - r) / a, (-b + r) / a
            hit = (disc > 0) & (((t1 > 0) & (t1 < end)) | ((t2 > 0) & (t2 < end)))
            ok &= ~hit
        vz = v[..., 2]
        t = -o[:, None, 2] / torch.where(vz.abs() > 1e-12, vz, torch.full_like(vz, 1e-12))
        x = o[:, None, :2] + t.unsqueeze(-1) * v[..., :2]
        ok &= ~((t > 0) & (t < end) & (x.norm(dim=-1) <= MATERIALS_DISK))
        seen[s : s + chunk] = ok.any(0)
    return seen.cpu().numpy()


def _nearest(x: torch.Tensor, y: torch.Tensor, chunk: int = 4096) -> torch.Tensor:
    """[len(x)] distance from each point of x to the nearest of y."""
    return torch.cat([torch.cdist(x[s : s + chunk], y).min(1).values
                      for s in range(0, len(x), chunk)])  # fmt: skip


def _materials_breakdown(v, f, ref, points, cfg) -> dict:
    """For the materials reference: completeness and Chamfer over the reference points a training
    camera sees (:func:`materials_visible`), and accuracy / completeness per shape (mesh points
    and reference points grouped by their nearest analytic shape)."""
    from ..mesh import sample_surface

    train = load_data(cfg, "train")
    vis = materials_visible(ref, train.c2w.cpu(), train.intrinsics.cpu(), train.width,
                            train.height, device=cfg.device)  # fmt: skip
    m = sample_surface(v, f, points, seed=0)  # the points _surface_distances used
    m = m[m[:, 2] >= MATERIALS_BELOW]
    dev = torch.device(cfg.device)
    mt = torch.as_tensor(m, dtype=torch.float32, device=dev)
    rt = torch.as_tensor(ref, dtype=torch.float32, device=dev)
    acc = _nearest(mt, rt).cpu().numpy()
    comp = _nearest(rt, mt).cpu().numpy()
    ids_m, ids_r = materials_shape_ids(m), materials_shape_ids(ref)
    per = {}
    for i, name in enumerate(MATERIALS_NAMES):
        a, c = acc[ids_m == i], comp[(ids_r == i) & vis]
        per[name] = {"accuracy": float(a.mean()) if len(a) else None,
                     "completeness_visible": float(c.mean()) if len(c) else None}  # fmt: skip
    comp_vis = float(comp[vis].mean())
    return {
        "visible_fraction": float(vis.mean()),
        "completeness_visible": comp_vis,
        "chamfer_visible": 0.5 * (float(acc.mean()) + comp_vis),
        "per_shape": per,
        "visible_note": "completeness over the reference points a training camera sees "
        "(analytic occlusion by the spheres and disk, as DTU's observation masks)",
    }


def evaluate_geometry(run, reference, resolution: int = 256, points: int = 50_000, device=None,
                      clean: float | None = None, views: int = 10,
                      snapshot: float | None = None, progress: bool = False):  # fmt: skip
    """Accuracy, completeness and Chamfer distance of an SDF run's surface against a reference,
    and the rendered depth's error where the reference is analytic.

    The run's zero level set is meshed by marching cubes at ``resolution`` inside its scene cube
    and ``points`` points are sampled on it (by area); ``reference`` is "materials" (the analytic
    spheres and disk, sampled the same way; mesh points under the disk, z < -0.1, are left out)
    or a point-cloud file (.npz with ``points`` or ``verts``, or .ply vertices; a mesh's vertices
    serve as its points). Accuracy: mean distance from the run's surface to the reference;
    completeness: mean distance from the reference to the run's surface; Chamfer: their mean.
    World units of the data (a COLMAP/LLFF run's mesh is mapped back to the capture's frame
    first). Also "delivered": the same figures, every face counted, of the mesh `warpnerf mesh`
    writes by default (culled by the training cameras, cleaned), and for "materials"
    "raw_every_face": of the raw level set with the points under the disk counted too
    (:func:`_delivered_figures`). ``clean`` (a fraction of the area,
    :func:`warpnerf.mesh.clean_mesh`) also reports the figures of the mesh without its floating
    pieces, under "cleaned". For "materials",
    "visible" adds the completeness and Chamfer over the reference surface the training cameras
    see and the errors per shape (:func:`_materials_breakdown`; of the cleaned mesh with
    ``clean``).

    Depth error (:func:`depth_error`, "materials" only: a point cloud has no ray hits, so the
    depth figures are None): on the first ``views`` val images (0: all), rendered by the run.
    ``snapshot``: the run's snapshot at that many training seconds instead of its last
    checkpoint. ``progress``: the marching-cubes grid's evaluation on stderr
    (:class:`~warpnerf.train.progress.Progress`).
    """
    from ..mesh import extract_mesh
    from .progress import Progress

    if not 8 <= resolution <= 1024:
        raise UserError(f"--mesh-resolution must be in [8, 1024], got {resolution}")
    if not 100 <= points <= 10_000_000:
        raise UserError(f"--geometry-points must be in [100, 1e7], got {points}")
    if views < 0:
        raise UserError(f"--geometry-views must be >= 0, got {views}")
    if clean is not None and not 0.0 <= clean < 1.0:
        raise UserError(f"--clean MIN_FRACTION must be in [0, 1), got {clean}")
    cfg, model, _ = load_run(run, device, snapshot)
    if model.kind != "sdf":
        raise UserError(f"{run}: --geometry needs an SDF run ({_sdf_fields()}), not {cfg.field}")
    analytic = reference == "materials"
    ref = materials_reference(points) if analytic else _load_reference(reference)
    a, field = cfg.aabb, model.field
    with Progress(resolution**3, "eval geometry: SDF grid", unit="pt", unit_scale=True,
                  enabled=progress) as bar:  # fmt: skip
        v, f = extract_mesh(bar.counting(lambda p: field.sdf(p.to(cfg.device))), [-a] * 3,
                            [a] * 3, resolution, 0.0, device=cfg.device)  # fmt: skip
    if len(f) == 0:
        raise UserError(f"{run}: the SDF has no zero level set inside its box; nothing to compare")
    below = MATERIALS_BELOW if analytic else None
    res = {"run": str(run), "reference": str(reference),
           **_surface_distances(v, f, ref, points, cfg, below)}  # fmt: skip
    if clean is not None:
        from ..mesh import clean_mesh

        vc, fc, info = clean_mesh(v, f, clean)
        same = info["components_removed"] == 0
        dist = {k: res[k] for k in ("accuracy", "completeness", "chamfer")} if same else (
            _surface_distances(vc, fc, ref, points, cfg, below))  # fmt: skip
        res["cleaned"] = {"clean": clean, **dist, "mesh_faces": int(len(fc)),
                          **{k: info[k] for k in ("components", "components_removed",
                                                  "area_removed_fraction")}}  # fmt: skip
    res.update(_delivered_figures(v, f, ref, points, cfg, below, model))
    if analytic:  # visible-surface figures and per-shape errors (of the cleaned mesh if any)
        vb, fb = (vc, fc) if clean is not None else (v, f)
        res["visible"] = _materials_breakdown(vb, fb, ref, points, cfg)
    res.update(points=int(points), resolution=resolution)
    res.update(_geometry_depth(model, cfg, views) if analytic else _NO_DEPTH)
    return res


def _delivered_figures(v, f, ref, points, cfg, below, model=None) -> dict:
    """The figures a user who opens the mesh meets, every vertex and face counted: "delivered"
    (the mesh `warpnerf mesh` writes by default: the faces where no training ray of ``model``
    puts weight and those no training camera sees culled, components under 1 % of the area
    dropped, :func:`warpnerf.mesh.surface_mesh`; the grid's figures under "weight_grid", or
    why there is none under "weights_note") and, where the main figures leave points out
    (materials: under the disk), "raw_every_face" (the raw level set). Bounds in the mesh's
    frame (the data's world frame for Blender scenes). ``v`` is the level set in the box
    [-cfg.aabb, cfg.aabb]^3, the field's frame."""
    import contextlib

    from ..mesh import DEFAULT_CLEAN, surface_mesh
    from .visibility import training_weight_grid

    out = {}
    if below is not None:
        out["raw_every_face"] = {
            **_surface_distances(v, f, ref, points, cfg),
            "bounds_min": v.min(0).tolist(),
            "bounds_max": v.max(0).tolist(),
        }
    train, wgrid, wnote = None, None, "no model"
    with contextlib.suppress(UserError):  # the training data may be gone: no culling then
        train = load_data(cfg, "train")
    if train is None:
        wnote = "the run's training data is not at hand"
    elif model is not None:  # (NDC too: the rays and the grid are in the field's frame)
        a = float(cfg.aabb)
        wgrid, wnote = training_weight_grid(model, cfg, with_refined_poses(model, train, "train"),
                                            [-a] * 3, [a] * 3)  # fmt: skip
    cams = train if cfg.ndc_camera() is None else None
    vd, fd, info = surface_mesh(v, f, cams, DEFAULT_CLEAN, device=cfg.device, weight_grid=wgrid)
    if wgrid is not None:
        info["weight_grid"] = wgrid.info
    else:
        info["weights_note"] = wnote
    d = {"accuracy": None, "completeness": None, "chamfer": None, "mesh_faces": 0}
    if len(fd):
        d = {
            **_surface_distances(vd, fd, ref, points, cfg),
            "bounds_min": vd.min(0).tolist(),
            "bounds_max": vd.max(0).tolist(),
        }
    out["delivered"] = {**d, **info}
    return out


_NO_DEPTH = {"depth_error_mean": None, "depth_error_median": None, "depth_pixels": None,
             "depth_note": "a point-cloud reference has no ray hits: no depth error"}  # fmt: skip


def _load_reference(path):
    from .sdf import load_points

    return load_points(path)[0]


def _geometry_depth(model, cfg, views: int) -> dict:
    """:func:`depth_error` against the materials scene on the run's val images."""
    if cfg.ndc_camera() is not None or cfg.scene is not None:
        return {**_NO_DEPTH, "depth_note": "the run's rays are in a normalised capture frame, "
                "not the analytic scene's: no depth error"}  # fmt: skip
    res = depth_error(model, cfg, load_data(cfg, "val"), materials_depth, views)
    res["depth_note"] = ("|expected depth / opacity - analytic first hit| on val pixels the "
                         "reference hits with opacity > 0.5")  # fmt: skip
    return res
