"""Neural SDF from a point cloud: |f| on the points + eikonal (|grad f| - 1)^2 on random points
and the surface points (+ an optional normal term), Adam with exponential decay, atomic
checkpoints, exact resume (SIGINT/SIGTERM finish the step, checkpoint it and raise
``Interrupted``); at the end a marching-cubes mesh in the input's units, Chamfer
distance to the points and eikonal statistics.

Points are normalised once (centre of their bounding box to the origin, largest half extent to
0.8), so the eikonal samples cover [-1, 1]^3; the transform is saved in the run and meshes come
back in the original units.

Two fields (``--field``): ``mlp``, :class:`~warpnerf.fields.neural_sdf.NeuralSDF` (positional
encoding, autograd gradients), and ``hash``, :class:`~warpnerf.fields.hash_point_sdf.HashPointSDF`
(Warp hash grid, central-difference gradients, lr 1e-2 by default). A hash grid is local: the
parts of the initial sphere that no point touches satisfy the eikonal equation and stay, as
surfaces away from the points. Two measures remove them (bunny, 300 steps on the CPU: Chamfer
0.0076 without the second, 0.0040 with both): the hash levels open coarse to fine over
``hash_c2f`` of the steps (:func:`open_levels`), and SAL's sign-agnostic distance term
| |f(x)| - d(x) | at the uniform samples, with d the distance to the nearest point (Atzmon &
Lipman 2020), which no surface far from the points satisfies.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import UserError, check_device
from ..fields.hash_point_sdf import HashPointSDF
from ..fields.neural_sdf import NeuralSDF
from ..options import check_at_least, option, with_defaults
from ..outputs import (
    build_for_weights,
    load_checkpoint,
    load_weights,
    write_json,
)
from .logs import TensorBoardLog
from .loop import (
    LoopConfig,
    LoopSettings,
    Task,
    adam,
    claim_run,
    lock_run,
    resume_checks,
    run_loop,
)
from .methods import LoadedRun, Method, register_method
from .presets import PRESET_NAMES, preset_option

__all__ = ["SDFConfig", "train_sdf", "load_points", "load_sdf_run", "chamfer", "MODEL"]

MODEL = "neural_sdf"
FIELDS = ("mlp", "hash")  # --field: NeuralSDF or HashPointSDF
CHECKPOINT = "checkpoint.pt"
# what a neural-SDF run writes in its folder
OUTPUTS = ("config.json", CHECKPOINT, "history.json", "metrics.json", "mesh.ply", "mesh.png")


# the loop's section (shared by every kind of run) with this one's defaults
SDF_LOOP = with_defaults(
    LoopConfig, iters=2000, ckpt_every=500,
    lr=option(None, "Adam's learning rate: 1e-3 (mlp), 1e-2 (hash)", check="positive"),
    lr_final=option(None, flag=None),  # reached at lr_decay_steps; lr / 10 (resolved, saved)
    max_seconds=option(0.0, "stop after this much training time (0: run all --iters)",
                       check="nonnegative"),
)  # fmt: skip


@dataclass
class SDFConfig(SDF_LOOP):
    """Every setting of a neural-SDF fit, its default and help (`warpnerf train sdf` builds its
    flags from these fields: warpnerf.options); the loop's section is :class:`LoopConfig`."""

    points: str = option(
        "builtin", "FILE.npz (verts|points [, normals]) or FILE.ply, or builtin (a torus)"
    )
    field: str = option("mlp", "mlp (positional encoding) or hash (hash-grid SDF)",
                        choices=FIELDS)  # fmt: skip
    preset: str = preset_option("the built-in torus")
    batch: int = option(4096, "surface points per step", check="positive")
    # eikonal points per step (half uniform in the box, half near the points); the CLI: = batch
    n_random: int = option(4096, flag=None)
    eikonal_weight: float = option(0.1, "weight of (|grad f| - 1)^2", check="finite")
    normal_weight: float = option(1.0, "weight of the normal term, when normals are given",
                                  check="finite")  # fmt: skip
    n_layers: int = option(6, "MLP layers", flag="--layers", check="positive")
    width: int = option(128, "MLP width", check="positive")
    skip: int = option(3, flag=None)  # the CLI: layers // 2
    pos_freqs: int = option(6, "positional-encoding frequencies", check="nonnegative")
    # --field hash: the MLP, the hash grid (levels of 2 features), the finite-difference step of
    # the gradient, the coarse-to-fine schedule and the distance term
    hash_width: int = option(64, "hash field: MLP width (2 hidden layers)", check="positive")
    hash_levels: int = option(16, "hash field: grid levels", check="positive")
    hash_log2_size: int = option(19, "hash field: log2 of the rows per level", check="positive")
    hash_base_res: int = option(4, flag=None)  # cells per side of the coarsest level
    hash_max_res: int = option(512, "hash field: cells per side of the finest level",
                               check="positive")  # fmt: skip
    # the finite-difference step of the hash field's gradient (box units); 0: the finest open
    # cell (0.0078 or 0.02 instead: the same bunny Chamfer within 3%)
    fd_step: float = option(0.0, flag=None)
    hash_c2f: float = option(0.8, "hash field: the levels open one by one over this fraction "
                             "of the steps (0: all from the start)",
                             check="nonnegative")  # fmt: skip
    hash_distance_weight: float = option(1.0, "hash field: weight of | |f| - d | at the uniform "
                                         "samples, d: distance to the nearest point",
                                         check="nonnegative")  # fmt: skip
    resolution: int = option(128, "marching-cubes grid at the end", check="positive")
    device: str = option("cpu", "cpu or cuda (on --resume, default the run's own)")
    model: str = option(MODEL, flag=None)

    @classmethod
    def from_dict(cls, d, where: str = "config"):
        """The config saved in a run's config.json (untrusted): unknown field names, values of
        the wrong type (``true`` is not a number), non-finite numbers, integers beyond +-2^31 and
        out-of-range values (:meth:`check_values`) are a UserError naming ``where`` (the file),
        the field and the expected form."""
        from ..json_input import check_fields

        return cls(**check_fields(cls, d, where)).check_values(where)

    def check_values(self, where: str | None = None):
        """The checks of :meth:`validate` that do not need the device; ``where`` None: messages
        name the command-line flags, else the file ``where`` and the config field."""
        from ..json_input import field_error, is_device

        def fail(name: str, rule: str):
            return field_error(where, name, rule)

        if self.preset not in PRESET_NAMES:
            raise field_error(where, "preset", f"must be one of {', '.join(PRESET_NAMES)}, got "
                              f"{self.preset!r}")  # fmt: skip
        if self.field not in FIELDS:
            raise field_error(where, "field", f"must be one of {', '.join(FIELDS)}, got "
                              f"{self.field!r}")  # fmt: skip
        LoopConfig.check_section(self, fail)
        check_at_least(
            self,
            fail,
            1,
            "batch",
            "n_random",
            "n_layers",
            "width",
            "hash_width",
            "hash_levels",
            "hash_base_res",
            "hash_max_res",
        )
        check_at_least(self, fail, 0, "pos_freqs", "skip")
        if self.pos_freqs > 64:  # 2^64 * coordinates stays finite in float32
            raise field_error(where, "pos_freqs", f"must be at most 64, got {self.pos_freqs}")
        d_in = 3 * (1 + 2 * self.pos_freqs)
        if self.field == "mlp" and self.skip < self.n_layers and self.width <= d_in:
            raise field_error(where, "width", f"must exceed the encoded input ({d_in} for "
                              f"--pos-freqs {self.pos_freqs}) because of the skip "
                              "connection")  # fmt: skip
        if not 8 <= self.resolution <= 1024:
            raise field_error(where, "resolution", f"must be in [8, 1024], got {self.resolution}")
        if self.field == "hash":
            try:
                self.hash_grid()
            except ValueError as e:  # HashGrid's own checks (its names without "hash_")
                at = f"{where}: " if where else ""
                raise UserError(f"{at}the hash grid (hash_levels, hash_log2_size, hash_base_res, "
                                f"hash_max_res): {e}") from None  # fmt: skip
        if not 0 <= self.hash_c2f <= 1:
            raise field_error(where, "hash_c2f", f"must be in [0, 1], got {self.hash_c2f}")
        for name in ("eikonal_weight", "normal_weight", "fd_step",
                     "hash_distance_weight"):  # fmt: skip
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise field_error(where, name, f"must be finite and >= 0, got {v}")
        if not is_device(self.device):
            raise field_error(where, "device", f"must be cpu, cuda or cuda:N, got {self.device!r}")
        if self.model != MODEL:
            raise field_error(where, "model", f"must be {MODEL!r}, got {self.model!r}")
        return self

    def resolve(self):
        """A copy with the defaults that depend on the field or on the first invocation filled
        in: lr (1e-2 for the hash field, 1e-3 for the MLP), lr_final (lr / 10), lr_decay_steps
        (iters); this config is left as it is."""
        self = dataclasses.replace(self)  # (the copy filled in)
        if self.lr is None:
            self.lr = 1e-2 if self.field == "hash" else 1e-3
        if self.lr_final is None:
            self.lr_final = self.lr / 10
        if self.lr_decay_steps <= 0:
            self.lr_decay_steps = self.iters
        return self

    def hash_grid(self):
        """The :class:`~warpnerf.ops.encoding.HashGrid` of ``--field hash`` (ValueError when the
        hash settings do not make one)."""
        from ..ops.encoding import HashGrid

        return HashGrid(self.hash_levels, 2, self.hash_log2_size, self.hash_base_res,
                        self.hash_max_res)  # fmt: skip

    def validate(self):
        """The config a run reads: this one resolved (:meth:`resolve`), checked once
        (:meth:`check_values` and the device) and frozen (read-only); this one is left as is."""
        cfg = self.resolve().check_values()
        check_device(cfg.device)
        return cfg.freeze()


