"""NeRF training: random ray batches across all training images, coarse/fine rendering through the
Warp kernels, Adam with exponential learning-rate decay, periodic validation PSNR, atomic
checkpoints and an exact ``resume`` (model, optimiser, learning-rate schedule and sampling RNG all
restored)."""

from __future__ import annotations

import contextlib
import dataclasses
import math
from pathlib import Path

import torch

from ..errors import UserError
from ..fields.model import RadianceModel, build_model
from ..io import (
    load_checkpoint,
    write_json,
)
from ..ops import random_pixels
from ..render import render_chunks, render_marched, render_nerf
from .logs import TensorBoardLog
from .loop import LoopSettings, Task, adam, claim_run, lock_run, resume_checks, run_loop
from .nerf_config import HASH_FIELDS, NeRFConfig, scene_settings

__all__ = [
    "NeRFConfig", "train_nerf", "load_run", "build_model", "load_data", "render_rays_of",
    "resolve_data", "dataset_rays", "render_dataset_image", "with_refined_poses", "NeRFTask",
    "validate", "distortion_coordinate",
]  # fmt: skip

CHECKPOINT = "checkpoint.pt"
# the adaptive batch's rays per step and rank (a data-parallel run of N ranks: N times as many)
MAX_RAYS_PER_RANK = 1 << 16
OUTPUTS = ("config.json", CHECKPOINT, "history.json")  # what a NeRF run writes in its folder


def resolve_data(cfg: NeRFConfig) -> NeRFConfig:
    """The one step that settles a new run's data-dependent settings: reads what the data
    decides (a COLMAP/LLFF capture's poses: transform, NDC camera, near/far, box), then fills in
    and checks the config (:meth:`NeRFConfig.validate`). A loaded run has them in its
    config.json already."""
    return cfg.validate(scene_settings(cfg))


def load_data(cfg: NeRFConfig, split: str, images_on: str | None = None, uint8: bool = False):
    """The run's dataset split (a :class:`~warpnerf.data.Dataset`) with its tensors on
    cfg.device (the built-in scene when cfg.data == "builtin"); ``images_on="host"`` keeps the
    images in host memory (a training batch's pixels are gathered there into pinned memory and
    copied, see :class:`NeRFTask`), "auto" does so when they would take more than
    a quarter of the GPU's free memory (see :func:`images_stay_on_host`); None: the run's
    ``cfg.images_on``. ``uint8`` (the training split): images kept in host memory are 8-bit (a
    quarter of the memory; read so from the files with ``images_on="host"``, converted after
    loading with "auto"), turned into float32 on the GPU per batch."""

    images_on = cfg.images_on if images_on is None else images_on
    direct = uint8 and images_on == "host" and cfg.device.startswith("cuda")
    ds = _load_split(cfg, split, uint8=direct)
    if direct or images_stay_on_host(cfg.device, ds.images, images_on):
        images = ds.images.cpu()
        if uint8 and images.dtype != torch.uint8:
            images = (images.clamp_(0, 1) * 255).round_().to(torch.uint8)
        return dataclasses.replace(ds, images=images).to(cfg.device, images=False)
    return ds.to(cfg.device)


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


def _load_split(cfg: NeRFConfig, split: str, uint8: bool = False):
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
    jitter=None, ray_images=None, ray_offset=0, background=None, distortion=False,
):  # fmt: skip
    """Renders rays with the run's model: grid marching when it has an occupancy grid
    (``generator``, on the rays' device, jitters the lattice when ``perturb``, unless the draws
    are given as ``jitter`` [n_rays]), otherwise stratified (+ hierarchical) samples (their
    jitter keyed by ``seed`` and the ray's index + ``ray_offset``). ``background``: None (the
    run's colour) or per-ray colours [n_rays, 3] (grid runs). ``distortion`` (grid runs, with
    gradients): add each ray's distortion loss as ``distortion`` [n_rays]
    (:func:`distortion_coordinate` normalises the ray distances)."""
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
                jitter=None if jitter is None else jitter[sl],
                ray_images=None if ray_images is None else ray_images[sl],
                distortion_s=s_of_t,
            ),
        )
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
    """The map t -> s in [0, 1) on which the distortion loss measures a ray: t / (t + a) in a
    contracted scene (a: the inner cube's half-size; distant space is squeezed as the
    contraction squeezes it), (t - near) / (far - near) otherwise."""
    if cfg.contract == "on":
        a = float(cfg.aabb)
        return lambda t: t / (t + a)
    near, span = float(cfg.near), max(float(cfg.far) - float(cfg.near), 1e-12)
    return lambda t: (t - near) / span


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


