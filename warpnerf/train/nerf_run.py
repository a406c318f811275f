"""A saved NeRF/VolSDF run and its data: loading a run folder (:func:`load_run`), a dataset
split (:func:`load_data`), the rays of its pixels (:func:`dataset_rays`), rendering rays and
images with the run's model (:func:`render_rays_of`, :func:`render_dataset_image`) and scoring
validation images (:func:`validate`). What eval, render, mesh, export and the viewer use; the
trainer (:mod:`warpnerf.train.nerf`) only trains."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import torch

from ..errors import UserError, check_device
from ..fields.model import RadianceModel, build_model
from ..outputs import build_for_weights, load_checkpoint
from ..render import render_chunks, render_marched, render_nerf
from .nerf_config import BLENDER_AABB, DATASET_FAR, DATASET_NEAR, MODEL, NeRFConfig, scene_settings
from .recipe import default_train_spp, wants_alpha

__all__ = [
    "resolve_data", "settle_new_run", "load_run", "load_data", "data_splits",
    "images_stay_on_host", "with_refined_poses", "dataset_rays", "render_rays_of",
    "distortion_coordinate", "near_zone", "surface_depth", "depth_scale", "render_dataset_image",
    "validate", "psnr_of_mse", "CHECKPOINT", "MAX_SPP", "pixel_points", "pixel_corners",
    "run_spp", "box_from_alpha", "BOX_MARGIN",
]  # fmt: skip

CHECKPOINT = "checkpoint.pt"


def _with_data(cfg: NeRFConfig) -> NeRFConfig:
    """A new run's config with what its data decides, read (no pixels): the data folder (a
    DIR/transforms.json given: DIR) and a COLMAP/LLFF capture's scene (transform, NDC camera,
    near/far, box; :func:`~warpnerf.train.nerf_config.scene_settings`). A copy, not resolved."""
    if cfg.scene is not None or cfg.data == "builtin":  # (a loaded run has them already)
        return cfg
    from ..data.blender import data_root

    cfg = dataclasses.replace(cfg, data=str(data_root(cfg.data)))
    cfg = dataclasses.replace(cfg, scene=scene_settings(cfg))
    if cfg.train_spp is None and Path(cfg.data).is_dir():  # rays a training pixel: where
        from ..data.loading import detect_format  # measured to win (recipe.py)

        fmt = cfg.data_format if cfg.data_format != "auto" else detect_format(cfg.data)
        cfg = dataclasses.replace(cfg, train_spp=default_train_spp(cfg, fmt))
    return cfg


def resolve_data(cfg: NeRFConfig) -> NeRFConfig:
    """A new run's config resolved with what its data decides (:func:`_with_data`), checked and
    frozen (:meth:`NeRFConfig.validate`), without the training split's size (the appearance
    codes and pose corrections keep the counts given; a run counts them,
    :func:`settle_new_run`)."""
    return _with_data(cfg).validate()


BOX_MARGIN = 1.05  # box_from_alpha: past the farthest reach the opaque pixels' rays ask for


def box_from_alpha(cfg: NeRFConfig, train) -> float | None:
    """The scene box a new run of an RGBA Blender-format split needs when --aabb is not given:
    where an opaque training pixel's ray passes outside the convention's box
    (:data:`~warpnerf.train.nerf_config.BLENDER_AABB`), the object reaches past it (the
    materials scene's ground disk), so the box grows to the largest such reach
    (:func:`warpnerf.data.mask_box.opaque_reach`) times :data:`BOX_MARGIN`, rounded up to
    1e-3; None (the box stays the default) when no ray asks for more, for captures, the built-in
    scene, contracted runs, fields without a box and images without alpha or whose alpha
    outlines nothing (:func:`~warpnerf.data.mask_box.shows_silhouette`)."""
    if (
        cfg.aabb > 0
        or cfg.data == "builtin"
        or cfg.scene is not None
        or train.alpha is None
        or train.format != "blender"
        or cfg.contract == "on"
        or not cfg.traits.in_box
    ):
        return None
    from ..data.cameras import MAX_CENTRE
    from ..data.mask_box import opaque_reach, shows_silhouette

    if not shows_silhouette(train.alpha):
        return None

    near = DATASET_NEAR if cfg.near is None else float(cfg.near)  # (resolve's, for Blender data)
    far = DATASET_FAR if cfg.far is None else float(cfg.far)
    reach = opaque_reach(train.c2w, train.intrinsics, train.alpha, near, far, BLENDER_AABB)
    if reach <= BLENDER_AABB:
        return None
    box = math.ceil(reach * BOX_MARGIN * 1000.0) / 1000.0
    if not box <= MAX_CENTRE:  # (cameras a million units out: nothing a box can hold)
        raise UserError(f"{cfg.data}: the training images' opaque pixels ask for a scene box of "
                        f"half-size {box:g}, past the largest ({MAX_CENTRE:g}); check the "
                        "cameras' transform_matrix, or give --aabb")  # fmt: skip
    return box


def settle_new_run(cfg: NeRFConfig) -> tuple:
    """(config, training split) of a new run, in one pass: what the data decides
    (:func:`_with_data`), the device and the values' bounds checked, the training images read
    (8-bit where they stay in host memory, with their alpha), then the config resolved with
    their count, checked once and frozen (:meth:`NeRFConfig.validate`): what the run reads,
    never changed after. The
    split keeps its alpha where the resolved run reads it (:func:`~warpnerf.train.recipe.
    wants_alpha`)."""
    draft = _with_data(cfg)
    check_device(draft.device)
    draft.check_values()  # the bounds before any file or scene is built from them (untrusted
    # sizes such as --builtin-size past the kernels' limits: one line, no run folder)
    train = load_data(draft, "train", draft.images_on, uint8=True, alpha=True)
    box = box_from_alpha(draft, train)
    if box is not None:
        draft = dataclasses.replace(draft, aabb=box)
    cfg = draft.validate(train_images=len(train))
    if train.alpha is not None and not wants_alpha(cfg):
        train = dataclasses.replace(train, alpha=None)
    return cfg, train


def load_data(cfg: NeRFConfig, split: str, images_on: str | None = None, uint8: bool = False,
              alpha: bool = False):  # fmt: skip
    """The run's dataset split (a :class:`~warpnerf.data.Dataset`) with its tensors on
    cfg.device (the built-in scene when cfg.data == "builtin"); ``images_on="host"`` keeps the
    images in host memory (a training batch's pixels are gathered there into pinned memory and
    copied, see :class:`NeRFTask`), "auto" does so when they would take more than
    a quarter of the GPU's free memory (see :func:`images_stay_on_host`); None: the run's
    ``cfg.images_on``. ``uint8`` (the training split): images kept in host memory are 8-bit (a
    quarter of the memory; read so from the files with ``images_on="host"``, converted after
    loading with "auto"), turned into float32 on the GPU per batch. ``alpha``: keep the
    images' alpha too (``Dataset.alpha``, where the files have one; moved and converted with
    the images)."""

    have = data_splits(cfg)
    if have is not None and split not in have:  # (never another split's images in its place)
        what = "the built-in scene" if cfg.data == "builtin" else "the data"
        raise UserError(f"{cfg.data}: {what} has no '{split}' split (its splits: "
                        f"{', '.join(have)}); choose one of those")  # fmt: skip
    images_on = cfg.images_on if images_on is None else images_on
    direct = uint8 and images_on == "host" and cfg.device.startswith("cuda")
    ds = _load_split(cfg, split, uint8=direct, alpha=alpha)
    if direct or images_stay_on_host(cfg.device, ds.images, images_on):
        kept = {}
        for k in ("images", "alpha"):
            v = getattr(ds, k)
            if v is not None:
                v = v.cpu()
                if uint8 and v.dtype != torch.uint8:
                    v = (v.clamp(0, 1) * 255).round_().to(torch.uint8)
            kept[k] = v
        return dataclasses.replace(ds, **kept).to(cfg.device, images=False)
    return ds.to(cfg.device)


def data_splits(cfg: NeRFConfig) -> tuple | None:
    """The splits the run's data has of its own: the built-in scene's train and val, the
    Blender split files present (``transforms_{split}.json``), the splits a nerfstudio folder's
    frames name (when every frame names one); None where every split loads (the hold-out rule
    of a single ``transforms.json``, nerfstudio, COLMAP and LLFF: val and test are both the
    held-out images, as documented) or the data cannot be read here (its loader says why)."""
    from ..data.dataset import SPLITS

    if cfg.data == "builtin":
        return ("train", "val")
    root = Path(cfg.data)
    try:
        if root.is_file():  # an index file named in place of its folder (DIR/transforms.json)
            root = root.parent
        if not root.is_dir():
            return None
        from ..data import detect_format

        fmt = cfg.data_format if cfg.data_format != "auto" else detect_format(root, "train")
        if fmt == "blender":
            have = tuple(s for s in SPLITS if (root / f"transforms_{s}.json").is_file())
            return None if (root / "transforms.json").is_file() else have or None
        if fmt == "nerfstudio":
            from ..json_input import read_json

            frames = read_json(root / "transforms.json", "transforms file").get("frames")
            named = [fr.get("split") if isinstance(fr, dict) else None for fr in frames]
            if named and all(isinstance(n, str) and n in SPLITS for n in named):
                return tuple(s for s in SPLITS if s in named)
    except (UserError, OSError, AttributeError, TypeError):  # (the loader reports these)
        return None
    return None


def with_refined_poses(model: RadianceModel, ds, split: str):
    """``ds`` with the run's refined training cameras (``--pose-refine``) when it is the training
    split the corrections were learned for (the same cameras), else ``ds`` as it is: eval of
    the train split, exports and the viewer's frustums show the cameras the model was fitted
    to."""
    poses = getattr(model, "poses", None)
    if poses is None or split != "train" or ds.c2w.shape[0] != poses.n_cameras:
        return ds
    with torch.no_grad():
        c2w = poses.corrected_c2w(ds.c2w.to(poses.rotation.device)).to(ds.c2w)
    return dataclasses.replace(ds, c2w=c2w)


def images_stay_on_host(device, images: torch.Tensor, images_on: str) -> bool:
    """Whether a CUDA run keeps ``images`` in host memory: ``images_on`` is "host", or "auto"
    and they would take more than a quarter of the GPU's free memory (CPU runs: never, they are
    there already)."""
    if images_on == "device" or not str(device).startswith("cuda"):
        return False
    if images_on == "host":
        return True
    free, _ = torch.cuda.mem_get_info(torch.device(device))
    return images.numel() * images.element_size() > free // 4


def _load_split(cfg: NeRFConfig, split: str, uint8: bool = False, alpha: bool = False):
    from ..data import load_dataset

    return load_dataset(
        cfg.data,
        split,
        fmt="auto" if cfg.data == "builtin" else cfg.data_format,
        background=(cfg.background,) * 3,
        downscale=cfg.downscale,
        max_images=cfg.max_images or None,
        holdout=cfg.holdout,
        builtin_size=cfg.builtin_size,
        device=cfg.device,
        uint8=uint8,
        allow_outside=cfg.allow_outside_paths,
        alpha=alpha,
    )


def dataset_rays(
    cfg: NeRFConfig, ds, cam_idx=None, px=None, py=None, image: int | None = None, check=True,
    poses=None,
):  # fmt: skip
    """Rays of a batch of pixels (cam_idx, px, py) or of every pixel of ``image``: undistorted
    when the dataset has distortion, in NDC when the run uses it (``check=False``: cam_idx drawn
    by :func:`random_pixels`, no range check and no host sync). ``poses``: a
    :class:`~warpnerf.fields.poses.CameraCorrection` of ``ds``'s cameras, applied to a batch's
    rays before the NDC map (differentiable in the corrections)."""
    from ..data.cameras import camera_rays, ndc_rays

    if poses is not None and image is None:
        o, d = camera_rays(
            ds.c2w, ds.intrinsics, cam_idx=cam_idx, px=px, py=py, distortion=ds.distortion,
            check=check,
        )  # fmt: skip
        o, d = poses(cam_idx, o, d)
        ndc = cfg.ndc_camera()
        return (o, d) if ndc is None else ndc_rays(o, d, ndc)
    dist = ds.distortion
    if image is not None:
        sl = slice(image, image + 1)
        return camera_rays(
            ds.c2w[sl], ds.intrinsics[sl], ds.width, ds.height,
            distortion=None if dist is None else dist[sl], ndc=cfg.ndc_camera(),
        )  # fmt: skip
    return camera_rays(
        ds.c2w, ds.intrinsics, cam_idx=cam_idx, px=px, py=py, distortion=dist,
        ndc=cfg.ndc_camera(), check=check,
    )  # fmt: skip


def render_rays_of(
    model: RadianceModel, cfg: NeRFConfig, o, d, perturb=False, seed=0, chunk=None, generator=None,
    jitter=None, ray_images=None, ray_offset=0, background=None, distortion=False, near=False,
    on_weights=None,
):  # fmt: skip
    """Renders rays with the run's model: grid marching when it has an occupancy grid
    (``generator``, on the rays' device, jitters the lattice when ``perturb``, unless the draws
    are given as ``jitter`` [n_rays]), otherwise stratified (+ hierarchical) samples (their
    jitter keyed by ``seed`` and the ray's index + ``ray_offset``). ``background``: None (the
    run's colour) or per-ray colours [n_rays, 3] (grid runs). ``distortion`` (grid runs, with
    gradients): add each ray's distortion loss as ``distortion`` [n_rays]
    (:func:`distortion_coordinate` normalises the ray distances). ``near`` (grid or proposal
    runs, with gradients): add each ray's weight within :func:`near_zone` as ``near_weight``
    [n_rays]. ``on_weights`` (grid or proposal runs, rendering): called with each chunk's
    samples ``(ray_indices, t_starts, t_ends, weights)``, ray indices into ``o``
    (:func:`warpnerf.render.render_marched`'s hook; grid runs render by the rounds path). A run
    with proposal sampling (``--sampler proposal``) renders with
    :func:`warpnerf.render_proposal.render_proposal` (its ``jitter`` [n_rays, levels + 1]; with
    gradients it adds ``interlevel`` [n_rays])."""

    def hook(sl):  # (the chunk's ray indices made indices into o)
        if on_weights is None:
            return None
        return lambda ri, *rest: on_weights(ri + sl.start, *rest)

    def near_t(sl):
        return near_zone(cfg, o[sl]) if near else None

    if model.proposal is not None:
        from ..render_proposal import render_proposal

        # the distortion loss in the sampler's own coordinate (the scene one) or another
        s_of_t = distortion and (cfg.distortion_space == "scene" or distortion_coordinate(cfg))
        return render_chunks(o.shape[0], chunk, lambda sl: render_proposal(
            model.proposal, model.coarse, o[sl], d[sl], cfg.near, cfg.far, perturb=perturb,
            generator=generator, jitter=None if jitter is None else jitter[sl],
            background=cfg.background if background is None else background[sl],
            t_threshold=cfg.t_threshold, ray_images=None if ray_images is None else ray_images[sl],
            distortion=s_of_t, near_t=near_t(sl), on_weights=hook(sl),
        ))  # fmt: skip
    if model.grid is not None:
        s_of_t = distortion_coordinate(cfg) if distortion else None
        return render_chunks(
            o.shape[0],
            chunk,
            lambda sl: render_marched(
                model.grid,
                model.coarse,
                o[sl],
                d[sl],
                cfg.near,
                cfg.far,
                perturb=perturb,
                generator=generator,
                background=cfg.background if background is None else background[sl],
                t_threshold=cfg.t_threshold,
                max_samples=cfg.max_samples,
                round_samples=cfg.round_samples,
                half=cfg.render_half,
                tracer=cfg.render_tracer,
                jitter=None if jitter is None else jitter[sl],
                ray_images=None if ray_images is None else ray_images[sl],
                distortion_s=s_of_t,
                near_t=near_t(sl),
                on_weights=hook(sl),
            ),
        )
    if on_weights is not None or near:
        raise ValueError("per-sample weights need a run with an occupancy grid or proposals")
    return render_nerf(
        model.coarse,
        o,
        d,
        cfg.near,
        cfg.far,
        n_coarse=cfg.n_coarse,
        fine=model.fine,
        n_fine=cfg.n_fine,
        perturb=perturb,
        seed=seed,
        background=cfg.background,
        t_threshold=cfg.t_threshold,
        chunk=chunk,
        aabb=cfg.aabb_box(),
        ray_offset=ray_offset,
    )


def distortion_coordinate(cfg: NeRFConfig):
    """The map t -> s in [0, 1) on which the distortion loss measures a ray. With
    ``--distortion-space scene``: t / (t + a) in a contracted scene (a: the inner cube's
    half-size; distant space is squeezed as the contraction squeezes it), (t - near) / (far -
    near) otherwise. With ``mipnerf360``: mip-NeRF 360's (1/near - 1/t) / (1/near - 1/far) (its
    ``construct_ray_warps`` with ``raydist_fn = reciprocal``; t below near counts as near)."""
    if cfg.distortion_space == "mipnerf360":
        g_near, g_far = 1.0 / float(cfg.near), 1.0 / float(cfg.far)
        return lambda t: (g_near - 1.0 / t.clamp_min(float(cfg.near))) / (g_near - g_far)
    if cfg.contract == "on":
        a = float(cfg.aabb)
        return lambda t: t / (t + a)
    near, span = float(cfg.near), max(float(cfg.far) - float(cfg.near), 1e-12)
    return lambda t: (t - near) / span


def near_zone(cfg: NeRFConfig, origins):
    """[n_rays] How far along each ray ``--near-loss`` penalises weight: ``--near-loss-frac``
    times the distance of the ray's origin (its camera) to the scene centre, the origin of the
    normalised scene (captures: the point nearest to every viewing axis; the built-in and
    Blender scenes: their centre)."""
    return float(cfg.near_loss_frac) * origins.detach().norm(dim=-1)


def surface_depth(depth, opacity):
    """Depth of the visible surface (depth / opacity; 0 where nothing is hit)."""
    return torch.where(opacity > 1e-3, depth / opacity.clamp_min(1e-3), torch.zeros_like(depth))


def depth_scale(cfg: NeRFConfig, depth, opacity) -> float | None:
    """What a depth map is normalised by for display: the far plane, or for a contracted
    (unbounded) run, whose far plane lies a thousand scene sizes away, the 99th percentile of
    the visible surface depths (opacity > 0.5) of this frame; None there when no pixel shows a
    surface (the caller falls back to far, or waits for a frame that does)."""
    if cfg.contract != "on":
        return float(cfg.far)
    surf = surface_depth(depth, opacity)
    seen = surf[(opacity > 0.5) & torch.isfinite(surf)]
    if seen.numel() == 0:
        return None
    step = max(1, seen.numel() // 1_000_000)  # (quantile's input limit; strided: all rows)
    return float(torch.quantile(seen[::step].double(), 0.99).clamp_min(1e-6))


MAX_SPP = 64  # eval --spp: rays a pixel at most (each one more whole-image render)


def run_spp(cfg) -> int:
    """Rays a pixel the run's images are rendered with by default (eval, validation): its
    ``--train-spp`` (1 for runs saved before it)."""
    return int(getattr(cfg, "train_spp", None) or 1)


def pixel_points(spp: int) -> list:
    """The ``spp`` points (x, y) in [0, 1)^2 of a pixel that a supersampled image averages:
    1: the centre; a square k^2: the centres of the pixel's k x k cells (stratified); otherwise
    the first ``spp`` points of the R2 sequence (Roberts 2018; low discrepancy). Deterministic,
    so a supersampled evaluation is repeatable."""
    spp = int(spp)
    if not 1 <= spp <= MAX_SPP:
        raise ValueError(f"spp must be in [1, {MAX_SPP}], got {spp}")
    k = math.isqrt(spp)
    if k * k == spp:
        return [((i + 0.5) / k, (j + 0.5) / k) for j in range(k) for i in range(k)]
    g = 1.32471795724474602596  # the plastic number: R2's generator
    a1, a2 = 1.0 / g, 1.0 / (g * g)
    return [((0.5 + a1 * n) % 1.0, (0.5 + a2 * n) % 1.0) for n in range(spp)]


def pixel_corners(width: int, height: int, device) -> tuple:
    """(px, py) [H * W] float32: each pixel's top-left corner (column, row), in the (row,
    column) order of an image's rays; add a point of :func:`pixel_points` for rays through it."""
    py, px = torch.meshgrid(torch.arange(height, device=device, dtype=torch.float32),
                            torch.arange(width, device=device, dtype=torch.float32),
                            indexing="ij")  # fmt: skip
    return px.reshape(-1), py.reshape(-1)


