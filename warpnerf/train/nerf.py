"""NeRF training: random ray batches across all training images, coarse/fine rendering through the
Warp kernels, Adam with exponential learning-rate decay, periodic validation PSNR, atomic
checkpoints and an exact ``resume`` (model, optimiser, learning-rate schedule and sampling RNG all
restored). Loading and rendering a saved run lives in :mod:`warpnerf.train.nerf_run` (its names
are re-exported here for the callers that import them from this module)."""

from __future__ import annotations

import contextlib
import math
from dataclasses import replace
from pathlib import Path

import torch

from ..data.cameras import frustum_bounds
from ..errors import UserError
from ..fields.mlp import mlp_precision
from ..fields.model import RadianceModel, build_model
from ..ops import random_pixels
from ..outputs import write_json
from .ema import KEY as EMA_KEY
from .ema import WeightAverage
from .logs import TensorBoardLog
from .loop import LoopSettings, Task, adam, claim_run, lock_run, resume_checks, run_loop
from .nerf_config import MODEL as NERF_MODEL
from .nerf_config import NeRFConfig
from .nerf_run import (
    CHECKPOINT,
    dataset_rays,
    depth_scale,
    distortion_coordinate,
    images_stay_on_host,
    load_data,
    load_run,
    near_zone,
    psnr_of_mse,
    render_dataset_image,
    render_rays_of,
    resolve_data,
    settle_new_run,
    surface_depth,
    validate,
    with_refined_poses,
)
from .recipe import mask_weight, random_background, wants_alpha
from .step_loss import LossSettings, step_loss
from .supersample import expand_rows, pixel_means, sub_offsets, sub_rays

__all__ = [
    "NeRFConfig", "train_nerf", "load_run", "build_model", "load_data", "render_rays_of",
    "resolve_data", "dataset_rays", "render_dataset_image", "with_refined_poses", "NeRFTask",
    "validate", "distortion_coordinate", "images_stay_on_host", "depth_scale", "surface_depth",
    "CHECKPOINT",
]  # fmt: skip

# the adaptive batch's rays per step and rank (a data-parallel run of N ranks: N times as many)
MAX_RAYS_PER_RANK = 1 << 16
OUTPUTS = ("config.json", CHECKPOINT, "history.json")  # what a NeRF run writes in its folder


def _optimizer(cfg, params, poses=None, capturable=False, model=None):
    """Adam over ``params``; with pose corrections (``poses``, whose parameters are among
    ``params``) a second group for them at ``pose_lr`` (``lr_scale``: the loop's schedule
    scales it with the main learning rate). The recipe's options (:mod:`~warpnerf.train.optim`,
    they need ``model``): ``--sparse-adam``, the hash tables in a group of their own whose
    entries without a gradient stay untouched (:class:`~warpnerf.train.optim.LazyAdam`);
    ``--mlp-weight-decay W``, the MLPs' weight matrices in a group with L2 ``W``."""
    groups = params
    if poses is not None:
        own = {id(p) for p in poses.parameters()}
        rest = [p for p in params if id(p) not in own]
        scale = cfg.pose_lr / cfg.lr
        groups = [{"params": rest}, {"params": list(poses.parameters()), "lr_scale": scale}]
    lazy = bool(getattr(cfg, "sparse_adam", False)) and model is not None
    decay = float(getattr(cfg, "mlp_weight_decay", 0.0)) if model is not None else 0.0
    cls = torch.optim.Adam
    if lazy or decay > 0:
        from .optim import LazyAdam, hash_tables, mlp_weights, split_groups

        tables = hash_tables(model) if lazy else ()
        weights = mlp_weights(model, skip=poses) if decay > 0 else ()
        groups = split_groups(groups, tables, weights, decay)
        cls = LazyAdam if tables else cls
    if cfg.traits.hash:  # instant-ngp's Adam: tiny eps (sparse, small table gradients)
        return adam(groups, capturable, cls=cls, lr=cfg.lr, betas=(0.9, 0.99), eps=1e-15)
    return adam(groups, capturable, cls=cls, lr=cfg.lr)


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
        saved_cfg, model, ckpt = load_run(run, device, averaged=False)  # (trains the raw ones)
        if main:
            resume_checks(run, ckpt["step"], cfg.iters, OUTPUTS)
        cfg = replace(saved_cfg, iters=cfg.iters, max_seconds=cfg.max_seconds).validate()
        # Data first: a bad dataset stops the run before anything is written.
        train = load_data(cfg, "train", cfg.images_on, uint8=True,  # (8-bit when kept on the host)
                          alpha=wants_alpha(cfg))  # fmt: skip
    else:
        # the data's training split read, then the config resolved, checked and frozen, once
        cfg, train = settle_new_run(cfg)
        if (run / CHECKPOINT).exists():
            raise UserError(
                f"{run}: already holds a run; pass --resume to continue it or choose another --out"
            )
        model, ckpt = None, None  # (built once the data is known: appearance codes count images)
    val = load_data(cfg, "val", cfg.images_on) if cfg.val_images > 0 else None
    if model is None:
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
    # the task before any file: what it refuses (--depth-loss without points, --cuda-graph on
    # for a run it cannot capture) leaves no run folder behind
    task = NeRFTask(cfg, model, train, val, log, dist=dist)
    if main:
        if not resume:
            claim_run(run, locks, OUTPUTS, CHECKPOINT)
        write_json(run / "config.json", cfg.to_dict())
    if not resume and getattr(cfg, "beta_final", 0) > 0 and model.grid is not None:
        if cfg.beta_final < model.grid.dt:  # measured on materials: val PSNR 30.4 -> 25.6 dB
            log(f"warning: --beta-final {cfg.beta_final:g} is below the marching step "
                f"{model.grid.dt:.4g}: the density's transition will be shorter than a step "
                "and renders alias into speckle; pass a --march-step below it")  # fmt: skip
    if ckpt is not None:
        task.resume(ckpt, run, log)
    if cfg.device.startswith("cuda"):
        torch.backends.cuda.matmul.allow_tf32 = cfg.tf32
    settings = LoopSettings.of(
        cfg, "train nerf", cfg.snapshots, val_every=cfg.val_every if val is not None else 0
    )
    hooks = [*hooks, *tb]
    return run_loop(
        task, settings, run=run, checkpoint=CHECKPOINT, resume_from=ckpt, progress=progress,
        log=log, hooks=hooks,
    )  # fmt: skip