@torch.no_grad()
def render_dataset_image(model, cfg, ds, i):
    """rgb [H, W, 3], depth [H, W], opacity [H, W] of image i of a dataset."""
    h, w = ds.height, ds.width
    o, d = dataset_rays(cfg, ds, image=i)
    out = render_rays_of(model, cfg, o, d, chunk=cfg.chunk)
    return out["rgb"].reshape(h, w, 3), out["depth"].reshape(h, w), out["opacity"].reshape(h, w)


def _psnr(mse: float) -> float:
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


def _optimizer(cfg, params, poses=None, capturable=False):
    """Adam over ``params``; with pose corrections (``poses``, whose parameters are among
    ``params``) a second group for them at ``pose_lr`` (``lr_scale``: the loop's schedule
    scales it with the main learning rate)."""
    groups = params
    if poses is not None:
        own = {id(p) for p in poses.parameters()}
        rest = [p for p in params if id(p) not in own]
        scale = cfg.pose_lr / cfg.lr
        groups = [{"params": rest}, {"params": list(poses.parameters()), "lr_scale": scale}]
    if cfg.field in HASH_FIELDS:  # instant-ngp's Adam: tiny eps (sparse, small table gradients)
        return adam(groups, capturable, lr=cfg.lr, betas=(0.9, 0.99), eps=1e-15)
    return adam(groups, capturable, lr=cfg.lr)


def load_run(run, device: str | None = None, snapshot: float | None = None):
    """(cfg, fields, checkpoint dict) of a run folder; device overrides the saved one;
    ``snapshot`` (seconds) loads the snapshot checkpoint kept at that training time
    (``--snapshots``) instead of the latest one."""
    run = Path(run)
    cfg_path, ckpt_path = run / "config.json", run / CHECKPOINT
    if not cfg_path.is_file() or not ckpt_path.is_file():
        raise UserError(f"{run}: not a training run (needs config.json and {CHECKPOINT})")
    if snapshot is not None:
        from .loop import snapshot_name

        ckpt_path = run / snapshot_name(float(snapshot))
        if not ckpt_path.is_file() or ckpt_path.is_symlink():
            raise UserError(f"{run}: no snapshot at {snapshot:g} s ({ckpt_path.name} is missing; "
                            "train with --snapshots to keep them)")  # fmt: skip
    from ..data._json import read_json

    saved = read_json(cfg_path, "run config")  # size- and depth-bounded, one-line errors
    if not isinstance(saved, dict):
        raise UserError(f"{cfg_path}: unreadable (expected a JSON object)")
    model = saved.get("model")
    if model == "neural_sdf":
        raise UserError(
            f"{run}: a neural-SDF run (use `warpnerf mesh` or `warpnerf train sdf --resume`)"
        )
    if model is not None:
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
    try:
        cfg = NeRFConfig.from_dict(saved, where=str(cfg_path))
    except TypeError as e:
        raise UserError(f"{cfg_path}: unreadable ({e})") from None
    if device:
        cfg.device = device
    if cfg.device.startswith("cuda") and not torch.cuda.is_available():
        raise UserError(
            f"{run}: trained on {cfg.device}, which is not available here; pass --device cpu"
        )
    if cfg.device.startswith("cuda"):  # matrix products as in training
        torch.backends.cuda.matmul.allow_tf32 = cfg.tf32
    model = build_model(cfg)
    keys = ("step", "fields", "optimizer", "generator", "history")
    ckpt = load_checkpoint(ckpt_path, cfg.device, keys)
    if not isinstance(ckpt["fields"], dict):
        raise UserError(f"{ckpt_path}: not a NeRF checkpoint ('fields' is not a dict)")
    model.load_parts(ckpt["fields"], ckpt_path)  # every part the config gives it, strictly
    if hasattr(model.coarse, "set_step"):  # the last step's schedules (open levels, beta), as
        model.coarse.set_step(max(int(ckpt["step"]) - 1, 0))  # its saved buffers hold them
    return cfg, model, ckpt


