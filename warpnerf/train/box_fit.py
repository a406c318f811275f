"""Fit an analytic box (center, side lengths) to images by gradient descent through the Warp
compositing path: random ray batches across all images, MSE, Adam with exponential decay.

In a run folder (:func:`run_box_fit_on_folder`, ``warpnerf train box``) the fit is checkpointed
atomically (box, optimiser, learning-rate schedule, batch RNG, history) every ``ckpt_every``
steps, at the end, at ``max_seconds`` and on SIGINT/SIGTERM (the step finishes, is checkpointed,
and :class:`~warpnerf.errors.Interrupted` is raised); ``resume`` then continues exactly as if the
fit had never stopped (the per-step jitter is seeded by the step, the batches come from the saved
generator).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import torch

from .. import outputs
from ..data.cameras import intrinsics_from_fov, spiral_path
from ..errors import UserError, check_device
from ..fields.sdf_volume import SDFVolume
from ..ops import generate_rays, random_pixels
from ..options import check_at_least, option, with_defaults
from ..render import render_rays, render_views
from .logs import TensorBoardLog
from .loop import LoopConfig, LoopSettings, Task, lock_run, resume_checks, run_loop
from .methods import LoadedRun, Method, register_method

__all__ = [
    "BoxFitConfig",
    "fit_box",
    "render_box_views",
    "run_box_fit_on_folder",
    "load_box_run",
    "MODEL",
]

MODEL = "box"  # config.json's "model" of a box run folder
CHECKPOINT = "checkpoint.pt"
# what a box run writes in its folder (the spiral video's files with frames > 0)
OUTPUTS = ("config.json", CHECKPOINT, "history.json", "result.json", "spiral_rgb.mp4",
           "spiral_rgb.gif", "spiral_depth.gif", "spiral_depth_000.png")  # fmt: skip
_RUN_KEYS = ("data", "device", "model")  # saved in config.json beside the BoxFitConfig fields


# the loop's section (shared by every kind of run) with the box fit's defaults: Adam, decayed
# exponentially to lr * lr_final_ratio at lr_decay_steps (0: iters; a run saves its first
# invocation's)
BOX_LOOP = with_defaults(
    LoopConfig, iters=400, lr=0.02, ckpt_every=100, lr_final=option(None, flag=None),
    max_seconds=option(
        0.0, "stop (a run folder checkpoints) after this much fitting time in this call (a "
        "resume gets a fresh budget; 0: run all --iters)", check="nonnegative",
    ),
)  # fmt: skip


@dataclass
class BoxFitConfig(BOX_LOOP):
    """The box fit's settings, defaults and help (`warpnerf train box` builds its flags from
    these fields: warpnerf.options); the loop's section is :class:`LoopConfig`."""

    batch: int = option(4096, "rays per step, drawn uniformly across all images",
                        check="positive")  # fmt: skip
    n_samples: int = option(64, "stratified samples per ray (jittered while fitting)",
                            flag="--samples", check="positive")  # fmt: skip
    near: float = option(0.0, "near bound of the rays", check="finite")
    far: float = option(5.0, "far bound of the rays", check="finite")
    lr_final_ratio: float = option(0.1, flag=None)
    beta: float = option(0.05, flag=None)
    alpha: float = option(1.0, flag=None)
    background: float = option(0.0, flag=None)  # black, as the seed's box task
    allow_outside_paths: bool = option(
        False, "let the dataset's files name images outside its folder (absolute paths, '..', "
        "symlinks out of it); refused by default",
    )  # fmt: skip

    @classmethod
    def from_dict(cls, d: dict, where: str = "config"):
        """The settings saved in a box run's config.json (untrusted; without the run keys):
        unknown field names, values of the wrong type (``true`` is not a number), non-finite
        numbers and out-of-range values are a UserError naming ``where``, the field and the
        expected form."""
        from ..json_input import check_fields

        return cls(**check_fields(cls, d, where)).check_values(where)

    def validate(self):
        """The config a fit reads: this one resolved (``lr_decay_steps`` 0: the first
        invocation's ``iters``), checked once (:meth:`check_values`) and frozen (read-only);
        this one is left as it is."""
        steps = self.lr_decay_steps if self.lr_decay_steps > 0 else self.iters
        return dataclasses.replace(self, lr_decay_steps=steps).check_values().freeze()

    def check_values(self, where: str | None = None):
        """Range checks; ``where`` None: messages name the command-line flags, else the file
        ``where`` and the config field."""
        from ..json_input import field_error

        def fail(name: str, rule: str):
            return field_error(where, name, rule)

        LoopConfig.check_section(self, fail)
        if self.lr is None:
            raise field_error(where, "lr", "must be a number, got null")
        check_at_least(self, fail, 1, "batch", "n_samples")
        if not (math.isfinite(self.far) and self.far > self.near >= 0):
            raise field_error(where, "near", f"must be >= 0 and below a finite far (--far), got "
                              f"near {self.near}, far {self.far}")  # fmt: skip
        for name in ("lr_final_ratio", "beta", "alpha"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise field_error(where, name, f"must be positive and finite, got {v}")
        if not (math.isfinite(self.background) and 0 <= self.background <= 1):
            raise field_error(where, "background", f"must be in [0, 1], got {self.background}")
        return self

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
    *,
    run=None,
    state: dict | None = None,
    log=print,
    hooks=(),
):
    """Optimises a rainbow box's center and side lengths so its renders match ``images``.

    Args:
        images: [N, H, W, 3] ground-truth colours in [0, 1].
        c2w: [N, 4, 4] camera-to-world (OpenGL); intrinsics: [N, 4] (fx, fy, cx, cy).
        run: a folder to checkpoint into (``checkpoint.pt`` and ``history.json``, atomically)
            every ``cfg.ckpt_every`` steps, at the end, at ``cfg.max_seconds`` and on
            SIGINT/SIGTERM, which finish the current step, checkpoint it and raise
            :class:`~warpnerf.errors.Interrupted`. None: no files, signals keep their handlers.
        state: a checkpoint (:func:`load_box_run`) to continue from, up to ``cfg.iters`` steps
            in all; the continuation equals an uninterrupted fit.

    Returns:
        dict with center, side_lengths, final_loss (mean of the last 10 steps), losses, step,
        seconds, and the fitted ``volume``.
    """
    volume = SDFVolume(
        "box",
        center=tuple(init_center),
        side_lengths=tuple(init_sides),
        alpha=cfg.alpha,
        beta=cfg.beta,
    ).to(images.device)
    task = BoxTask(images, c2w, intrinsics, cfg, volume, log_every)
    if state is not None:
        where = Path(run) / CHECKPOINT if run is not None else "the checkpoint"
        outputs.load_weights(volume, state["volume"], where, "box parameters")
        task.gen.set_state(state["generator"].cpu())  # map_location may have moved it
    settings = LoopSettings.of(cfg, "fit box", lr_final=cfg.lr * cfg.lr_final_ratio)
    history = run_loop(
        task, settings, run=run, checkpoint=CHECKPOINT, resume_from=state, progress=progress,
        log=log, hooks=hooks,
    )  # fmt: skip
    losses = history["loss"]
    return {
        "center": volume.center.detach().tolist(),
        "side_lengths": volume.side_lengths.detach().tolist(),
        "final_loss": float(sum(losses[-10:]) / len(losses[-10:])) if losses else float("nan"),
        "losses": losses,
        "step": history["step"][-1] if history["step"] else 0,
        "seconds": history["seconds"][-1] if history["seconds"] else 0.0,
        "volume": volume,
    }