def load_points(path) -> tuple:
    """(points [N, 3] float32, normals [N, 3] or None) from .npz / .ply, or the built-in torus."""
    if str(path) == "builtin":
        from ..fields.sdf_scene import torus_scene
        from ..mesh import extract_mesh, sample_surface

        scene = torus_scene()
        v, f = extract_mesh(scene.sdf, [-1.2] * 3, [1.2] * 3, 96)
        return sample_surface(v, f, 5000, seed=1).astype(np.float32), None
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such point-cloud file")
    from ..safe_writes import open_input

    with contextlib.suppress(OSError), open_input(path, "point cloud", follow=True):
        pass  # a FIFO or device is refused here, never waited on (the PLY reader opens by name)
    normals = None
    try:
        if path.suffix == ".npz":
            from ..data.arrays import load_npz

            d = load_npz(path, "point cloud")  # (bounded inflation, no pickles)
            key = next((k for k in ("points", "verts", "vertices") if k in d), None)
            if key is None:
                raise UserError(f"{path}: needs an array 'points' or 'verts' (has {list(d)})")
            pts = d[key]
            normals = d["normals"] if "normals" in d else None
        elif path.suffix == ".ply":
            from ..mesh import read_ply_points

            pts, normals = read_ply_points(path)
        else:
            raise UserError(f"{path}: expected a .npz or .ply file")
        pts = np.asarray(pts, dtype=np.float32)
        if normals is not None:
            normals = np.asarray(normals, dtype=np.float32)
    except (
        OSError,
        ValueError,
        KeyError,
        IndexError,
        TypeError,
        EOFError,
        zipfile.BadZipFile,
    ) as e:
        raise UserError(f"{path}: unreadable point cloud ({type(e).__name__}: {e})") from None
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 16:
        raise UserError(f"{path}: points must be [N >= 16, 3], got {list(pts.shape)}")
    if not np.isfinite(pts).all():
        raise UserError(f"{path}: points contain NaN/Inf")
    if float((pts.max(0) - pts.min(0)).max()) <= 1e-12:
        raise UserError(f"{path}: all points coincide (zero extent)")
    if normals is not None:
        if normals.shape != pts.shape or not np.isfinite(normals).all():
            raise UserError(f"{path}: normals must be finite and shaped like the points")
        normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    return pts, normals