class NeRFTask(Task):
    """NeRF and VolSDF as a :class:`~warpnerf.train.loop.Task`: random ray batches across all
    training images, coarse/fine or occupancy-grid rendering, the photometric loss (plus the
    coarse pass's and VolSDF's eikonal term), validation PSNR."""

    method = NERF_MODEL  # its kind of run (train/methods.py)

    history_keys = ("psnr", "val_step", "val_psnr")
    validation_keys = ("val_psnr",)

    def __init__(self, cfg, model: RadianceModel, train, val, log=print, dist=None):
        self.cfg, self.model, self.train, self.val = cfg, model, train, val
        self.log = log
        self._grid_step = None  # the step whose grid update is done
        self.dist = dist  # data-parallel: this rank renders its share of each global batch
        self.n_img, self.h, self.w = train.images.shape[:3]
        self.flat = train.images.reshape(-1, 3)
        # --random-background: each training ray seen over a random colour; the pixels of an
        # RGBA dataset are re-composited onto it by their alpha (losses.composite_target)
        self.random_bg = random_background(cfg, train)
        # --mask-loss: the opacity's cross-entropy against the alpha (losses.opacity_term)
        self.mask_w = mask_weight(cfg, train)
        if getattr(cfg, "mask_loss", 0) > 0 and self.mask_w == 0:
            log(f"--mask-loss {cfg.mask_loss:g}: the training images have no alpha; no mask loss")
        # the step's loss terms and weights (train/step_loss.py; both steps assemble it there)
        self.loss_settings = LossSettings.of(cfg, model, self.mask_w)
        self.flat_alpha = None
        if (self.random_bg or self.mask_w > 0) and train.alpha is not None:
            self.flat_alpha = train.alpha.reshape(-1)
        # images in host memory on a CUDA run (--images-on): each batch's pixels are gathered
        # on the host, by the indices drawn there, and copied without blocking
        self.host_images = self.flat.device.type == "cpu" and cfg.device.startswith("cuda")
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.grid = model.grid
        # The grid's updates and lattice jitter draw from a generator on the device (saved too).
        self.grid_gen = None
        if self.grid is not None:
            self.grid_gen = torch.Generator(device=cfg.device).manual_seed(cfg.seed + 1)
            # --view-cull: a new grid (a resumed one has its mask) empties the cells outside
            # every training camera's frustum for good (OccupancyGrid.cull)
            if getattr(cfg, "view_cull", False) and int(self.grid.n_updates) == 0:
                bounds = frustum_bounds(train.intrinsics, self.w, self.h, train.distortion)
                culled = self.grid.cull(train.c2w, train.intrinsics, self.w, self.h,
                                        bounds=bounds,
                                        ndc=cfg.ndc_camera())  # fmt: skip
                log(f"view culling: {culled:.1%} of the grid's cells lie outside every "
                    "training camera's frustum")  # fmt: skip
        elif model.proposal is not None:  # --sampler proposal: its jitter (and backgrounds)
            self.grid_gen = torch.Generator(device=cfg.device).manual_seed(cfg.seed + 1)
        self.batch = cfg.batch
        # --train-spp: rays a training pixel, and their offsets from its centre (on the device)
        self.train_spp = int(getattr(cfg, "train_spp", 1) or 1)
        self.sub_offsets = sub_offsets(self.train_spp, cfg.device) if self.train_spp > 1 else None
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
        # --mlp-precision: the field's MLPs under autocast in the training step's rendering
        self.precision = getattr(cfg, "mlp_precision", "fp32")
        if self.precision != "fp32" and not hasattr(model.coarse, "mlp_dtype"):
            raise UserError(f"--mlp-precision {self.precision} needs --field hash (the "
                            f"{cfg.field} field's MLPs have no half-precision option)")  # fmt: skip
        self.graph = self._graph_step(log)
        # --ema: tiny-cuda-nn's average of the weights, for validation, the viewer, the saved run
        self.ema = WeightAverage(model, cfg.ema) if getattr(cfg, "ema", 0) > 0 else None

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
        if self.ema is not None:  # (load_run checked that the checkpoint has it)
            self.ema.load(ckpt.get(EMA_KEY), Path(run) / CHECKPOINT)

    def parameters(self):
        return list(self.model.parameters())

    def optimizer(self, params, lr):
        return _optimizer(self.cfg, params, self.model.poses, capturable=self.graph is not None,
                          model=self.model)  # fmt: skip

    def train_step(self, step, opt, params):
        """The static-shape step captured in a CUDA graph (None: the eager one, as for the
        first step, whose counts size the buffers)."""
        if self.graph is None or self.graph.last is None:
            return None
        self._grid_update(step)
        whole = self.graph.run(step, opt, params)
        if whole is None:  # the capture failed: the eager step from now on (said once); this
            self.log(f"CUDA graph capture failed ({self.graph.failed}); training goes on with "
                     "the eager step (--cuda-graph off)")  # fmt: skip
            self.graph = None  # step's grid update is done (loss() does not repeat it)
        return whole

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

    def pixel_offsets(self, n: int) -> torch.Tensor:
        """--pixel-jitter: [n, 2] uniform points in [0, 1)^2 of the batch's pixels, from the
        device generator where the run has one (grid and proposal runs; the graph step draws
        them the same way), else from the host's."""
        if self.grid_gen is not None:
            return torch.rand(n, 2, device=self.cfg.device, generator=self.grid_gen)
        return torch.rand(n, 2, generator=self.gen).to(self.cfg.device)

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
        spp = self.train_spp  # rays a pixel (--train-spp; supersample.py): pixel i's are i*spp..
        if self.grid_gen is not None:  # the lattice jitter (and backgrounds), drawn for all the
            # batch's rays; proposal sampling: one column per level (fields/proposal.py)
            cols = () if grid is not None else (model.proposal.n_draws,)
            jitter = torch.rand(n * spp, *cols, device=cfg.device, generator=self.grid_gen)
            if self.random_bg:  # (contracted: no fixed colour behind the scene)
                bg = torch.rand(n, 3, device=cfg.device, generator=self.grid_gen)
        if getattr(cfg, "pixel_jitter", False):  # rays through random points of their pixels
            off = self.pixel_offsets(n)  # (after the draws above, as the graph step draws)
            px, py = px + (off[:, 0] - 0.5), py + (off[:, 1] - 0.5)
        if self.dist is not None:  # this rank's share
            sl = self.dist.share(n)
            jitter = None if jitter is None else jitter[sl.start * spp : sl.stop * spp]
            bg = None if bg is None else bg[sl]
            # the share's mean loss weighted so that the ranks' average is the batch's mean
            scale = (sl.stop - sl.start) * self.dist.world / max(n, 1)
            cam, px, py = cam[sl], px[sl], py[sl]
            idx = (idx[0][sl], idx[1][sl]) if self.host_images else idx[sl]
        if self.host_images:
            idx, idx_host = idx
            target, alpha = self._pixels_on_host(idx_host)
        bg_rays = bg
        if spp > 1:  # each pixel's sub-rays (their backgrounds: the pixel's)
            cam, px, py = sub_rays(cam, px, py, self.sub_offsets)
            bg_rays = None if bg is None else expand_rows(bg, spp)
        o, d = dataset_rays(cfg, self.train, cam, px, py, check=False,  # (our own indices)
                            poses=model.poses)  # fmt: skip
        seed = cfg.seed * 1000003 + step  # (stratified jitter: keyed by the global ray index)
        images = cam if cfg.appearance_dim else None  # each ray's image: its appearance code
        with self.mlp_precision():
            out = render_rays_of(model, cfg, o, d, perturb=True, seed=seed,
                                 generator=self.grid_gen, jitter=jitter, ray_images=images,
                                 ray_offset=sl.start * spp, background=bg_rays,
                                 distortion=cfg.distortion_loss > 0,
                                 near=cfg.near_loss > 0)  # fmt: skip
        if spp > 1:  # the pixels' renders: the means of their sub-rays'
            out = pixel_means(out, o.shape[0] // spp, spp)
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
            target, alpha = self.pixels(idx)
        # the depth prior's draws, then the eikonal term's box points (every rank draws both)
        depth = None
        if self.keypoints is not None:
            with self.mlp_precision():
                depth = self._depth_term(seed)
        box = None
        if model.kind == "sdf":
            box = torch.rand(cfg.batch, 3, generator=self.gen).to(cfg.device)
        loss, more = step_loss(self.loss_settings, model, out, target, alpha, bg, scale=scale,
                               box=box, depth=depth, dist=self.dist)  # fmt: skip
        terms.update(more)
        return loss, terms

    def pixels(self, idx):
        """(colours [n, 3] float32, alpha [n] or None) of the training pixels ``idx`` (flat
        indices into the split, on the images' device)."""
        target = self.flat[idx]
        if target.dtype == torch.uint8:  # an 8-bit split held on the training device
            target = target.to(torch.float32).div_(255.0)
        alpha = None
        if self.flat_alpha is not None:
            alpha = self.flat_alpha[idx]
            if alpha.dtype == torch.uint8:
                alpha = alpha.to(torch.float32).div_(255.0)
        return target, alpha

    def _pixels_on_host(self, idx_host):
        """:meth:`pixels` of a split kept in host memory: gathered there into pinned memory and
        copied to the device without blocking."""
        dev = self.cfg.device
        out = []
        for flat in (self.flat, self.flat_alpha):
            if flat is None:
                out.append(None)
                continue
            v = torch.empty((idx_host.shape[0], *flat.shape[1:]), dtype=flat.dtype,
                            pin_memory=True)  # fmt: skip
            torch.index_select(flat, 0, idx_host, out=v)
            v = v.to(dev, non_blocking=True)
            if v.dtype == torch.uint8:  # 8-bit host images: their float values on the GPU
                v = v.to(torch.float32).div_(255.0)
            out.append(v)
        return out[0], out[1]

    def mlp_precision(self):
        """The training step's rendering: the field's MLPs at ``--mlp-precision``."""
        return mlp_precision(self.model.coarse, self.precision)

    def batch_rays(self, cam, px, py):
        """Rays of a training batch's pixels (indices the task drew itself: no range check)."""
        return dataset_rays(self.cfg, self.train, cam, px, py, check=False,
                            poses=self.model.poses)  # fmt: skip

    def distortion_map(self):
        """The ray coordinate of the distortion loss, or None without the loss."""
        return distortion_coordinate(self.cfg) if self.cfg.distortion_loss > 0 else None

    def near_distances(self, origins):
        """[n_rays] How far along each ray ``--near-loss`` reaches (:func:`near_zone`), or
        None without the loss."""
        return near_zone(self.cfg, origins) if self.cfg.near_loss > 0 else None

    def _grid_update(self, step: int) -> None:
        """The field's schedules for ``step`` and, every ``grid_every`` steps, the occupancy
        grid's update (in place: a captured step reads the grid's own buffers); once per step
        (a step whose capture failed goes on eagerly without updating the grid twice)."""
        if self._grid_step == step:
            return
        self._grid_step = step
        cfg, grid, field = self.cfg, self.grid, self.model.coarse
        if hasattr(field, "set_step"):  # coarse-to-fine hash levels (a function of the step)
            field.set_step(step)
        if self.model.proposal is not None:  # the proposal weights' anneal exponent
            self.model.proposal.set_step(step)
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

    def record(self, history, terms):
        terms = dict(terms, psnr=psnr_of_mse(terms["psnr"]))  # the fine pass's MSE, as PSNR
        if "_marched" in terms:  # a static-shape step: its counts size the next one
            marched, live = int(terms.pop("_marched")), int(terms.pop("_live"))
            self.graph.last = (terms["batch"], marched, live)
            self._next_batch(live)
        super().record(history, terms)

    def after_step(self, step, history):
        if self.ema is not None:  # (outside a captured step: one multi-tensor op, no sync)
            self.ema.update(step)

    def eval_weights(self):
        """The averaged weights in place while open (``--ema``; the raw ones otherwise)."""
        return self.ema.applied() if self.ema is not None else contextlib.nullcontext()

    def validate(self, step):
        keep = {}
        with self.eval_weights():  # (--ema: the average is what a saved run renders with)
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
        if self.ema is not None:  # --ema: the averaged weights ("fields" keeps the raw ones)
            state[EMA_KEY] = self.ema.state()
        return state
