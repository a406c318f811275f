"""The registry of methods: the kinds of run `warpnerf train` makes (NeRF/VolSDF, a neural SDF
fitted to points, a box fit), each with how to open a saved run and a live training task.

A run folder's config.json names its method under ``model`` (a NeRF/VolSDF run written before
the registry has no ``model`` key: it is a NeRF run). The tools that take a run folder
(``view``, ``mesh``, ``eval``, ``render``, ``export``) and the live viewer ask the registry
(:func:`method_of_run`, :func:`method_of_task`), never the run's keys or the task's attributes.

Adding a kind of run: its module (config, task, loader, trainer), then one entry::

    register_method(Method("mymethod", ("mymethod",), "my method", "radiance",
                           open_run=open_my_run, open_task=open_my_task,
                           config=MyConfig, train=train_my_method))

and `warpnerf train mymethod` exists with MyConfig's flags (the four built-in commands keep
their own, richer front ends in cli/train.py: presets, resume checks, data parallel).

``view`` picks how the viewer shows it: "radiance" (a :class:`~warpnerf.fields.model.
RadianceModel` with a NeRFConfig: volume rendering), "point_sdf" (an SDF network in [-1, 1]^3,
sphere-traced) or "box" (an analytic SDF volume). ``open_run(run, device) -> Opened`` and
``open_task(task) -> Opened`` give the viewer (and ``mesh``) what that view needs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..errors import UserError

__all__ = ["Method", "Opened", "METHODS", "register_method", "method_of_config", "method_of_run",
           "method_of_task", "VIEWS"]  # fmt: skip

VIEWS = ("radiance", "point_sdf", "box")  # the viewer's ways of showing a run


@dataclass
class Opened:
    """A run (or a training task) opened for the viewer and the mesh tool: its config, the
    model the view renders (a RadianceModel, an SDF network, an SDFVolume), the training
    cameras for the overlay (or None), a title, and ``reload() -> step`` (None: nothing to
    reload; a NeRF run reloads its latest checkpoint while another process trains it)."""

    cfg: object
    model: object
    cameras: object = None
    title: str = ""
    reload: Callable | None = None  # reload(lock) -> step; lock guards the copy into the model
    extra: dict | None = None  # what a method's own tools need besides (a checkpoint's keys)
    load_cameras: Callable | None = None  # loads ``cameras`` when first asked (reads the data)

    def training_cameras(self):
        """The training cameras (loaded by ``load_cameras`` on the first call), or None."""
        if self.cameras is None and self.load_cameras is not None:
            self.cameras, self.load_cameras = self.load_cameras(), None
        return self.cameras


@dataclass(frozen=True)
class Method:
    """A kind of run. ``name``: config.json's ``model``; ``commands``: the `train` subcommands
    that make it; ``what``: its name in messages; ``view``: one of :data:`VIEWS`;
    ``open_run(run, device) -> Opened``; ``open_task(task) -> Opened`` (the live viewer);
    ``renders``: eval, render and export take it (cameras and images: the NeRF pipeline);
    ``mesh(opened, bounds, level) -> dict`` (None: no surface to extract): what `warpnerf mesh`
    marches, as the keywords of the CLI's mesh source (fn: points on ``device`` -> values, lower
    and upper corners, the marched level and the level asked for (both None: a density level
    the command chooses from the grid), back: vertices -> the data's
    units or None, field for --colors or None, density: fn is minus a density, cameras: a
    callable giving the training cameras in the mesh's frame (or None), or None: what the
    default cleaning culls by; optional weights: None, or a callable (lower, upper, progress)
    -> (a grid of the cells where training rays put weight, with ``grid``, ``lower`` and
    ``upper``, or None, and why not), :func:`warpnerf.train.visibility.training_weight_grid`,
    which the default cleaning culls by first). A method
    added after the built-in ones gives ``config`` (a dataclass declared with
    :func:`~warpnerf.options.option`) and ``train(cfg, out, resume, progress) -> result``
    (JSON-able): `warpnerf train <command>` then exists with the config's flags, ``--out``,
    ``--resume`` and ``--quiet`` (``help``: its line in `warpnerf train --help`)."""

    name: str
    commands: tuple
    what: str
    view: str
    open_run: Callable
    open_task: Callable
    renders: bool = False
    mesh: Callable | None = None
    config: type | None = None
    train: Callable | None = None
    help: str = ""

    def __post_init__(self):
        if self.view not in VIEWS:
            raise ValueError(f"view must be one of {', '.join(VIEWS)}, got {self.view!r}")


METHODS: dict[str, Method] = {}
LEGACY = "nerf"  # a config.json without ``model``: a NeRF/VolSDF run written before the registry


def register_method(method: Method) -> Method:
    """Adds ``method`` to :data:`METHODS` (ValueError for a name registered already)."""
    if method.name in METHODS:
        raise ValueError(f"method {method.name!r} is registered already")
    METHODS[method.name] = method
    return method


def method_of_config(saved: dict, where: str = "config.json") -> Method:
    """The method of a run's saved config (a dict read from config.json); UserError naming
    ``where`` for a ``model`` no method has."""
    name = saved.get("model", LEGACY) if isinstance(saved, dict) else None
    if not isinstance(name, str) or name not in METHODS:
        kinds = ", ".join(f"{m.name} ({m.what})" for m in METHODS.values())
        from ..jsonio import show

        raise UserError(f"{where}: model {show(name)} is not a kind of run warpnerf knows "
                        f"({kinds})")  # fmt: skip
    return METHODS[name]


def method_of_run(run) -> Method:
    """The method of run folder ``run`` (its config.json, read bounded); UserError when it is
    not a run folder."""
    from ..jsonio import read_json

    run = Path(run)
    if not run.is_dir():
        raise UserError(f"{run}: no such run folder")
    path = run / "config.json"
    if not path.exists():  # (a FIFO or a link there: read_json names it)
        raise UserError(f"{run}: not a training run (no config.json)")
    saved = read_json(path, "run config")
    if not isinstance(saved, dict):
        raise UserError(f"{path}: unreadable (expected a JSON object)")
    return method_of_config(saved, str(path))


def method_of_task(task) -> Method:
    """The method of a training task (its class's ``method``)."""
    name = getattr(type(task), "method", None)
    if name not in METHODS:
        raise TypeError(f"{type(task).__name__} names no registered method ({name!r})")
    return METHODS[name]


# ------------------------------------------------------------------------ the built-in methods


def _open_nerf(run, device=None) -> Opened:
    import contextlib

    from .nerf_run import load_data, load_run, with_refined_poses

    run = Path(run)
    cfg, model, _ = load_run(run, device)

    def cameras():  # (read only when asked: `mesh --keep-all` never reads the images)
        with contextlib.suppress(UserError):  # the cameras are an overlay: the data may be gone
            return with_refined_poses(model, load_data(cfg, "train"), "train")
        return None

    def reload(lock) -> int:
        """Loads the run's latest checkpoint into the opened model (copied in under ``lock``,
        a context manager); returns its step."""
        _, fresh, ck = load_run(run, device)
        with lock:
            for k, part in model.parts().items():
                if part is not None:
                    part.load_state_dict(fresh.parts()[k].state_dict())
        return int(ck["step"])

    return Opened(cfg, model, None, f"{run.name}: {cfg.field}", reload, load_cameras=cameras)


def _nerf_mesh(o: Opened, bounds, level) -> dict:
    """A NeRF/VolSDF run's surface: an SDF field's zero level set, else the density's level set
    marched as -density at -level (inside negative, like an SDF); with no level given, level
    and shown_level are None: the command chooses the density from the grid
    (:func:`warpnerf.mesh.density_level`)."""
    cfg, field = o.cfg, o.model.field
    b = bounds or (cfg.aabb if cfg.aabb > 0 else 1.5)
    back = None
    if cfg.scene is not None:  # COLMAP/LLFF: vertices back to the capture's world units
        from ..data.capture import normalised_to_world

        ndc = cfg.ndc_camera()
        back = lambda v: normalised_to_world(v, cfg.scene["transform"], ndc)  # noqa: E731
    lo, hi = [-b] * 3, [b] * 3
    if cfg.ndc_camera() is not None:  # NDC box; z = 1 is infinity
        lo[2], hi[2] = -1.0, 0.99
    # the training cameras, in the mesh's frame, for `mesh`'s culling (not NDC: another frame)
    cams = o.training_cameras if cfg.ndc_camera() is None else None  # (loaded when culling)

    def weights(lower, upper, progress=False):  # the cells where the training rays put weight
        from .visibility import training_weight_grid

        ds = o.training_cameras()  # (NDC too: the rays and the grid are in the field's frame)
        if ds is None:
            return None, "the run's training data is not at hand"
        return training_weight_grid(o.model, cfg, ds, lower, upper, progress=progress)

    out = dict(lower=lo, upper=hi, back=back, device=cfg.device, field=field, cameras=cams,
               weights=weights)  # fmt: skip
    if o.model.kind == "sdf":  # the SDF's zero level set
        level = level or 0.0
        return dict(out, fn=lambda p: field.sdf(p.to(cfg.device)), level=level, shown_level=level,
                    what=cfg.field, density=False)  # fmt: skip
    return dict(out, fn=lambda p: -field.density(p.to(cfg.device))[0],
                level=None if level is None else -level, shown_level=level, what="nerf",
                density=True)  # fmt: skip


def _nerf_task(task) -> Opened:
    return Opened(task.cfg, task.model, getattr(task, "train", None))


def _open_point_sdf(run, device=None) -> Opened:
    from .sdf import load_sdf_run

    cfg, model, ck = load_sdf_run(run, device)
    model.eval()
    title = f"{Path(run).name}: neural SDF ({cfg.field})"
    return Opened(cfg, model, None, title, extra={"normalisation": ck["normalisation"]})


def _point_sdf_mesh(o: Opened, bounds, level) -> dict:
    """A neural SDF's zero level set in its normalised box, vertices mapped back to the point
    cloud's units."""
    import numpy as np

    cfg, model = o.cfg, o.model
    c, s = o.extra["normalisation"]["center"], o.extra["normalisation"]["scale"]
    b = bounds or 1.0  # in the normalised frame
    level = level or 0.0
    return dict(fn=lambda p: model(p.to(cfg.device)), lower=[-b] * 3, upper=[b] * 3, level=level,
                shown_level=level, what="sdf run", back=lambda v: v / s + np.asarray(c),
                device=cfg.device, field=None, density=False, cameras=None)  # fmt: skip


def _point_sdf_task(task) -> Opened:
    return Opened(task.cfg, task.model)


def _open_box(run, device=None) -> Opened:
    import contextlib

    from ..data.blender import load_blender
    from ..fields.sdf_volume import SDFVolume
    from ..io import load_weights
    from .box_fit import load_box_run

    cfg, data, dev, ckpt = load_box_run(run, device)
    volume = SDFVolume("box", alpha=cfg.alpha, beta=cfg.beta).to(dev)
    load_weights(volume, ckpt["volume"], Path(run) / "checkpoint.pt", "box parameters")
    train = None
    with contextlib.suppress(UserError):  # the cameras are an overlay
        train = load_blender(data, "train", background=(cfg.background,) * 3, holdout=0,
                             allow_outside=cfg.allow_outside_paths)  # fmt: skip
    return Opened(cfg, volume, train, f"{Path(run).name}: box fit")


def _box_task(task) -> Opened:
    from types import SimpleNamespace

    n, h, w = task.images.shape[:3]
    cams = SimpleNamespace(c2w=task.c2w, intrinsics=task.intrinsics, width=w, height=h,
                           images=task.images)  # fmt: skip
    return Opened(task.cfg, task.volume, cams)


from .box_fit import MODEL as _BOX  # noqa: E402  (each method module's config.json name)
from .nerf_config import MODEL as _NERF  # noqa: E402
from .sdf import MODEL as _POINT_SDF  # noqa: E402

register_method(Method(_NERF, ("nerf", "volsdf"), "NeRF/VolSDF", "radiance", _open_nerf,
                       _nerf_task, renders=True, mesh=_nerf_mesh))  # fmt: skip
register_method(Method(_POINT_SDF, ("sdf",), "neural-SDF", "point_sdf", _open_point_sdf,
                       _point_sdf_task, mesh=_point_sdf_mesh))  # fmt: skip
register_method(Method(_BOX, ("box",), "box fit", "box", _open_box, _box_task))