def normalisation(points: np.ndarray) -> tuple:
    """(center [3], scale): normalised = (p - center) * scale fits in [-0.8, 0.8]^3."""
    lo, hi = points.min(0), points.max(0)
    center = (lo + hi) / 2
    half = float((hi - lo).max() / 2)
    return center.astype(np.float64), 0.8 / max(half, 1e-12)


def _build(cfg):
    torch.manual_seed(cfg.seed)
    if cfg.field == "hash":
        model = HashPointSDF(cfg.hash_grid(), cfg.hash_width, fd_step=cfg.fd_step)
    else:
        model = NeuralSDF(cfg.n_layers, cfg.width, cfg.skip, cfg.pos_freqs)
    return model.to(cfg.device)


def open_levels(cfg, step: int) -> int:
    """The hash levels open at step ``step`` (0-based): one, then one more per equal share of
    ``hash_c2f * lr_decay_steps`` steps, all of them from there on."""
    span = cfg.hash_c2f * cfg.lr_decay_steps
    if span <= 0:
        return cfg.hash_levels
    return min(cfg.hash_levels, 1 + int(step * cfg.hash_levels / span))


@torch.no_grad()
def nearest_distance(x: torch.Tensor, points: torch.Tensor, chunk: int = 4096) -> torch.Tensor:
    """Distance [n] from each of x [n, 3] to the nearest of points [m, 3]."""
    return torch.cat([torch.cdist(x[s : s + chunk], points).min(1).values
                      for s in range(0, len(x), chunk)])  # fmt: skip