def train_nerf(
    cfg: NeRFConfig,
    run,
    resume: bool = False,
    progress: bool = True,
    log=print,
    device: str | None = None,
    hooks=(),
    tensorboard: int = 0,
    dist=None,
):
    """Trains (or resumes) a run in folder ``run``; returns the history dict.

    ``hooks``: :class:`~warpnerf.train.loop.LoopHook` s that watch the training (the live
    viewer); ``tensorboard`` N > 0: also TensorBoard event files in RUN/tensorboard, a record
    every N steps (the command line's default: 10).

    On resume only ``cfg.iters`` (the total to reach) and ``cfg.max_seconds`` are taken from
    ``cfg``; everything else comes from the run's config.json, and ``device`` (if given) moves it.

    ``dist`` (:class:`~warpnerf.train.distributed.Dist`): this process is one rank of a
    data-parallel run (``torchrun``); only rank 0 takes the folder's lock and writes files.
    """
    with contextlib.ExitStack() as locks:  # the run folder's lock, held to the end
        return _train_nerf(cfg, Path(run), resume, progress, log, device, locks, hooks,
                           tensorboard, dist)  # fmt: skip


def _train_nerf(cfg, run: Path, resume, progress, log, device, locks, hooks, tensorboard,
                dist=None):  # fmt: skip
    main = dist is None or dist.main
    if resume:
        if main:
            lock_run(run, locks)
        saved_cfg, model, ckpt = load_run(run, device)
        if main:
            resume_checks(run, ckpt["step"], cfg.iters, OUTPUTS)
        saved_cfg.iters, saved_cfg.max_seconds = cfg.iters, cfg.max_seconds
        cfg = saved_cfg
        cfg.validate()
    else:
        resolve_data(cfg)
        if (run / CHECKPOINT).exists():
            raise UserError(
                f"{run}: already holds a run; pass --resume to continue it or choose another --out"
            )
        model, ckpt = None, None  # (built once the data is known: appearance codes count images)
    if cfg.lr_decay_steps <= 0:
        cfg.lr_decay_steps = cfg.iters
    # Data first: a bad dataset stops the run before anything is written.
    train = load_data(cfg, "train", cfg.images_on, uint8=True)  # (8-bit when kept on the host)
    val = load_data(cfg, "val", cfg.images_on) if cfg.val_images > 0 else None
    if model is None:
        if cfg.appearance_dim:  # one code per training image
            cfg.appearance_images = len(train)
        if cfg.pose_refine:  # one correction per training camera
            cfg.pose_images = len(train)
        model = build_model(cfg)
    else:
        for on, count, what in (
            (cfg.appearance_dim, cfg.appearance_images, "appearance codes"),
            (cfg.pose_refine, cfg.pose_images, "pose corrections"),
        ):
            if on and count != len(train):
                raise UserError(
                    f"{run}: the run has {what} for {count} training images, but the training "
                    f"split now has {len(train)}; resume with the data it was trained on"
                )  # fmt: skip
    tb = [TensorBoardLog(run, tensorboard)] if tensorboard and main else []  # (writes nothing)
    if main:
        if not resume:
            claim_run(run, locks, OUTPUTS, CHECKPOINT)
        write_json(run / "config.json", cfg.to_dict())
    task = NeRFTask(cfg, model, train, val, log, dist=dist)
    if not resume and getattr(cfg, "beta_final", 0) > 0 and model.grid is not None:
        if cfg.beta_final < model.grid.dt:  # measured on materials: val PSNR 30.4 -> 25.6 dB
            log(f"warning: --beta-final {cfg.beta_final:g} is below the marching step "
                f"{model.grid.dt:.4g}: the density's transition will be shorter than a step "
                "and renders alias into speckle; pass a --march-step below it")  # fmt: skip
    if ckpt is not None:
        task.resume(ckpt, run, log)
    if cfg.device.startswith("cuda"):
        torch.backends.cuda.matmul.allow_tf32 = cfg.tf32
    settings = LoopSettings.of(cfg, "train nerf", val_every=cfg.val_every if val is not None else 0)
    hooks = [*hooks, *tb]
    return run_loop(
        task, settings, run=run, checkpoint=CHECKPOINT, resume_from=ckpt, progress=progress,
        log=log, hooks=hooks,
    )  # fmt: skip


