"""Evaluation (PSNR/SSIM per image, side-by-side PNGs) and camera-path videos of a NeRF run.

Geometry evaluation lives in :mod:`warpnerf.train.geometry_eval`, the materials scene's ground
truth in :mod:`warpnerf.data.materials_truth` and the built-in camera paths in
:mod:`warpnerf.data.camera_path`; their public names are re-exported here (their old home)."""

from __future__ import annotations

import dataclasses
import statistics
import time
from pathlib import Path

import torch

from ..data.camera_path import MAX_FRAMES, PATHS, camera_path
from ..data.cameras import MAX_DEPTH, camera_rays
from ..data.materials_truth import materials_depth, materials_reference, sphere_depth
from ..errors import UserError, check_fits
from ..metrics import psnr, ssim
from ..ops.bridge import INT32_MAX
from ..outputs import (
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
from .geometry_eval import depth_error, evaluate_geometry, sdf_field_names
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
from .nerf_run import MAX_SPP, pixel_corners, pixel_points, run_spp

__all__ = [
    "sphere_traced_rays_of",
    "evaluate_run",
    "evaluate_geometry",
    "materials_reference",
    "materials_depth",
    "sphere_depth",
    "depth_error",
    "render_run",
    "path_cameras",
    "depth_image",
    "camera_path",
    "train_and_evaluate",
]

# NeRFConfig fields that only affect rendering, so evaluation may override them, and the ranges
# of the numbers among them (rays at once and sample counts index in int32; a float32 distance)
RENDER_SETTINGS = ("chunk", "march_step", "round_samples", "render_half", "render_tracer")
RENDER_RANGES = {"chunk": (1, INT32_MAX), "march_step": (1e-9, MAX_DEPTH),
                 "round_samples": (0, INT32_MAX)}  # fmt: skip
SSIM_SETTINGS = "Gaussian 11x11, sigma 1.5, K1 0.01, K2 0.03, valid region, mean over RGB"


def depth_image(depth, opacity, scale):
    """The visible surface's depth normalised by ``scale`` (clipped to 1), as RGB uint8."""
    surf = surface_depth(depth, opacity)
    return torch.from_numpy(depth_to_uint8(surf, scale)).unsqueeze(-1).expand(*surf.shape, 3)


RENDERERS = ("volume", "sphere")  # eval / render --renderer: volume rendering, sphere tracing


def _check_renderer(renderer: str, model, cfg) -> None:
    if renderer not in RENDERERS:
        raise UserError(f"--renderer must be one of {', '.join(RENDERERS)}, got {renderer!r}")
    if renderer == "sphere" and model.kind != "sdf":
        raise UserError(f"--renderer sphere needs an SDF run ({sdf_field_names()}), not "
                        f"{cfg.field} (a density field has no surface to trace)")  # fmt: skip


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
    spp: int | None = None,
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
    ``progress``: images done on stderr (:class:`~warpnerf.train.progress.Progress`).
    ``spp``: rays a pixel, averaged (volume rendering; :func:`render_dataset_image`: the
    box-filtered image, 1 = the pixels' centres; None: the run's ``--train-spp``, 1 when
    sphere tracing; metrics.json records it)."""
    # every number the command takes, before any work (the kernels' limits)
    if split not in ("train", "val", "test"):
        raise UserError(f"--split must be train, val or test, got {split!r}")
    if max_images < 0:
        raise UserError(f"--max-images must be >= 0, got {max_images}")
    _check_spp(spp, renderer)
    for key, value in render.items():
        if key not in RENDER_SETTINGS:
            raise TypeError(f"evaluate_run: unknown rendering setting {key!r}")
        lo, hi = RENDER_RANGES.get(key, (None, None))
        if value is not None and lo is not None and not lo <= value <= hi:
            raise UserError(f"--{key.replace('_', '-')} must be in [{lo:g}, {hi:g}], got {value}")
    cfg, model, ckpt = load_run(run, device, snapshot)
    _check_renderer(renderer, model, cfg)
    if spp is None:  # the run's own (what it trained for); sphere tracing: the centres
        spp = 1 if renderer == "sphere" else run_spp(cfg)
    grid = model.grid
    changed = {}
    for key, value in render.items():
        if value is None:
            continue
        if key != "chunk" and grid is None:
            raise UserError(f"--{key.replace('_', '-')} needs a run with an occupancy grid")
        changed[key] = type(getattr(cfg, key))(value)
    if changed:  # (checked with the run's own: --chunk x samples a ray within int32 offsets)
        cfg = dataclasses.replace(cfg, **changed).check_values().freeze()
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
                         progress, spp)  # fmt: skip


def _check_spp(spp, renderer: str):
    """--spp given to eval or render: None (the run's) or an integer in [1, MAX_SPP]; more than
    one only for volume rendering (UserError otherwise)."""
    if spp is not None and (isinstance(spp, bool) or not isinstance(spp, int)
                            or not 1 <= spp <= MAX_SPP):  # fmt: skip
        raise UserError(f"--spp must be an integer in [1, {MAX_SPP}], got {spp!r}")
    if spp is not None and spp > 1 and renderer == "sphere":
        raise UserError("--spp needs --renderer volume (sphere tracing renders pixel centres)")
    return spp


def _evaluate(cfg, model, ckpt, grid, ds, split, n, out_dir, sphere=None, which=CHECKPOINT,
              progress=False, spp=1):  # fmt: skip
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
            rgb, depth, opacity = render_dataset_image(model, cfg, ds, i, spp)
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
            depth_image(
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
        "spp": spp,
        "per_image": rows,
        "provenance": {**command_now(), **environment(cfg.device)},
    }
    if sphere:
        for k in ("sphere_iters", "sphere_hits"):
            metrics[k] = sum(r[k] for r in rows) / max(n, 1)
    write_json(out_dir / "metrics.json", metrics)
    return metrics


@torch.no_grad()
def render_run(run, path: str = "spiral", frames: int | None = None, size=None, device=None, fps=20,
               renderer: str = "volume", progress: bool = False,
               spp: int | None = None):  # fmt: skip
    """Colour and depth videos (mp4 + gif) and PNG frames along a camera path, under
    RUN/render_{path}/ (RUN/render_{path}_sphere/ with ``renderer="sphere"``: SDF runs'
    surfaces sphere-traced). ``size`` = (W, H), default the training resolution. ``path``:
    "spiral", "orbit" or a camera-path file saved by the viewer (its keyframes, field of view,
    frame count and the near/far the viewer rendered each keyframe with; ``frames`` overrides
    the count; output in RUN/render_{file stem}/). ``progress``: frames done on stderr
    (:class:`~warpnerf.train.progress.Progress`). ``spp``: rays a pixel, averaged (volume
    rendering; None: the run's ``--train-spp``)."""
    check_video_numbers(frames, size)  # before any work
    spp = _check_spp(spp, renderer)
    cfg, model, _ = load_run(run, device)
    _check_renderer(renderer, model, cfg)
    spp = spp or (1 if renderer == "sphere" else run_spp(cfg))
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
        cams, k = path_cameras(cfg, train, path, frames, (w, h))
    name = path if user_path is None else Path(path).stem
    out_dir = Path(run) / (f"render_{name}" + ("_sphere" if renderer == "sphere" else ""))
    names = [f"{kind}_{f:03d}.png" for kind in kinds for f in range(frames)]
    names += [f"{kind}.{x}" for kind in kinds for x in ("gif", "mp4")]
    make_folder(out_dir, "render folder")  # (a link to another folder is refused)
    with output_lock(out_dir, "render folder"):
        check_foreign([out_dir / x for x in names])
        return _render_frames(cfg, model, cams, k, w, h, frames, fps, out_dir, renderer,
                              windows, progress, spp)  # fmt: skip


def path_cameras(cfg, train, path: str, frames: int, size) -> tuple:
    """(cameras [frames, 4, 4] on the run's device, intrinsics [4]) of `render`'s built-in path
    ``path`` ("spiral" or "orbit") at ``size`` (W, H): around the training cameras' target
    (:func:`~warpnerf.data.camera_path.camera_path`), or for a forward-facing (NDC) run a spiral
    in front of them, with the first training camera's intrinsics scaled to the size."""
    (w, h), w0, h0 = size, train.width, train.height
    k = train.intrinsics[0].clone()
    k[[0, 2]] *= w / w0
    k[[1, 3]] *= h / h0
    if cfg.ndc_camera() is not None:  # forward-facing: stay in front, as the captures did
        from ..data.cameras import forward_facing_spiral

        return forward_facing_spiral(train.c2w, frames).float().to(cfg.device), k
    return camera_path(train.c2w, path, frames).to(cfg.device), k


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


def _frame_rays(cfg, c2w, k, w, h, point):
    """Rays of one frame through ``point`` (x, y in [0, 1)) of every pixel."""
    if point == (0.5, 0.5):
        return camera_rays(c2w, k, w, h, ndc=cfg.ndc_camera())
    px, py = pixel_corners(w, h, c2w.device)
    cam = torch.zeros(w * h, dtype=torch.int64, device=c2w.device)
    return camera_rays(c2w[None], k[None], cam_idx=cam, px=px + point[0], py=py + point[1],
                       ndc=cfg.ndc_camera())  # fmt: skip


def _render_frames(cfg, model, cams, k, w, h, frames, fps, out_dir, renderer="volume",
                   windows=None, progress=False, spp=1):  # fmt: skip
    from .progress import Progress

    rgbs, depths, geo, t0, scale = [], [], [], time.perf_counter(), None
    # frames rendered together (:func:`frames_per_batch`); one at a time with per-frame near/far
    per = 1 if windows is not None else frames_per_batch(w, h, frames, cfg.chunk)
    bar = Progress(frames, "render", unit="frame", enabled=progress)
    with bar:
        for f0 in range(0, frames, per):
            fs = range(f0, min(f0 + per, frames))
            fc = cfg
            if windows is not None:  # this frame's near/far (a viewer's camera path)
                near, far = float(windows[f0][0]), float(windows[f0][1])
                fc = dataclasses.replace(cfg, near=near, far=far)
            total = None
            for point in pixel_points(spp):  # (spp > 1: the mean of the pixels' points)
                rays = [_frame_rays(cfg, cams[f], k, w, h, point) for f in fs]
                o, d = (torch.cat(x) for x in zip(*rays))
                if renderer == "sphere":
                    out = sphere_traced_rays_of(model, fc, o, d)
                    break
                out = render_rays_of(model, fc, o, d, chunk=cfg.chunk)
                each = {key: out[key] for key in ("rgb", "depth", "opacity")}
                total = each if total is None else {x: total[x] + each[x] for x in total}
            if renderer != "sphere" and spp > 1:
                out = {x: v / spp for x, v in total.items()}
                if model.kind == "sdf":  # (the geometry image: the pixels' centres)
                    rays = [_frame_rays(cfg, cams[f], k, w, h, (0.5, 0.5)) for f in fs]
                    o, d = (torch.cat(x) for x in zip(*rays))
            if model.kind == "sdf":  # geometry: sphere-trace the learned SDF, Lambert-shaded
                shaded = _geometry_image(model.coarse, cfg, o, d)
            for i, f in enumerate(fs):
                px = slice(i * w * h, (i + 1) * w * h)
                rgb = to_uint8(out["rgb"][px].reshape(h, w, 3).cpu())
                dep = out["depth"][px].reshape(h, w).cpu()
                opa = out["opacity"][px].reshape(h, w).cpu()
                if scale is None:  # the first frame that shows a surface sets it for the video
                    scale = depth_scale(cfg, dep, opa)
                dep = depth_image(dep, opa, scale or cfg.far).numpy()
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
        "spp": spp,
    }


@torch.no_grad()
def _geometry_image(field, cfg, o, d):
    """Shaded normals of the SDF's zero level set (grey albedo, white background) [n, 3]."""
    from ..ops import ray_aabb_intersect
    from ..render import render_chunks
    from ..sphere_tracing import shade, sphere_trace_fn

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