def load_sdf_run(run, device=None):
    """(cfg, model, checkpoint) of a neural-SDF run folder."""
    from ..json_input import read_run_config

    run = Path(run)
    if not (run / "config.json").exists():
        raise UserError(f"{run}: not a training run (needs a readable config.json)")
    d = read_run_config(run / "config.json")
    if not isinstance(d, dict) or d.get("model") != MODEL:
        model = d.get("model") if isinstance(d, dict) else None
        raise UserError(f"{run}: not a neural-SDF run (config model {model!r})")
    if not (run / CHECKPOINT).exists():  # (a FIFO or a link: load_checkpoint names it)
        raise UserError(f"{run}: no {CHECKPOINT} yet (the run never reached a checkpoint)")
    if device:  # (moved to another device)
        d["device"] = device
    cfg = SDFConfig.from_dict(d, str(run / "config.json")).freeze()
    check_device(cfg.device, str(run))
    keys = ("step", "model", "optimizer", "generator", "history", "normalisation")
    ckpt = load_checkpoint(run / CHECKPOINT, cfg.device, keys)
    # the config's sizes bounded by the weights the checkpoint holds, before the model is built
    model = build_for_weights(lambda: _build(cfg), ckpt["model"], run / CHECKPOINT,
                              run / "config.json")  # fmt: skip
    load_weights(model, ckpt["model"], run / CHECKPOINT, "network weights")
    if cfg.field == "hash":  # the levels open at the checkpoint's step
        model.set_open_levels(open_levels(cfg, ckpt["step"]))
    return cfg, model, ckpt