class NeRFTask(Task):
    """NeRF and VolSDF as a :class:`~warpnerf.train.loop.Task`: random ray batches across all
    training images, coarse/fine or occupancy-grid rendering, the photometric loss (plus the
    coarse pass's and VolSDF's eikonal term), validation PSNR."""

    history_keys = ("psnr", "val_step", "val_psnr")
    validation_keys = ("val_psnr",)

    def __init__(self, cfg, model: RadianceModel, train, val, log=print, dist=None):
        self.cfg, self.model, self.train, self.val = cfg, model, train, val
        self.log = log
        self.dist = dist  # data-parallel: this rank renders its share of each global batch
        self.n_img, self.h, self.w = train.images.shape[:3]
        self.flat = train.images.reshape(-1, 3)
        # images in host memory on a CUDA run (--images-on): each batch's pixels are gathered
        # on the host, by the indices drawn there, and copied without blocking
        self.host_images = self.flat.device.type == "cpu" and cfg.device.startswith("cuda")
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.grid = model.grid
        # The grid's updates and lattice jitter draw from a generator on the device (saved too).
        self.grid_gen = None
        if self.grid is not None:
            self.grid_gen = torch.Generator(device=cfg.device).manual_seed(cfg.seed + 1)
        self.batch = cfg.batch
        self._kept = None  # data-parallel: the last step's global sample count (on the device)
        self.keypoints = None  # --depth-loss: the training split's sparse-point observations
        if cfg.depth_loss > 0:
            kp = train.keypoints
            if kp is None or cfg.ndc_camera() is not None:
                raise UserError(
                    f"--depth-loss needs a COLMAP capture with sparse points (points3D) and "
                    f"world-space rays; {cfg.data} has "
                    + ("NDC rays (forward-facing)" if kp is not None else "no point observations")
                )  # fmt: skip
            self.keypoints = {k: v.to(cfg.device) for k, v in kp.items()}
        self.graph = self._graph_step(log)

    def _graph_step(self, log):
        """The static-shape step (:mod:`~warpnerf.train.graph_step`) when ``--cuda-graph``
        and the run allow it, else None."""
        from .graph_step import GraphStep, unsupported

        mode = getattr(self.cfg, "cuda_graph", "auto")
        if mode == "on" and not self.cfg.device.startswith("cuda"):
            raise UserError("--cuda-graph on needs --device cuda (CPU runs use the eager step)")
        if mode == "off" or not self.cfg.device.startswith("cuda"):
            return None
        why = unsupported(self.cfg, self.model, self)
        if why is not None:
            if mode == "on":
                raise UserError(f"--cuda-graph on: this run cannot be captured ({why})")
            return None
        return GraphStep(self, capture=True)

    def resume(self, ckpt, run, log):
        self.gen.set_state(ckpt["generator"].cpu())  # map_location may have moved it
        self.batch = ckpt.get("batch", self.cfg.batch)
        if self.graph is not None:  # the static-shape step's sizes, when the run had them
            self.graph.restore(ckpt.get("static_shape"))
        if self.grid_gen is not None:
            if ckpt.get("grid_generator_device") == self.grid_gen.device.type:
                self.grid_gen.set_state(ckpt.get("grid_generator").cpu())
            else:
                log(f"{run}: resumed on another device type; the grid's random stream restarts "
                    "from the seed (the continuation is not bit-exact)")  # fmt: skip

    def parameters(self):
        return list(self.model.parameters())

    def optimizer(self, params, lr):
        return _optimizer(self.cfg, params, self.model.poses, capturable=self.graph is not None)

    def train_step(self, step, opt, params):
        """The static-shape step captured in a CUDA graph (None: the eager one, as for the
        first step, whose counts size the buffers)."""
        if self.graph is None or self.graph.last is None:
            return None
        self._grid_update(step)
        whole = self.graph.run(step, opt, params)
        if whole is None:  # the capture failed: the eager step from now on (said once)
            self.log(f"CUDA graph capture failed ({self.graph.failed}); training goes on with "
                     "the eager step (--cuda-graph off)")  # fmt: skip
            self.graph = None
            return self._eager_once(step, opt, params)
        return whole

    def _eager_once(self, step, opt, params):
        """This step the eager way (its grid update is done), for a failed capture."""
        every, self.cfg.grid_every = self.cfg.grid_every, 1 << 30
        try:
            loss, terms = self.loss(step)
        finally:
            self.cfg.grid_every = every
        opt.zero_grad(set_to_none=True)
        loss.backward()
        from ._signals import nonfinite_flags

        flags = nonfinite_flags(loss, params)
        opt.step()
        return loss, terms, flags

    def _next_batch(self, n_kept: int) -> None:
        """The next step's rays, aiming at ``target_samples`` samples from this step's
        ``n_kept`` (the global batch's), at most MAX_RAYS_PER_RANK rays per rank."""
        if self.cfg.target_samples > 0:
            batch = int(self.batch * self.cfg.target_samples / max(n_kept, 1))
            ranks = 1 if self.dist is None else self.dist.world
            self.batch = min(max(batch, 64), MAX_RAYS_PER_RANK * ranks)

    def _settle_batch(self) -> None:
        """Data-parallel: sizes the batch from the previous step's global sample count, summed
        on the device during that step (read here, after the step's end-of-step sync, so the
        read waits for nothing)."""
        if self._kept is not None:
            kept, self._kept = self._kept, None
            self._next_batch(int(kept.item()))

    def loss(self, step):
        self._settle_batch()
        cfg, model, grid = self.cfg, self.model, self.grid
        self._grid_update(step)
        cam, px, py, idx = random_pixels(
            self.n_img, self.w, self.h, self.batch, generator=self.gen, device=cfg.device,
            host_index=self.host_images,
        )  # fmt: skip
        n = cam.shape[0]  # the global batch (every rank draws it whole)
        sl, jitter, scale, bg = slice(0, n), None, 1.0, None
        if grid is not None:  # the lattice jitter (and backgrounds), drawn for all the batch's rays
            jitter = torch.rand(n, device=cfg.device, generator=self.grid_gen)
            if cfg.contract == "on":  # unbounded: no fixed colour behind the scene
                bg = torch.rand(n, 3, device=cfg.device, generator=self.grid_gen)
        if self.dist is not None:  # this rank's share
            sl = self.dist.share(n)
            jitter = None if jitter is None else jitter[sl]
            bg = None if bg is None else bg[sl]
            # the share's mean loss weighted so that the ranks' average is the batch's mean
            scale = (sl.stop - sl.start) * self.dist.world / max(n, 1)
            cam, px, py = cam[sl], px[sl], py[sl]
            idx = (idx[0][sl], idx[1][sl]) if self.host_images else idx[sl]
        if self.host_images:
            idx, idx_host = idx
            target = torch.empty(idx_host.shape[0], 3, dtype=self.flat.dtype, pin_memory=True)
            torch.index_select(self.flat, 0, idx_host, out=target)
            target = target.to(cfg.device, non_blocking=True)
            if target.dtype == torch.uint8:  # 8-bit host images: their float values on the GPU
                target = target.to(torch.float32).div_(255.0)
        o, d = dataset_rays(cfg, self.train, cam, px, py, check=False,  # (our own indices)
                            poses=model.poses)  # fmt: skip
        seed = cfg.seed * 1000003 + step  # (stratified jitter: keyed by the global ray index)
        images = cam if cfg.appearance_dim else None  # each ray's image: its appearance code
        out = render_rays_of(model, cfg, o, d, perturb=True, seed=seed, generator=self.grid_gen,
                             jitter=jitter, ray_images=images, ray_offset=sl.start,
                             background=bg, distortion=cfg.distortion_loss > 0)  # fmt: skip
        n_kept = out.get("n_kept")
        terms = {}
        if grid is not None:
            terms["batch"] = self.batch
            if self.dist is not None:  # the global batch's samples: summed on the device, no
                # host wait mid-step; the next step's batch is sized from it (_settle_batch)
                kept = torch.tensor([float(n_kept)], dtype=torch.float64, device=cfg.device)
                self._kept = self.dist.sum_(kept)
                terms["samples_per_ray"] = (self._kept / self.batch).reshape(())
            else:
                terms["samples_per_ray"] = n_kept / self.batch
                if self.graph is not None:  # the static-shape step sizes its buffers from these
                    self.graph.last = (self.batch, out["n_marched"], n_kept)
                    terms["dropped_samples"] = 0
                self._next_batch(n_kept)
        if not self.host_images:
            target = self.flat[idx]
            if target.dtype == torch.uint8:  # an 8-bit split held on the training device
                target = target.to(torch.float32).div_(255.0)
        loss_fine = torch.mean((out["rgb"] - target) ** 2)
        if scale != 1.0:
            loss_fine = loss_fine * scale
        terms["psnr"] = loss_fine.detach()
        loss = loss_fine
        if "distortion" in out:  # mip-NeRF 360's distortion loss, the rays' mean
            dist_loss = out["distortion"].mean() * scale
            terms["distortion"] = dist_loss.detach()
            loss = loss + cfg.distortion_loss * dist_loss
        if self.keypoints is not None:  # the depth prior at sparse points (the same on every
            # rank: every rank draws and renders the whole set, the ranks' mean is the term)
            depth_term = self._depth_term(seed)
            terms["depth"] = depth_term.detach()
            loss = loss + cfg.depth_loss * depth_term
        coarse = out.get("rgb_coarse")
        if coarse is not None and coarse.requires_grad and model.fine is not None:
            loss = loss + torch.mean((coarse - target) ** 2) * scale  # (scale 1: exact)
        if model.kind == "sdf":  # eikonal on the rendered samples and on random box points
            f = model.coarse
            box = (torch.rand(cfg.batch, 3, generator=self.gen) * 2 - 1).to(cfg.device) * cfg.aabb
            if self.dist is None:
                aux = model.aux_losses().get("eikonal")  # (none when no sample was coloured)
                eik = f.eikonal(box) if aux is None else 0.5 * (aux + f.eikonal(box))
            else:  # (every rank draws the same box points: their term needs no exchange)
                eik = self._dp_eikonal(model.eikonal_parts(), f.eikonal(box))
            loss = loss + cfg.eikonal_weight * eik
            terms["beta"] = f.beta.detach()
        return loss, terms

    def batch_rays(self, cam, px, py):
        """Rays of a training batch's pixels (indices the task drew itself: no range check)."""
        return dataset_rays(self.cfg, self.train, cam, px, py, check=False,
                            poses=self.model.poses)  # fmt: skip

    def distortion_map(self):
        """The ray coordinate of the distortion loss, or None without the loss."""
        return distortion_coordinate(self.cfg) if self.cfg.distortion_loss > 0 else None

    def _grid_update(self, step: int) -> None:
        """The field's schedules for ``step`` and, every ``grid_every`` steps, the occupancy
        grid's update (in place: a captured step reads the grid's own buffers)."""
        cfg, grid, field = self.cfg, self.grid, self.model.coarse
        if hasattr(field, "set_step"):  # coarse-to-fine hash levels (a function of the step)
            field.set_step(step)
        if grid is not None and step % cfg.grid_every == 0:
            if hasattr(field, "grid_density"):  # an SDF: the densest point of each cell
                lo, hi = grid.box[:3], grid.box[3:]
                r = 0.5 * math.sqrt(sum(((b - a) / grid.res) ** 2 for a, b in zip(lo, hi)))
                grid.update(lambda x: field.grid_density(x, r), self.grid_gen)
            else:
                grid.update(lambda x: field.density(x)[0], self.grid_gen)

    def _depth_term(self, seed: int):
        """--depth-loss: ``depth_rays`` observations of sparse points drawn from the training
        images, rendered like the step's rays; the mean Huber loss (delta 0.1) of each ray's
        depth over the point's distance along it, against 1 (missing opacity and weight in
        front of or behind the point both raise it), over the rays whose point lies between
        the near and far planes."""
        cfg, kp = self.cfg, self.keypoints
        j = torch.randint(kp["cam"].shape[0], (cfg.depth_rays,), generator=self.gen)
        if kp["cam"].device.type == "cuda":  # (a pinned copy does not wait for the GPU)
            j = j.pin_memory()
        j = j.to(kp["cam"].device, non_blocking=True)
        cam = kp["cam"][j]
        o, d = dataset_rays(cfg, self.train, cam, kp["px"][j], kp["py"][j], check=False,
                            poses=self.model.poses)  # fmt: skip
        z = ((kp["xyz"][j] - o) * d).sum(-1)  # the point's distance along the ray
        images = cam if cfg.appearance_dim else None
        out = render_rays_of(self.model, cfg, o, d, perturb=True, seed=seed + (1 << 20),
                             generator=self.grid_gen, ray_images=images)  # fmt: skip
        # a point nearer than the near plane (or behind a refined camera) cannot be reached:
        # its ray gets no weight (a tiny z would make the ratio's gradient explode)
        valid = (z > cfg.near) & (z < cfg.far)
        ratio = out["depth"] / torch.where(valid, z, torch.ones_like(z))
        per_ray = torch.nn.functional.huber_loss(
            ratio, torch.ones_like(ratio), delta=0.1, reduction="none"
        )
        return (per_ray * valid).sum() / valid.sum().clamp_min(1)

    def _dp_eikonal(self, parts, box_term):
        """A data-parallel rank's eikonal term, such that the ranks' average is the one
        process's: each field's mean at the rendered samples becomes this rank's sum over the
        samples of every rank (their counts summed on the device, no host wait), times the
        number of ranks; without any rendered sample anywhere, the box points' term alone."""
        dev = box_term.device
        counts = torch.tensor([float(n) for _, n in parts], dtype=torch.float64)
        if dev.type == "cuda":  # (a pinned copy does not wait for the GPU)
            counts = counts.pin_memory().to(dev, non_blocking=True)
        total = self.dist.sum_(counts.to(dev))
        aux = box_term.new_zeros(())
        for k, (mean, n) in enumerate(parts):
            if mean is not None:
                share = (n * self.dist.world / total[k].clamp_min(1.0)).to(mean.dtype)
                aux = aux + mean * share
        return torch.where(total.sum() > 0, 0.5 * (aux + box_term), box_term)

    def record(self, history, terms):
        terms = dict(terms, psnr=_psnr(terms["psnr"]))  # the fine pass's MSE, as PSNR
        if "_marched" in terms:  # a static-shape step: its counts size the next one
            marched, live = int(terms.pop("_marched")), int(terms.pop("_live"))
            self.graph.last = (terms["batch"], marched, live)
            self._next_batch(live)
        super().record(history, terms)

    def validate(self, step):
        keep = {}
        psnr = validate(self.model, self.cfg, self.val, keep)
        if keep:  # the first image, for the TensorBoard log: prediction | truth, and depth
            rgb, depth = keep["rgb"], keep["depth"]
            self.val_images = {
                "rgb": torch.cat([rgb.cpu(), self.val.images[0].cpu()], 1).numpy(),
                "depth": (
                    surface_depth(depth, keep["opacity"])
                    / max(depth_scale(self.cfg, depth, keep["opacity"]) or self.cfg.far, 1e-6)
                )
                .clamp(0, 1)
                .cpu()
                .numpy(),  # fmt: skip
            }
        return {"val_psnr": psnr}

    def validation_text(self, history):
        return f"train psnr {history['psnr'][-1]:.2f}, val psnr {history['val_psnr'][-1]:.2f}"

    def postfix(self, history):
        return {"loss": f"{history['loss'][-1]:.4f}", "psnr": f"{history['psnr'][-1]:.2f}"}

    def state(self):
        self._settle_batch()  # (the checkpoint holds the next step's batch, as on one process)
        state = {
            "fields": {  # (the layout of runs from before the model object)
                k: (v.state_dict() if v is not None else None)
                for k, v in self.model.parts().items()
            },
            "generator": self.gen.get_state(),
            "config": self.cfg.to_dict(),
            "batch": self.batch,
        }
        if self.grid_gen is not None:
            state["grid_generator"] = self.grid_gen.get_state()
            state["grid_generator_device"] = self.grid_gen.device.type
        if self.graph is not None and self.graph.last is not None:  # a resume keeps the shapes
            state["static_shape"] = {"last": list(self.graph.last),
                                     "current": list(self.graph.current or ())}  # fmt: skip
        return state


def validate(model, cfg, val, keep: dict | None = None) -> float:
    """Mean PSNR over the first cfg.val_images validation images (``keep``, a dict: receives
    the first image's ``rgb`` [H, W, 3] and ``depth`` [H, W])."""
    n = min(cfg.val_images, val.images.shape[0])
    mses = []
    for i in range(n):
        rgb, depth, opacity = render_dataset_image(model, cfg, val, i)
        if keep is not None and i == 0:
            keep.update(rgb=rgb, depth=depth, opacity=opacity)
        mses.append(float(((rgb - val.images[i].to(rgb.device)) ** 2).mean()))
    return sum(_psnr(m) for m in mses) / max(n, 1)
