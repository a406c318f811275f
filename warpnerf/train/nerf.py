"""NeRF training: random ray batches across all training images, coarse/fine rendering through the
Warp kernels, Adam with exponential learning-rate decay, periodic validation PSNR, atomic
checkpoints and an exact ``resume`` (model, optimiser, learning-rate schedule and sampling RNG all
restored)."""

from __future__ import annotations

import contextlib
import math
import time
from pathlib import Path

import torch

from ..errors import Interrupted, UserError
from ..fields.nerf import NeRFField
from ..io import (
    adopt,
    check_foreign,
    load_checkpoint,
    load_weights,
    output_lock,
    save_checkpoint,
    write_json,
)
from ..ops import random_pixels
from ..render import render_marched, render_nerf
from ._signals import check_resume_iters, nonfinite_flags, raise_if_diverged, stop_requests
from .nerf_config import NeRFConfig

__all__ = ["NeRFConfig", "train_nerf", "load_run", "build_fields", "load_data", "render_rays_of"]

CHECKPOINT = "checkpoint.pt"
OUTPUTS = ("config.json", CHECKPOINT, "history.json")  # what a NeRF run writes in its folder


def build_fields(cfg: NeRFConfig) -> dict:
    """{"coarse": field, "fine": field or None}. The hash field is one network used for both
    passes (the coarse pass only places the fine samples, without gradients)."""
    if cfg.field == "volsdf":
        from ..fields.volsdf import VolSDFField

        torch.manual_seed(cfg.seed)
        cfg.resolve()
        f = VolSDFField(
            cfg.aabb,
            cfg.n_layers,
            cfg.width,
            cfg.skip,
            cfg.pos_freqs,
            cfg.dir_freqs,
            n_features=cfg.width,
            color_width=cfg.width,
            view_dependence=cfg.view_dependence,
            beta=cfg.beta,
            beta_min=cfg.beta_min,
            learn_beta=cfg.learn_beta,
        ).to(cfg.device)
        return {"coarse": f, "fine": f if cfg.n_fine > 0 else None}
    if cfg.field == "hash":
        from ..fields.hash_nerf import HashNeRFField
        from ..ops.encoding import HashGrid

        torch.manual_seed(cfg.seed)
        f = HashNeRFField(
            cfg.resolve().aabb_box(),
            HashGrid(**cfg._grid_kwargs()),
            cfg.hidden,
            cfg.view_dependence,
        ).to(cfg.device)
        out = {"coarse": f, "fine": f if cfg.n_fine > 0 and not cfg.grid_res else None}
        if cfg.grid_res:
            from ..occupancy import OccupancyGrid

            out["grid"] = OccupancyGrid(
                cfg.aabb_box(),
                cfg.grid_res,
                dt=cfg.march_step,
                occ_threshold=cfg.occ_threshold,
                warmup=-(-cfg.grid_warmup // cfg.grid_every),
            ).to(cfg.device)
        return out

    def make():
        return NeRFField(
            cfg.n_layers,
            cfg.width,
            cfg.skip,
            cfg.pos_freqs,
            cfg.dir_freqs,
            cfg.view_dependence,
            cfg.density_activation,
        )

    torch.manual_seed(cfg.seed)
    out = {"coarse": make()}
    out["fine"] = make() if cfg.n_fine > 0 else None
    return {k: (v.to(cfg.device) if v is not None else None) for k, v in out.items()}


def load_data(cfg: NeRFConfig, split: str):
    """The dataset split as tensors on cfg.device (builtin scene when cfg.data == "builtin")."""
    if cfg.data == "builtin":
        from ..data.synthetic import make_synthetic_dataset

        train, val = make_synthetic_dataset(size=cfg.builtin_size, device=cfg.device)
        ds = dict(train if split == "train" else val)
    else:
        from ..data import load_dataset

        ds = load_dataset(
            cfg.data,
            split=split,
            background=(cfg.background,) * 3,
            downscale=cfg.downscale,
            max_images=cfg.max_images or None,
            fmt=cfg.data_format,
            holdout=cfg.holdout,
        )
    for k in ("images", "c2w", "intrinsics", "distortion"):
        if k in ds:
            ds[k] = ds[k].to(cfg.device)
    return ds


def dataset_rays(cfg: NeRFConfig, ds, cam_idx=None, px=None, py=None, image: int | None = None):
    """Rays of a batch of pixels (cam_idx, px, py) or of every pixel of ``image``: undistorted
    when the dataset has distortion, in NDC when the run uses it."""
    from ..data.cameras import camera_rays

    dist = ds.get("distortion")
    if image is not None:
        sl = slice(image, image + 1)
        return camera_rays(
            ds["c2w"][sl], ds["intrinsics"][sl], ds["width"], ds["height"],
            distortion=None if dist is None else dist[sl], ndc=cfg.ndc_camera(),
        )  # fmt: skip
    return camera_rays(
        ds["c2w"], ds["intrinsics"], cam_idx=cam_idx, px=px, py=py, distortion=dist,
        ndc=cfg.ndc_camera(),
    )  # fmt: skip


def render_rays_of(
    fields_, cfg: NeRFConfig, o, d, perturb=False, seed=0, chunk=None, generator=None
):
    """Renders rays with the run's fields: grid marching when the run has an occupancy grid
    (``generator``, on the rays' device, jitters the lattice when ``perturb``), otherwise
    stratified (+ hierarchical) samples."""
    if fields_.get("grid") is not None:
        n = o.shape[0]
        chunk = chunk or max(n, 1)
        outs = [
            render_marched(
                fields_["grid"],
                fields_["coarse"],
                o[s : s + chunk],
                d[s : s + chunk],
                cfg.near,
                cfg.far,
                perturb=perturb,
                generator=generator,
                background=cfg.background,
                t_threshold=cfg.t_threshold,
                max_samples=cfg.max_samples,
                round_samples=cfg.round_samples,
                half=cfg.render_half,
            )
            for s in range(0, max(n, 1), chunk)
        ]
        out = {k: torch.cat([x[k] for x in outs]) for k in ("rgb", "depth", "opacity")}
        out.update({k: sum(x[k] for x in outs) for k in ("n_marched", "n_kept")})
        return out
    return render_nerf(
        fields_,
        o,
        d,
        cfg.near,
        cfg.far,
        n_coarse=cfg.n_coarse,
        n_fine=cfg.n_fine,
        perturb=perturb,
        seed=seed,
        background=cfg.background,
        t_threshold=cfg.t_threshold,
        chunk=chunk,
        aabb=cfg.aabb_box(),
    )


@torch.no_grad()
def render_dataset_image(fields_, cfg, ds, i):
    """rgb [H, W, 3], depth [H, W], opacity [H, W] of image i of a dataset."""
    h, w = ds["height"], ds["width"]
    o, d = dataset_rays(cfg, ds, image=i)
    out = render_rays_of(fields_, cfg, o, d, chunk=cfg.chunk)
    return out["rgb"].reshape(h, w, 3), out["depth"].reshape(h, w), out["opacity"].reshape(h, w)


def _psnr(mse: float) -> float:
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


def _unique(fields_) -> dict:
    """The fields with a shared network listed once (the hash field serves both passes)."""
    out, seen = {}, set()
    for k, f in fields_.items():
        out[k] = f if f is not None and id(f) not in seen else None
        seen.add(id(f))
    return out


def _parameters(fields_):
    return [p for f in _unique(fields_).values() if f is not None for p in f.parameters()]


def _optimizer(cfg, params):
    if cfg.field == "hash":  # instant-ngp's Adam: tiny eps (sparse, small table gradients)
        return torch.optim.Adam(params, lr=cfg.lr, betas=(0.9, 0.99), eps=1e-15)
    return torch.optim.Adam(params, lr=cfg.lr)


def _save(run: Path, step, fields_, opt, gen, history, cfg, extra=None):
    state = {
        **(extra or {}),
        "step": step,
        "fields": {
            k: (v.state_dict() if v is not None else None) for k, v in _unique(fields_).items()
        },
        "optimizer": opt.state_dict(),
        "generator": gen.get_state(),
        "history": history,
        "config": cfg.to_dict(),
    }
    save_checkpoint(run / CHECKPOINT, state)


def load_run(run, device: str | None = None):
    """(cfg, fields, checkpoint dict) of a run folder; device overrides the saved one."""
    run = Path(run)
    cfg_path, ckpt_path = run / "config.json", run / CHECKPOINT
    if not cfg_path.is_file() or not ckpt_path.is_file():
        raise UserError(f"{run}: not a training run (needs config.json and {CHECKPOINT})")
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
    fields_ = build_fields(cfg)
    keys = ("step", "fields", "optimizer", "generator", "history")
    ckpt = load_checkpoint(ckpt_path, cfg.device, keys)
    if not isinstance(ckpt["fields"], dict):
        raise UserError(f"{ckpt_path}: not a NeRF checkpoint ('fields' is not a dict)")
    for k, f in _unique(fields_).items():
        if f is not None and k in ckpt["fields"]:  # (runs before the grid existed have none)
            load_weights(f, ckpt["fields"][k], ckpt_path, f"{k} field's weights")
    return cfg, fields_, ckpt


def train_nerf(
    cfg: NeRFConfig,
    run,
    resume: bool = False,
    progress: bool = True,
    log=print,
    device: str | None = None,
):
    """Trains (or resumes) a run in folder ``run``; returns the history dict.

    On resume only ``cfg.iters`` (the total to reach) and ``cfg.max_seconds`` are taken from
    ``cfg``; everything else comes from the run's config.json, and ``device`` (if given) moves it.
    """
    with contextlib.ExitStack() as locks:  # the run folder's lock, held to the end
        return _train_nerf(cfg, Path(run), resume, progress, log, device, locks)


def _train_nerf(cfg, run: Path, resume, progress, log, device, locks):
    if resume:
        if run.is_dir():  # (a missing folder: the loader says it is not a run)
            locks.enter_context(output_lock(run, "run folder"))
        saved_cfg, fields_, ckpt = load_run(run, device)
        check_resume_iters(run, ckpt["step"], cfg.iters)
        adopt(run, OUTPUTS)  # a run from before manifests: its files are the run's own
        saved_cfg.iters, saved_cfg.max_seconds = cfg.iters, cfg.max_seconds
        cfg = saved_cfg
        cfg.validate()
    else:
        cfg.validate()
        if (run / CHECKPOINT).exists():
            raise UserError(
                f"{run}: already holds a run; pass --resume to continue it or choose another --out"
            )
        fields_, ckpt = build_fields(cfg), None
    if cfg.lr_decay_steps <= 0:
        cfg.lr_decay_steps = cfg.iters
    # Data first: a bad dataset stops the run before anything is written.
    train = load_data(cfg, "train")
    val = load_data(cfg, "val") if cfg.val_images > 0 else None
    if not resume:
        locks.enter_context(output_lock(run, "run folder"))
        if (run / CHECKPOINT).exists():  # another process started a run here meanwhile
            raise UserError(f"{run}: already holds a run; choose another --out")
        check_foreign([run / n for n in OUTPUTS])
    write_json(run / "config.json", cfg.to_dict())
    n_img, h, w = train["images"].shape[:3]
    flat = train["images"].reshape(-1, 3)
    params = _parameters(fields_)
    opt = _optimizer(cfg, params)
    gen = torch.Generator().manual_seed(cfg.seed)
    grid = fields_.get("grid")
    # The grid's updates and lattice jitter draw from a generator on the device (saved too).
    grid_gen = torch.Generator(device=cfg.device).manual_seed(cfg.seed + 1) if grid else None

    def density_of(x):
        return fields_["coarse"].density(x)[0]

    history = {"step": [], "loss": [], "psnr": [], "val_step": [], "val_psnr": [], "seconds": []}
    start, batch = 0, cfg.batch
    if ckpt is not None:
        load_weights(opt, ckpt["optimizer"], run / CHECKPOINT, "optimizer state")
        gen.set_state(ckpt["generator"].cpu())  # map_location may have moved it
        history, start = ckpt["history"], ckpt["step"]
        batch = ckpt.get("batch", cfg.batch)
        state = ckpt.get("grid_generator")
        if grid_gen is not None and ckpt.get("grid_generator_device") == grid_gen.device.type:
            grid_gen.set_state(state.cpu())
        elif grid_gen is not None:
            log(f"{run}: resumed on another device type; the grid's random stream restarts "
                "from the seed (the continuation is not bit-exact)")  # fmt: skip
    if cfg.device.startswith("cuda"):
        torch.backends.cuda.matmul.allow_tf32 = cfg.tf32
    elapsed0 = history["seconds"][-1] if history["seconds"] else 0.0
    t0, val_time = time.perf_counter(), 0.0  # training time excludes validation renders
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.iters, initial=start, desc="train nerf", unit="step", disable=None)
    with stop_requests() as stop:
        for step in range(start, cfg.iters):
            lr = cfg.lr * (cfg.lr_final / cfg.lr) ** min(step / cfg.lr_decay_steps, 1.0)
            for group in opt.param_groups:
                group["lr"] = lr
            if grid is not None and step % cfg.grid_every == 0:
                grid.update(density_of, grid_gen)
            cam, px, py, idx = random_pixels(n_img, w, h, batch, generator=gen, device=cfg.device)
            o, d = dataset_rays(cfg, train, cam, px, py)
            out = render_rays_of(
                fields_, cfg, o, d, perturb=True, seed=cfg.seed * 1000003 + step, generator=grid_gen
            )
            if grid is not None:
                history.setdefault("samples_per_ray", []).append(out["n_kept"] / batch)
                history.setdefault("batch", []).append(batch)
                if cfg.target_samples > 0:  # next step's rays: aim at target_samples samples
                    batch = int(batch * cfg.target_samples / max(out["n_kept"], 1))
                    batch = min(max(batch, 64), 1 << 16)
            target = flat[idx]
            loss_fine = torch.mean((out["rgb"] - target) ** 2)
            loss = loss_fine
            coarse = out.get("rgb_coarse")
            if coarse is not None and coarse.requires_grad and fields_.get("fine") is not None:
                loss = loss + torch.mean((coarse - target) ** 2)
            if cfg.field == "volsdf":  # eikonal on the rendered samples and on random box points
                f = fields_["coarse"]
                box = (torch.rand(cfg.batch, 3, generator=gen) * 2 - 1).to(cfg.device) * cfg.aabb
                eik = 0.5 * (f.last_eikonal + f.eikonal(box))
                loss = loss + cfg.eikonal_weight * eik
                history.setdefault("beta", []).append(float(f.beta.detach()))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            flags = nonfinite_flags(loss, params)
            opt.step()
            done = step + 1
            # the step's one host sync: losses and the divergence flags in one transfer (a
            # diverged step is never saved: the run keeps its last good checkpoint)
            loss_v, fine_v, *bad = torch.cat(
                [torch.stack([loss.detach(), loss_fine.detach()]).double(), flags.double()]
            ).tolist()
            raise_if_diverged(bad, done, loss_v, run, lr)
            if cfg.device.startswith("cuda"):
                torch.cuda.synchronize()
            seconds = elapsed0 + time.perf_counter() - t0 - val_time
            history["step"].append(done)
            history["loss"].append(loss_v)
            history["psnr"].append(_psnr(fine_v))
            history["seconds"].append(seconds)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{loss_v:.4f}", psnr=f"{history['psnr'][-1]:.2f}")
            session = seconds - elapsed0  # this invocation's training time
            out_of_time = cfg.max_seconds > 0 and session >= cfg.max_seconds
            if val is not None and (done % cfg.val_every == 0 or done == cfg.iters or out_of_time):
                tv = time.perf_counter()
                v = validate(fields_, cfg, val)
                val_time += time.perf_counter() - tv
                history["val_step"].append(done)
                history["val_psnr"].append(v)
                log(
                    f"step {done}: train psnr {history['psnr'][-1]:.2f}, val psnr {v:.2f}, "
                    f"{seconds:.0f} s"
                )
            stopping = out_of_time or stop["signum"] is not None
            if done % cfg.ckpt_every == 0 or done == cfg.iters or stopping:
                extra = {"batch": batch}
                if grid_gen is not None:
                    extra["grid_generator"] = grid_gen.get_state()
                    extra["grid_generator_device"] = grid_gen.device.type
                _save(run, done, fields_, opt, gen, history, cfg, extra)
                write_json(run / "history.json", history)
            if out_of_time:
                log(f"stopping at step {done}: --max-seconds {cfg.max_seconds} reached")
                break
            if stop["signum"] is not None:  # SIGINT/SIGTERM: the step is done, checkpoint it
                break
    if bar is not None:
        bar.close()
    if stop["signum"] is not None:
        raise Interrupted(stop["signum"], history["step"][-1], run)
    return history


def validate(fields_, cfg, val) -> float:
    """Mean PSNR over the first cfg.val_images validation images."""
    n = min(cfg.val_images, val["images"].shape[0])
    mses = []
    for i in range(n):
        rgb, _, _ = render_dataset_image(fields_, cfg, val, i)
        mses.append(float(((rgb - val["images"][i]) ** 2).mean()))
    return sum(_psnr(m) for m in mses) / max(n, 1)