def sdf_loss(model, surf, normals, rand, cfg, uniform_dist=None):
    """(loss, parts): mean |f| on the points, eikonal on the random and the surface points,
    optional normals, and given ``uniform_dist`` (the distances [m] of the first m random points
    to the point cloud) SAL's sign-agnostic | |f| - d | on those points (Atzmon & Lipman 2020);
    the parts are detached 0-dim tensors (read at the loop's one sync)."""
    pts = torch.cat([surf, rand])
    f, g = model.gradient(pts)
    n = surf.shape[0]
    l_surf = f[:n].abs().mean()
    l_eik = ((g.norm(dim=-1) - 1.0) ** 2).mean()
    loss = l_surf + cfg.eikonal_weight * l_eik
    parts = {"surface": l_surf.detach(), "eikonal": l_eik.detach()}
    if uniform_dist is not None and cfg.hash_distance_weight > 0:
        f_uni = f[n : n + len(uniform_dist)]
        l_dist = (f_uni.abs() - uniform_dist).abs().mean()
        loss = loss + cfg.hash_distance_weight * l_dist
        parts["distance"] = l_dist.detach()
    if normals is not None and cfg.normal_weight > 0:
        l_n = (1 - torch.nn.functional.cosine_similarity(g[:n], normals, dim=-1)).mean()
        loss = loss + cfg.normal_weight * l_n
        parts["normal"] = l_n.detach()
    return loss, parts


def train_sdf(cfg: SDFConfig, run, resume=False, progress=True, log=print, device=None,
              tensorboard: int = 0, hooks=()):  # fmt: skip
    """Trains (or resumes) a neural SDF in folder ``run``; returns the final metrics dict
    (``tensorboard`` N > 0: also TensorBoard event files in RUN/tensorboard, a record every N
    steps; ``hooks``: :class:`~warpnerf.train.loop.LoopHook` s, e.g. the live viewer).

    SIGINT/SIGTERM during training finish the current step, checkpoint it and raise
    :class:`~warpnerf.errors.Interrupted` (no mesh or metrics); ``resume=True`` then continues
    exactly (bit-identical on CPU with the same seed)."""
    with contextlib.ExitStack() as locks:  # the run folder's lock, held to the end
        return _train_sdf(cfg, Path(run), resume, progress, log, device, locks, tensorboard,
                          hooks)  # fmt: skip


def _train_sdf(cfg, run: Path, resume, progress, log, device, locks, tensorboard, hooks):
    ckpt = None
    if resume:
        lock_run(run, locks)
        saved, model, ckpt = load_sdf_run(run, device)
        resume_checks(run, ckpt["step"], cfg.iters, OUTPUTS)
        cfg = dataclasses.replace(saved, iters=cfg.iters, max_seconds=cfg.max_seconds).validate()
    else:
        cfg = cfg.validate()  # (resolved, checked and frozen: what the run reads)
        if (run / CHECKPOINT).exists():
            raise UserError(f"{run}: already holds a run; pass --resume or choose another --out")
        model = None
    pts_np, nrm_np = load_points(cfg.points)
    center, scale = normalisation(pts_np)
    if model is None:
        model = _build(cfg)
    tb = [TensorBoardLog(run, tensorboard)] if tensorboard else []  # (checks; writes nothing)
    if not resume:
        claim_run(run, locks, OUTPUTS, CHECKPOINT)
    write_json(run / "config.json", cfg.to_dict())
    dev = cfg.device
    pts = torch.as_tensor((pts_np - center) * scale, dtype=torch.float32, device=dev)
    nrm = torch.as_tensor(nrm_np, device=dev) if nrm_np is not None else None
    # local scale of the near-surface samples: distance to the 8th nearest point (on a subset)
    sub = pts[torch.randperm(len(pts), generator=torch.Generator().manual_seed(0))[:2000].to(dev)]
    sigma = float(torch.cdist(sub, pts).topk(9, largest=False).values[:, -1].median())
    task = SDFTask(cfg, model, pts, nrm, sigma, {"center": center.tolist(), "scale": scale})
    if ckpt is not None:
        task.gen.set_state(ckpt["generator"].cpu())
    settings = LoopSettings.of(cfg, "train sdf")
    history = run_loop(
        task, settings, run=run, checkpoint=CHECKPOINT, resume_from=ckpt, progress=progress,
        log=log, hooks=[*hooks, *tb],
    )  # fmt: skip
    metrics = finish_sdf_run(run, model, cfg, pts_np, center, scale, log=log)
    metrics.update(step=history["step"][-1] if history["step"] else 0,
                   seconds=history["seconds"][-1] if history["seconds"] else 0.0)  # fmt: skip
    write_json(run / "metrics.json", metrics)
    return metrics


