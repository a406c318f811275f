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

and `warpnerf train mymethod` exists with MyConfig's flags. The built-in methods register so in
their own modules (nerf_method.py, sdf.py, box_fit.py); an outside package names its module in
the ``warpnerf.methods`` entry points (:mod:`warpnerf.plugins`). Every method's `train`
commands come out of one path (:mod:`warpnerf.cli.train_commands`): the front end registered
for a command (``register_train_command``: cli/train.py registers the built-ins' four, with
presets, resume checks and data parallel), else the one generated from ``config`` and
``train``.

``view`` picks how the viewer shows it: "radiance" (a :class:`~warpnerf.fields.model.
RadianceModel` with a NeRFConfig: volume rendering), "point_sdf" (an SDF network in [-1, 1]^3,
sphere-traced) or "box" (an analytic SDF volume). ``open_run(run, device) -> LoadedRun`` and
``open_task(task) -> LoadedRun`` give the viewer (and ``mesh``) what that view needs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..errors import UserError
from ..plugins import Registry, add_entry

__all__ = ["Method", "LoadedRun", "Opened", "METHODS", "register_method", "method_of_config",
           "method_of_run", "method_of_task", "VIEWS"]  # fmt: skip

VIEWS = ("radiance", "point_sdf", "box")  # the viewer's ways of showing a run


@dataclass
class LoadedRun:
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


Opened = LoadedRun  # its name before issue 46, kept for one release


@dataclass(frozen=True)
class Method:
    """A kind of run. ``name``: config.json's ``model``; ``commands``: the `train` subcommands
    that make it; ``what``: its name in messages; ``view``: one of :data:`VIEWS`;
    ``open_run(run, device) -> LoadedRun``; ``open_task(task) -> LoadedRun`` (the live viewer);
    ``renders``: eval, render and export take it (cameras and images: the NeRF pipeline);
    ``mesh(opened, bounds, level) -> dict`` (None: no surface to extract; ``level``: None, a
    number or "rendered", which a method without renders refuses,
    :func:`~warpnerf.train.surface_level.plain_level`): what `warpnerf mesh`
    marches, as the keywords of the CLI's mesh source (fn: points on ``device`` -> values, lower
    and upper corners, the marched level and the level asked for (both None: a density level
    the command chooses from the grid), optional level_rule: the figures of a level the method
    chose (:func:`~warpnerf.train.surface_level.rendered_level`), back: vertices -> the data's
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


# The built-in methods register in their own modules (nerf_method.py, sdf.py, box_fit.py; imported
# by warpnerf.train in that order), an outside package's through the "warpnerf.methods" entry
# points (warpnerf/plugins.py), loaded when the registry is first read.
METHODS: dict[str, Method] = Registry("warpnerf.methods")
LEGACY = "nerf"  # a config.json without ``model``: a NeRF/VolSDF run written before the registry


def register_method(method: Method) -> Method:
    """Adds ``method`` to :data:`METHODS` (ValueError for a name registered already)."""
    if not add_entry(METHODS, method.name, method):
        raise ValueError(f"method {method.name!r} is registered already")
    return method


def method_of_config(saved: dict, where: str = "config.json") -> Method:
    """The method of a run's saved config (a dict read from config.json); UserError naming
    ``where`` for a ``model`` no method has."""
    name = saved.get("model", LEGACY) if isinstance(saved, dict) else None
    if not isinstance(name, str) or name not in METHODS:
        kinds = ", ".join(f"{m.name} ({m.what})" for m in METHODS.values())
        from ..json_input import show

        raise UserError(f"{where}: model {show(name)} is not a kind of run warpnerf knows "
                        f"({kinds})")  # fmt: skip
    return METHODS[name]


def method_of_run(run) -> Method:
    """The method of run folder ``run`` (its config.json, read bounded); UserError when it is
    not a run folder."""
    from ..json_input import read_run_config

    run = Path(run)
    if not run.is_dir():
        raise UserError(f"{run}: no such run folder")
    path = run / "config.json"
    if not path.exists():  # (a FIFO or a link there: read_json names it)
        raise UserError(f"{run}: not a training run (no config.json)")
    saved = read_run_config(path)
    if not isinstance(saved, dict):
        raise UserError(f"{path}: unreadable (expected a JSON object)")
    return method_of_config(saved, str(path))


def method_of_task(task) -> Method:
    """The method of a training task (its class's ``method``)."""
    name = getattr(type(task), "method", None)
    if name not in METHODS:
        raise TypeError(f"{type(task).__name__} names no registered method ({name!r})")
    return METHODS[name]