@torch.no_grad()
def render_dataset_image(model, cfg, ds, i, spp: int = 1):
    """rgb [H, W, 3], depth [H, W], opacity [H, W] of image i of a dataset. ``spp`` > 1: the
    mean of ``spp`` renders, each through another point of every pixel (:func:`pixel_points`):
    the box-filtered image a camera with square pixels records (what a dataset downsampled by
    area averaging holds, and what ``--train-spp`` trains)."""
    h, w = ds.height, ds.width
    if spp == 1:
        o, d = dataset_rays(cfg, ds, image=i)
        out = render_rays_of(model, cfg, o, d, chunk=cfg.chunk)
        return out["rgb"].reshape(h, w, 3), out["depth"].reshape(h, w), out["opacity"].reshape(h, w)
    dev, m = ds.c2w.device, h * w
    px, py = pixel_corners(w, h, dev)
    points = torch.tensor(pixel_points(spp), dtype=torch.float32, device=dev)  # [spp, 2]
    # as many points a call as fill one rendering chunk (each ray's result is its own)
    per = max(1, min(spp, int(cfg.chunk) // m)) if cfg.chunk else spp
    total = None
    for p0 in range(0, spp, per):
        pts = points[p0 : p0 + per]
        k = pts.shape[0]
        cam = torch.full((k * m,), int(i), dtype=torch.int64, device=dev)
        xs = (px[None, :] + pts[:, :1]).reshape(-1)  # point-major: [k, H * W]
        ys = (py[None, :] + pts[:, 1:]).reshape(-1)
        o, d = dataset_rays(cfg, ds, cam, xs, ys)
        out = render_rays_of(model, cfg, o, d, chunk=cfg.chunk)
        each = [out[key].reshape(k, m, -1).sum(0) for key in ("rgb", "depth", "opacity")]
        total = each if total is None else [a + b for a, b in zip(total, each)]
    rgb, depth, opacity = (t / spp for t in total)
    return rgb.reshape(h, w, 3), depth.reshape(h, w), opacity.reshape(h, w)


def psnr_of_mse(mse: float) -> float:
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


def load_run(run, device: str | None = None, snapshot: float | None = None,
             averaged: bool = True):  # fmt: skip
    """(cfg, fields, checkpoint dict) of a run folder; device overrides the saved one;
    ``snapshot`` (seconds) loads the snapshot checkpoint kept at that training time
    (``--snapshots``) instead of the latest one. A run trained with ``--ema`` gets its averaged
    weights in the model (what eval, render, mesh, export and the viewer show; see
    :mod:`~warpnerf.train.ema`); ``averaged=False``: the raw weights (a resume trains on them,
    and restores the average from the checkpoint's ``ema``)."""
    run = Path(run)
    cfg_path, ckpt_path = run / "config.json", run / CHECKPOINT
    if not cfg_path.exists() or not ckpt_path.exists():  # (a FIFO or link: its reader names it)
        raise UserError(f"{run}: not a training run (needs config.json and {CHECKPOINT})")
    if snapshot is not None:
        from .loop import snapshot_name

        ckpt_path = run / snapshot_name(float(snapshot))
        if not ckpt_path.is_file() or ckpt_path.is_symlink():
            raise UserError(f"{run}: no snapshot at {snapshot:g} s ({ckpt_path.name} is missing; "
                            "train with --snapshots to keep them)")  # fmt: skip
    from ..json_input import read_run_config

    saved = read_run_config(cfg_path)  # size- and depth-bounded, one-line errors
    if not isinstance(saved, dict):
        raise UserError(f"{cfg_path}: unreadable (expected a JSON object)")
    model = saved.get("model")
    if model == "neural_sdf":
        raise UserError(
            f"{run}: a neural-SDF run (use `warpnerf mesh` or `warpnerf train sdf --resume`)"
        )
    if model is not None and model != MODEL:
        raise UserError(
            f"{run}: a {model} run, not a NeRF run (config.json's model is {model!r}; "
            f"use `warpnerf train {model} --resume`)"
        )
    if saved.get("field") and "grid_res" not in saved:
        saved["grid_res"] = 0  # a run from before the occupancy grid: it had none
    if saved.get("field") and "contract" not in saved:
        saved["contract"] = "off"  # a run from before scene contraction: bounded
    if saved.get("field"):  # runs from before these options had their old fixed defaults
        saved.setdefault("appearance_dim", 0)  # (today's default is data-dependent)
        saved.setdefault("hash_max_res", 2048)
    if device:  # (moved to another device)
        saved["device"] = device
    try:  # (a saved config is resolved and checked: read-only from here)
        cfg = NeRFConfig.from_dict(saved, where=str(cfg_path)).freeze()
    except TypeError as e:
        raise UserError(f"{cfg_path}: unreadable ({e})") from None
    check_device(cfg.device, str(run))
    if cfg.device.startswith("cuda"):  # matrix products as in training
        torch.backends.cuda.matmul.allow_tf32 = cfg.tf32
    keys = ("step", "fields", "optimizer", "generator", "history")
    ckpt = load_checkpoint(ckpt_path, cfg.device, keys)  # (allocates at most its file's size)
    if not isinstance(ckpt["fields"], dict):
        raise UserError(f"{ckpt_path}: not a NeRF checkpoint ('fields' is not a dict)")
    # the config's sizes bounded by the weights the checkpoint holds, before the model is built
    model = build_for_weights(lambda: build_model(cfg), ckpt["fields"], ckpt_path, cfg_path)
    model.load_parts(ckpt["fields"], ckpt_path)  # every part the config gives it, strictly
    from .ema import apply_average, saved_average

    if averaged:  # --ema: the averaged weights replace the raw ones (checked, strictly)
        apply_average(model, cfg, ckpt, ckpt_path)
    else:
        saved_average(cfg, ckpt, ckpt_path)  # (config and checkpoint must agree)
    if hasattr(model.coarse, "set_step"):  # the last step's schedules (open levels, beta), as
        model.coarse.set_step(max(int(ckpt["step"]) - 1, 0))  # its saved buffers hold them
    return cfg, model, ckpt


def validate(model, cfg, val, keep: dict | None = None) -> float:
    """Mean PSNR over the first cfg.val_images validation images, each rendered with the run's
    ``train_spp`` rays a pixel (``keep``, a dict: receives the first image's ``rgb`` [H, W, 3]
    and ``depth`` [H, W])."""
    n = min(cfg.val_images, val.images.shape[0])
    spp = run_spp(cfg)
    mses = []
    for i in range(n):
        rgb, depth, opacity = render_dataset_image(model, cfg, val, i, spp)
        if keep is not None and i == 0:
            keep.update(rgb=rgb, depth=depth, opacity=opacity)
        mses.append(float(((rgb - val.images[i].to(rgb.device)) ** 2).mean()))
    return sum(psnr_of_mse(m) for m in mses) / max(n, 1)