class SDFTask(Task):
    """A neural SDF fitted to points as a :class:`~warpnerf.train.loop.Task`: each step draws
    surface points, uniform box points and points near the surface, and minimises
    :func:`sdf_loss`."""

    method = MODEL  # its kind of run (train/methods.py)

    history_keys = ("surface", "eikonal")

    def __init__(self, cfg, model, pts, nrm, sigma, normalisation):
        self.cfg, self.model, self.pts, self.nrm, self.sigma = cfg, model, pts, nrm, sigma
        self.normalisation = normalisation
        self.gen = torch.Generator().manual_seed(cfg.seed)

    def parameters(self):
        return list(self.model.parameters())

    def optimizer(self, params, lr):
        if self.cfg.field == "hash":  # instant-ngp's Adam: tiny eps for the sparse table updates
            return adam(params, lr=lr, betas=(0.9, 0.99), eps=1e-15)
        return adam(params, lr=lr)

    def loss(self, step):
        cfg, pts, gen, dev = self.cfg, self.pts, self.gen, self.pts.device
        idx = torch.randint(0, len(pts), (cfg.batch,), generator=gen).to(dev)
        half = cfg.n_random // 2
        near_idx = torch.randint(0, len(pts), (cfg.n_random - half,), generator=gen).to(dev)
        noise = torch.randn(cfg.n_random - half, 3, generator=gen).to(dev) * self.sigma
        uni = (torch.rand(half, 3, generator=gen) * 2 - 1).to(dev)
        rand = torch.cat([uni, pts[near_idx] + noise])
        surf_nrm = self.nrm[idx] if self.nrm is not None else None
        dist = None
        if cfg.field == "hash":
            self.model.set_open_levels(open_levels(cfg, step))
            if cfg.hash_distance_weight > 0:
                dist = nearest_distance(uni, pts)
        loss, parts = sdf_loss(self.model, pts[idx], surf_nrm, rand, cfg, dist)
        return loss, {"surface": parts["surface"], "eikonal": parts["eikonal"]}

    def postfix(self, history):
        return {"surface": f"{history['surface'][-1]:.4f}",
                "eikonal": f"{history['eikonal'][-1]:.4f}"}  # fmt: skip

    def state(self):
        return {
            "model": self.model.state_dict(),
            "generator": self.gen.get_state(),
            "normalisation": self.normalisation,
        }


@torch.no_grad()
def chamfer(a: torch.Tensor, b: torch.Tensor, chunk: int = 4096) -> tuple:
    """(mean over a of the distance to b, mean over b of the distance to a)."""
    return (nearest_distance(a, b, chunk).mean().item(),
            nearest_distance(b, a, chunk).mean().item())  # fmt: skip


def eikonal_stats(model, points: torch.Tensor) -> dict:
    _, g = model.gradient(points, create_graph=False)
    r = (g.norm(dim=-1) - 1).abs()
    return {"mean": r.mean().item(), "p95": r.quantile(0.95).item(), "max": r.max().item()}


