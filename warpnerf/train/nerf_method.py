"""The NeRF/VolSDF method (`train nerf`, `train volsdf`) in the registry of kinds of run
(:mod:`warpnerf.train.methods`): how a saved run is opened for the viewer and `mesh`, what
`mesh` marches, and its registration, made as an added method's is (docs/ARCHITECTURE.md)."""

from __future__ import annotations

from pathlib import Path

from ..errors import UserError
from .methods import LoadedRun, Method, register_method
from .nerf_config import MODEL

__all__: list = []


def _open_nerf(run, device=None) -> LoadedRun:
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

    return LoadedRun(cfg, model, None, f"{run.name}: {cfg.field}", reload, load_cameras=cameras)


def _nerf_mesh(o: LoadedRun, bounds, level) -> dict:
    """A NeRF/VolSDF run's surface: an SDF field's level set (the zero level unless ``level``
    is given; "rendered": the level where its renders put the surface, with the figures of
    :func:`~warpnerf.train.surface_level.rendered_level` as ``level_rule``), else the density's
    level set marched as -density at -level (inside negative, like an SDF); with no level
    given, level and shown_level are None: the command chooses the density from the grid
    (:func:`warpnerf.mesh.density_level`)."""
    from .surface_level import mesh_level, plain_level

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
    if o.model.kind == "sdf":  # the SDF's level set (zero unless given)
        level, rule = mesh_level(o.model, cfg, level, o.training_cameras)
        return dict(out, fn=lambda p: field.sdf(p.to(cfg.device)), level=level, shown_level=level,
                    what=cfg.field, density=False, level_rule=rule)  # fmt: skip
    level = plain_level(level, "a NeRF run (its default level is where its rays turn opaque)")
    return dict(out, fn=lambda p: -field.density(p.to(cfg.device))[0],
                level=None if level is None else -level, shown_level=level, what="nerf",
                density=True)  # fmt: skip


def _nerf_task(task) -> LoadedRun:
    return LoadedRun(task.cfg, task.model, getattr(task, "train", None))


register_method(Method(MODEL, ("nerf", "volsdf"), "NeRF/VolSDF", "radiance", _open_nerf,
                       _nerf_task, renders=True, mesh=_nerf_mesh))  # fmt: skip