class BoxTask(Task):
    """The box fit as a :class:`~warpnerf.train.loop.Task`: random pixels of the images, rays
    volume-rendered through the box's SDF, mean squared colour error; the side lengths are kept
    above 1e-3 after each step."""

    method = MODEL  # its kind of run (train/methods.py)

    def __init__(self, images, c2w, intrinsics, cfg, volume, log_every=0):
        self.images, self.c2w, self.intrinsics, self.cfg = images, c2w, intrinsics, cfg
        self.flat = images.reshape(-1, 3)
        self.volume, self.log_every = volume, log_every
        self.gen = torch.Generator().manual_seed(cfg.seed)

    def parameters(self):
        return list(self.volume.parameters())

    def loss(self, step):
        cfg, (n_img, h, w, _) = self.cfg, self.images.shape
        cam, px, py, flat = random_pixels(
            n_img, w, h, cfg.batch, generator=self.gen, device=self.images.device
        )
        o, d = generate_rays(self.c2w, self.intrinsics, cam_idx=cam, px=px, py=py)
        out = render_rays(
            o, d, cfg.near, cfg.far, self.volume, perturb=True, seed=cfg.seed * 100003 + step,
            **cfg.render_kwargs(),
        )  # fmt: skip
        return torch.mean((out["rgb"] - self.flat[flat]) ** 2), {}

    def after_step(self, step, history):
        with torch.no_grad():
            self.volume.side_lengths.clamp_(min=1e-3)
        if self.log_every and (step % self.log_every == 0 or step == self.cfg.iters - 1):
            c = [round(v, 4) for v in self.volume.center.tolist()]
            s = [round(v, 4) for v in self.volume.side_lengths.tolist()]
            print(f"step {step:5d} loss {history['loss'][-1]:.3e} center {c} sides {s}")

    def postfix(self, history):
        return {"loss": f"{history['loss'][-1]:.2e}"}

    def state(self):
        return {
            "volume": self.volume.state_dict(),
            "generator": self.gen.get_state(),
            "config": self.cfg.to_dict(),
        }