def finish_sdf_run(run, model, cfg, pts_np, center, scale, log=print):
    """Mesh (input units) + screenshot + Chamfer (in bbox diagonals) + eikonal statistics.
    mesh.ply is the zero level set cleaned as `warpnerf mesh` cleans a run's
    (:func:`~warpnerf.mesh.clean_mesh`: components under :data:`~warpnerf.mesh.DEFAULT_CLEAN`
    of the area dropped, e.g. a hash field's surfaces away from the points); "vertices",
    "faces" and the Chamfer distances are of that mesh, "mesh_clean" says what was dropped
    (and ``log`` a line)."""
    from ..mesh import (
        DEFAULT_CLEAN,
        clean_mesh,
        extract_mesh,
        sample_surface,
        screenshot,
        write_ply,
    )

    model.eval()
    dev = cfg.device
    v, f = extract_mesh(lambda p: model(p), [-1] * 3, [1] * 3, cfg.resolution, 0.0, device=dev)
    n_faces, cleaned = int(len(f)), None
    if n_faces:
        v, f, c = clean_mesh(v, f, DEFAULT_CLEAN)
        cleaned = {"clean": DEFAULT_CLEAN, "faces_extracted": n_faces,
                   **{k: c[k] for k in ("components", "components_removed",
                                        "area_removed_fraction")}}  # fmt: skip
        log(f"mesh.ply: {c['components_removed']} of {c['components']} components dropped "
            f"(under {DEFAULT_CLEAN:.0%} of the area; {c['area_removed_fraction']:.2%} of it), "
            f"{len(f)} of {n_faces} faces kept")  # fmt: skip
    m = {"vertices": len(v), "faces": len(f)}
    if cleaned is not None:
        m["mesh_clean"] = cleaned
    diag = float(np.linalg.norm(pts_np.max(0) - pts_np.min(0)))
    if len(f):
        v_world = v / scale + center
        write_ply(run / "mesh.ply", v_world, f)
        try:
            screenshot(run / "mesh.png", v_world, f)
        except ImportError as e:  # pyvista is a dependency; tolerate machines without it
            print(f"warning: no mesh screenshot ({e})")
        surf = torch.as_tensor(sample_surface(v_world, f, 30_000), dtype=torch.float32)
        a_to_b, b_to_a = chamfer(surf, torch.as_tensor(pts_np))
        m["chamfer"] = 0.5 * (a_to_b + b_to_a) / diag
        m["chamfer_mesh_to_points"] = a_to_b / diag
        m["chamfer_points_to_mesh"] = b_to_a / diag
    else:
        m["chamfer"] = math.inf
    g = torch.Generator().manual_seed(123)
    box = (torch.rand(20_000, 3, generator=g) * 2 - 1).to(dev)
    pts = torch.as_tensor((pts_np - center) * scale, dtype=torch.float32, device=dev)
    m["eikonal_residual_box"] = eikonal_stats(model, box)
    m["eikonal_residual_surface"] = eikonal_stats(model, pts)
    with torch.no_grad():
        m["surface_abs_sdf_mean"] = float(model(pts).abs().mean()) / scale / diag
    m["units"] = "chamfer and surface |sdf| in units of the point cloud's bounding-box diagonal"
    return m


# ------------------------------------------------- the method, registered as an added one is


def _open_point_sdf(run, device=None) -> LoadedRun:
    cfg, model, ck = load_sdf_run(run, device)
    model.eval()
    title = f"{Path(run).name}: neural SDF ({cfg.field})"
    return LoadedRun(cfg, model, None, title, extra={"normalisation": ck["normalisation"]})


def _point_sdf_mesh(o: LoadedRun, bounds, level) -> dict:
    """A neural SDF's zero level set in its normalised box, vertices mapped back to the point
    cloud's units."""
    import numpy as np

    from .surface_level import plain_level

    cfg, model = o.cfg, o.model
    c, s = o.extra["normalisation"]["center"], o.extra["normalisation"]["scale"]
    b = bounds or 1.0  # in the normalised frame
    level = plain_level(level, "a neural SDF fitted to points") or 0.0
    return dict(fn=lambda p: model(p.to(cfg.device)), lower=[-b] * 3, upper=[b] * 3, level=level,
                shown_level=level, what="sdf run", back=lambda v: v / s + np.asarray(c),
                device=cfg.device, field=None, density=False, cameras=None)  # fmt: skip


def _point_sdf_task(task) -> LoadedRun:
    return LoadedRun(task.cfg, task.model)


register_method(Method(MODEL, ("sdf",), "neural-SDF", "point_sdf", _open_point_sdf,
                       _point_sdf_task, mesh=_point_sdf_mesh))  # fmt: skip