def _read_config(run: Path, strict: bool = False):
    """config.json of a run folder as a dict; None when there is none, or (unless ``strict``:
    then a UserError naming the file) when it is unreadable, malformed or not a JSON object."""
    from ..json_input import read_run_config

    path = run / "config.json"
    if not path.exists():  # (a FIFO or a link there: read_json names it)
        return None
    try:
        d = read_run_config(path)
    except UserError:
        if strict:
            raise
        return None
    if not isinstance(d, dict) and strict:
        raise UserError(f"{path}: expected a JSON object (a run's config)")
    return d if isinstance(d, dict) else None


def load_box_run(run, device: str | None = None):
    """(cfg, data, device, checkpoint) of a box run folder; ``device`` overrides the saved one."""
    from ..json_input import is_device, show

    run = Path(run)
    d = _read_config(run, strict=(run / CHECKPOINT).exists())
    if d is None or not (run / CHECKPOINT).exists():
        raise UserError(f"{run}: not a training run (needs config.json and {CHECKPOINT})")
    if d.get("model") != MODEL:
        raise UserError(f"{run}: not a box run (config model {d.get('model')!r})")
    data, saved_device = d.get("data"), d.get("device", "cpu")
    cfg = BoxFitConfig.from_dict(
        {k: v for k, v in d.items() if k not in _RUN_KEYS}, str(run / "config.json")
    )
    if not isinstance(data, str) or not is_device(saved_device):
        raise UserError(
            f"{run / 'config.json'}: fields 'data' and 'device' must be a folder and cpu, cuda or "
            f"cuda:N; got {show(data)}, {show(saved_device)}"
        )
    device = check_device(device or saved_device, str(run))
    keys = ("step", "volume", "optimizer", "generator", "history")
    ckpt = outputs.load_checkpoint(run / CHECKPOINT, device, keys)
    return cfg, data, device, ckpt


def run_box_fit_on_folder(
    data,
    out,
    cfg: BoxFitConfig,
    device: str | None = None,
    frames: int = 40,
    progress: bool = False,
    resume: bool = False,
    log=print,
    tensorboard: int = 0,
    hooks=(),
):
    """The seed's box task on a Blender-format folder: images alpha-composited on black, fits the
    rainbow box in run folder ``out`` (``config.json``, atomic ``checkpoint.pt`` and
    ``history.json`` as it goes), then writes ``result.json`` and (frames > 0) a spiral video of
    the fit. A new fit in a folder that holds an earlier box fit starts over (a folder holding
    another kind of run is refused). SIGINT/SIGTERM: see :func:`fit_box`.

    ``resume=True`` continues the fit in ``out`` up to ``cfg.iters`` steps in all; only
    ``cfg.iters`` and ``cfg.max_seconds`` are taken from ``cfg`` (``data`` may be None): the data
    and every other setting come from the run's config.json, and ``device`` (if given) moves it.
    ``device`` None: cpu for a new fit.

    ``tensorboard`` N > 0: also TensorBoard event files in OUT/tensorboard, every N steps;
    ``hooks``: :class:`~warpnerf.train.loop.LoopHook` s (the live viewer).

    Returns {"center": [x, y, z], "side_lengths": [a, b, c], "final_loss": float}.
    """
    with contextlib.ExitStack() as locks:  # the run folder's lock, held to the end
        return _run_box_fit(data, Path(out), cfg, device, frames, progress, resume, log, locks,
                            tensorboard, hooks)  # fmt: skip


def _run_box_fit(data, out: Path, cfg, device, frames, progress, resume, log, locks,
                 tensorboard=0, hooks=()):  # fmt: skip
    from ..data.blender import load_blender

    state = None
    if resume:
        lock_run(out, locks)
        saved, data, device, state = load_box_run(out, device)
        resume_checks(out, state["step"], cfg.iters, OUTPUTS)
        cfg = dataclasses.replace(saved, iters=cfg.iters, max_seconds=cfg.max_seconds)
    else:
        device = device or "cpu"
        old = _read_config(out)
        if (out / CHECKPOINT).exists() and (old is None or old.get("model") != MODEL):
            raise UserError(f"{out}: holds another kind of run; choose another --out")
    cfg = cfg.validate()  # (resolved, checked and frozen: what the fit reads)
    # Data first: a bad folder stops the fit before anything is written.
    # every frame is fitted (holdout 0: no frames held out of a single transforms.json)
    ds = load_blender(data, "train", background=(cfg.background,) * 3, holdout=0,
                      allow_outside=cfg.allow_outside_paths)  # fmt: skip
    dev = torch.device(device)
    tb = [TensorBoardLog(out, tensorboard)] if tensorboard else []  # (checks; writes nothing)
    if not resume:
        locks.enter_context(outputs.output_lock(out, "run folder"))
        old = _read_config(out)  # again, under the lock
        if (out / CHECKPOINT).exists() and (old is None or old.get("model") != MODEL):
            raise UserError(f"{out}: holds another kind of run; choose another --out")
        outputs.check_foreign([out / n for n in OUTPUTS])
        # an earlier fit's files would not match this one's (only files warpnerf wrote go)
        outputs.remove_own(out, (CHECKPOINT, "history.json", "result.json"))
    outputs.write_json(out / "config.json", cfg.to_dict() | {"data": str(data), "device": device,
                                                             "model": MODEL})  # fmt: skip
    fit = fit_box(
        ds.images.to(dev),
        ds.c2w.to(dev),
        ds.intrinsics.to(dev),
        cfg,
        progress=progress,
        run=out,
        state=state,
        log=log,
        hooks=[*hooks, *tb],
    )
    volume = fit.pop("volume")
    result = {k: fit[k] for k in ("center", "side_lengths", "final_loss")}
    extra = {"step": fit["step"], "seconds": fit["seconds"], "losses": fit["losses"]}
    outputs.write_json(out / "result.json", result | extra)
    if frames > 0:
        write_spiral(volume, out, frames, min(ds.width, 256), cfg)
    return result


SPIRAL_FOV_X = 0.7  # radians: the spiral video's camera (and the demo's)
SPIRAL_RADIUS = 3.0


def write_spiral(volume, out: Path, frames: int, size: int, cfg: BoxFitConfig, prefix="spiral"):
    """Renders ``frames`` views on a spiral: {prefix}_rgb.mp4/.gif, {prefix}_depth.gif and the
    first frame's depth PNG normalised by its maximum. Returns (rgb, depth) tensors."""
    dev = volume.center.device
    cams = spiral_path(frames, radius=SPIRAL_RADIUS).to(dev)
    k = intrinsics_from_fov(size, size, SPIRAL_FOV_X).to(dev).expand(frames, 4)
    out_r = render_views(cams, k, size, size, cfg.near, cfg.far, volume, **cfg.render_kwargs())
    rgb, depth = out_r["rgb"].cpu(), out_r["depth"].cpu()
    # Expected depth of the visible surface (depth / opacity), normalised by its maximum.
    surf = torch.where(
        out_r["opacity"].cpu() > 1e-3,
        depth / out_r["opacity"].cpu().clamp_min(1e-3),
        torch.zeros_like(depth),
    )
    dmax = float(surf.max()) or 1.0
    outputs.write_video(out / f"{prefix}_rgb.mp4", [outputs.to_uint8(f) for f in rgb])
    outputs.write_video(out / f"{prefix}_rgb.gif", [outputs.to_uint8(f) for f in rgb])
    outputs.write_video(
        out / f"{prefix}_depth.gif", [outputs.depth_to_uint8(f, dmax) for f in surf]
    )
    outputs.write_image(out / f"{prefix}_depth_000.png", outputs.depth_to_uint8(surf[0]))
    return rgb, surf


# ------------------------------------------------- the method, registered as an added one is


def _open_box(run, device=None) -> LoadedRun:
    import contextlib

    from ..data.blender import load_blender
    from ..fields.sdf_volume import SDFVolume

    cfg, data, dev, ckpt = load_box_run(run, device)
    volume = SDFVolume("box", alpha=cfg.alpha, beta=cfg.beta).to(dev)
    outputs.load_weights(volume, ckpt["volume"], Path(run) / "checkpoint.pt", "box parameters")
    train = None
    with contextlib.suppress(UserError):  # the cameras are an overlay
        train = load_blender(data, "train", background=(cfg.background,) * 3, holdout=0,
                             allow_outside=cfg.allow_outside_paths)  # fmt: skip
    return LoadedRun(cfg, volume, train, f"{Path(run).name}: box fit")


def _box_task(task) -> LoadedRun:
    from types import SimpleNamespace

    n, h, w = task.images.shape[:3]
    cams = SimpleNamespace(c2w=task.c2w, intrinsics=task.intrinsics, width=w, height=h,
                           images=task.images)  # fmt: skip
    return LoadedRun(task.cfg, task.volume, cams)


register_method(Method(MODEL, ("box",), "box fit", "box", _open_box, _box_task))
