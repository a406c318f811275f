"""Geometry evaluation of an SDF run (``warpnerf eval --geometry``): accuracy, completeness and
Chamfer distance of its surface against a reference (the materials scene's analytic ground truth,
:mod:`warpnerf.data.materials_truth`, or a point cloud), of the mesh `warpnerf mesh` delivers,
and the rendered depth's error against the analytic first hits."""

from __future__ import annotations

import torch

from ..data.materials_truth import (
    MATERIALS_BELOW,
    MATERIALS_NAMES,
    materials_depth,
    materials_reference,
    materials_shape_ids,
    materials_visible,
)
from ..errors import UserError
from .nerf import load_data, load_run, render_dataset_image, with_refined_poses
from .surface_level import check_level

__all__ = ["evaluate_geometry", "surface_figures", "mesh_culling", "shape_signed_medians",
           "depth_error", "rendered_depths", "sdf_field_names", "disk_top_profile"]  # fmt: skip


def sdf_field_names() -> str:
    """The registered fields with an SDF geometry, comma-separated (for error messages)."""
    from ..fields.model import fields_with

    return ", ".join(fields_with(geometry="sdf"))


@torch.no_grad()
def rendered_depths(model, cfg, ds, depth_fn, views: int = 10, min_opacity: float = 0.5) -> dict:
    """The rendered surface depth against the reference's along the pixels of the first
    ``views`` images of ``ds`` (0: all) that the reference hits and the run renders opaque.

    Each image is rendered with the run's own renderer; its surface depth is expected depth /
    opacity, kept where ``depth_fn(o, d)`` (true distance along the unit rays, inf on a miss)
    is finite and the opacity exceeds ``min_opacity``. Units: the rays' (the data's world units
    for Blender-format runs).

    Returns:
        {"origins", "directions" [m, 3] float64, "rendered", "true" [m] float64 (on the CPU),
        "views": the images rendered}.
    """
    from .nerf import dataset_rays

    n = ds.images.shape[0] if not views else min(views, ds.images.shape[0])
    parts = {"origins": [], "directions": [], "rendered": [], "true": []}
    for i in range(n):
        _, depth, opacity = render_dataset_image(model, cfg, ds, i)
        o, d = dataset_rays(cfg, ds, image=i)
        o, d = o.double(), d.double()
        t_true = depth_fn(o, d)  # (unit directions)
        depth, opacity = depth.reshape(-1), opacity.reshape(-1)
        ok = torch.isfinite(t_true) & (opacity > min_opacity)
        for k, v in zip(parts, (o[ok], d[ok], (depth[ok] / opacity[ok]).double(), t_true[ok])):
            parts[k].append(v.cpu())
    out = {k: torch.cat(v) if v else torch.zeros((0, 3) if k in ("origins", "directions")
                                                  else 0, dtype=torch.float64)
           for k, v in parts.items()}  # fmt: skip
    return {**out, "views": n}


def depth_error(model, cfg, ds, depth_fn, views: int = 10, min_opacity: float = 0.5,
                shapes=None) -> dict:  # fmt: skip
    """Mean and median |rendered depth - true depth| over the pixels of
    :func:`rendered_depths` (the first ``views`` images of ``ds``, 0: all, that the reference
    hits and the run renders opaque).

    ``shapes`` (optional): (names, ids_fn) with ``ids_fn(points [m, 3] numpy) -> [m]`` the index
    into ``names`` of the shape each true hit point lies on; the figures are then also given per
    shape under "depth_by_shape", with the signed median of rendered - true depth (positive: the
    rendered surface lies behind the true one, seen from the camera).

    Returns:
        {"depth_error_mean", "depth_error_median" (None without such pixels), "depth_pixels",
        "depth_views"} (+ "depth_by_shape": {name: {"pixels", "mean", "median",
        "signed_median"}} for the shapes with pixels).
    """
    r = rendered_depths(model, cfg, ds, depth_fn, views, min_opacity)
    s = r["rendered"] - r["true"]
    e = s.abs()
    out = {
        "depth_error_mean": float(e.mean()) if e.numel() else None,
        "depth_error_median": float(e.median()) if e.numel() else None,
        "depth_pixels": int(e.numel()),
        "depth_views": r["views"],
    }
    if shapes is not None:
        names, ids_fn = shapes
        hits = r["origins"] + r["true"].unsqueeze(-1) * r["directions"]
        ids = torch.as_tensor(ids_fn(hits.numpy()), dtype=torch.long) if len(hits) else None
        per = {}
        for k, name in enumerate(names):
            sel = ids == k if ids is not None else None
            if sel is None or not bool(sel.any()):
                continue
            per[name] = {"pixels": int(sel.sum()), "mean": float(e[sel].mean()),
                         "median": float(e[sel].median()),
                         "signed_median": float(s[sel].median())}  # fmt: skip
        out["depth_by_shape"] = per
    return out


def _surface_distances(v, f, ref, points, cfg, below=None) -> dict:
    """Accuracy / completeness / Chamfer of the mesh (points sampled on it, mapped to the data's
    world units) against the reference points; mesh points with z < ``below`` left out."""
    import numpy as np

    from ..mesh import sample_surface
    from .sdf import chamfer

    m = sample_surface(v, f, points, seed=0)
    if cfg.scene is not None:
        from ..data.capture import normalised_to_world

        m = normalised_to_world(m, cfg.scene["transform"], cfg.ndc_camera())
        m = m[np.isfinite(m).all(1)]
    if below is not None:
        m = m[m[:, 2] >= below]
    if len(m) == 0:
        return {"accuracy": None, "completeness": None, "chamfer": None, "mesh_faces": len(f),
                "surface_points": 0}  # fmt: skip
    dev = torch.device(cfg.device)
    acc, comp = chamfer(torch.as_tensor(m, dtype=torch.float32, device=dev),
                        torch.as_tensor(ref, dtype=torch.float32, device=dev))  # fmt: skip
    return {"accuracy": acc, "completeness": comp, "chamfer": 0.5 * (acc + comp),
            "mesh_faces": int(len(f)), "surface_points": int(len(m))}  # fmt: skip


def _nearest(x: torch.Tensor, y: torch.Tensor, chunk: int = 4096) -> torch.Tensor:
    """[len(x)] distance from each point of x to the nearest of y."""
    return torch.cat([torch.cdist(x[s : s + chunk], y).min(1).values
                      for s in range(0, len(x), chunk)])  # fmt: skip


def _materials_breakdown(v, f, ref, points, cfg, train) -> dict:
    """For the materials reference: completeness and Chamfer over the reference points a training
    camera sees (:func:`materials_visible`; ``train``: the training split), and per shape
    (mesh points and reference points grouped by their nearest analytic shape): accuracy,
    completeness and the mesh's median signed distance (:func:`shape_signed_medians`)."""
    from ..mesh import sample_surface

    vis = materials_visible(ref, train.c2w.cpu(), train.intrinsics.cpu(), train.width,
                            train.height, device=cfg.device)  # fmt: skip
    m = sample_surface(v, f, points, seed=0)  # the points _surface_distances used
    m = m[m[:, 2] >= MATERIALS_BELOW]
    dev = torch.device(cfg.device)
    mt = torch.as_tensor(m, dtype=torch.float32, device=dev)
    rt = torch.as_tensor(ref, dtype=torch.float32, device=dev)
    acc = _nearest(mt, rt).cpu().numpy()
    comp = _nearest(rt, mt).cpu().numpy()
    ids_m, ids_r = materials_shape_ids(m), materials_shape_ids(ref)
    signed = shape_signed_medians(v, f, points)
    per = {}
    for i, name in enumerate(MATERIALS_NAMES):
        a, c = acc[ids_m == i], comp[(ids_r == i) & vis]
        per[name] = {"accuracy": float(a.mean()) if len(a) else None,
                     "completeness_visible": float(c.mean()) if len(c) else None,
                     "signed_median": signed[name]}  # fmt: skip
    comp_vis = float(comp[vis].mean())
    return {
        "visible_fraction": float(vis.mean()),
        "completeness_visible": comp_vis,
        "chamfer_visible": 0.5 * (float(acc.mean()) + comp_vis),
        "per_shape": per,
        "visible_note": "completeness over the reference points a training camera sees "
        "(analytic occlusion by the spheres and disk, as DTU's observation masks)",
        "signed_note": SIGNED_NOTE,
    }


SIGNED_NOTE = ("signed_median: of the mesh points nearest each shape, the median signed "
               "distance to it (a sphere: |p - c| - r, negative when the mesh is too small; the "
               "disk: z of the points on faces facing up within its rim, its top)")  # fmt: skip


def _mesh_sample(v, f, points: int):
    """``points`` points sampled on a mesh (by area, seed 0) [m, 3], whether each one's face
    faces up (marching cubes' winding) [m], and its nearest materials shape's index [m]."""
    import numpy as np

    from ..mesh import sample_surface

    m, face = sample_surface(v, f, points, seed=0, return_faces=True)
    t = v[f[face]]
    up = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])[:, 2] > 0
    return m, up, materials_shape_ids(m)


def shape_signed_medians(v, f, points: int, sample=None) -> dict:
    """{name: median signed distance or None} of a materials mesh (in the scene's frame) to each
    analytic shape (:data:`MATERIALS_NAMES`), over ``points`` points sampled on it (by area,
    seed 0; or ``sample``, :func:`_mesh_sample`'s) grouped by their nearest shape: a sphere's
    |p - c| - r; the disk's top, z of the points within its rim on faces whose outward normal
    (marching cubes' winding) points up."""
    import numpy as np

    from ..data.materials_truth import MATERIALS_DISK, materials_signed_distances

    m, up, ids = sample if sample is not None else _mesh_sample(v, f, points)
    sd = materials_signed_distances(m)
    disk = len(MATERIALS_NAMES) - 1
    top = up & (np.linalg.norm(m[:, :2], axis=1) <= MATERIALS_DISK)
    out = {}
    for i, name in enumerate(MATERIALS_NAMES):
        sel = (ids == i) & (m[:, 2] >= MATERIALS_BELOW) & (top if i == disk else True)
        out[name] = float(np.median(sd[sel, i])) if sel.any() else None
    return out


DISK_RINGS = (0.0, 0.4, 0.8, 1.2, 1.45, 1.6)


def disk_top_profile(v, f, points: int, rings=DISK_RINGS, sample=None) -> dict:
    """Where a materials mesh puts the ground disk's top, ring by ring: {"r0-r1": {"points",
    "median_z"}} over the points sampled on it (or ``sample``, :func:`_mesh_sample`'s) nearest
    the disk, within its rim and on faces facing up (as :func:`shape_signed_medians`' "disk"),
    grouped by their distance from the disk's centre in the rings ``rings`` (edges, world
    units). Tells a uniform offset of the floor from one at its rim or under the spheres."""
    import numpy as np

    from ..data.materials_truth import MATERIALS_DISK

    m, up, ids = sample if sample is not None else _mesh_sample(v, f, points)
    rho = np.linalg.norm(m[:, :2], axis=1)
    disk = (ids == len(MATERIALS_NAMES) - 1) & up & (rho <= MATERIALS_DISK)
    out = {}
    for a, b in zip(rings[:-1], rings[1:]):
        sel = disk & (rho >= a) & (rho < b)
        z = float(np.median(m[sel, 2])) if sel.any() else None
        out[f"{a:g}-{b:g}"] = {"points": int(sel.sum()), "median_z": z}
    return out


def evaluate_geometry(run, reference, resolution: int = 256, points: int = 50_000, device=None,
                      clean: float | None = None, views: int = 10,
                      snapshot: float | None = None, progress: bool = False,
                      level: float | str = 0.0):  # fmt: skip
    """Accuracy, completeness and Chamfer distance of an SDF run's surface against a reference,
    and the rendered depth's error where the reference is analytic.

    The run's level set f = ``level`` (default the zero level; "rendered": the level of
    :func:`~warpnerf.train.surface_level.rendered_level`, the median SDF at the rendered depths
    of opaque training rays, clamped to +-5 beta; given as "level_rule" and "level_rendered")
    is meshed by marching cubes at ``resolution`` inside its scene cube
    and ``points`` points are sampled on it (by area); ``reference`` is "materials" (the analytic
    spheres and disk, sampled the same way; mesh points under the disk, z < -0.1, are left out)
    or a point-cloud file (.npz with ``points`` or ``verts``, or .ply vertices; a mesh's vertices
    serve as its points). Accuracy: mean distance from the run's surface to the reference;
    completeness: mean distance from the reference to the run's surface; Chamfer: their mean.
    World units of the data (a COLMAP/LLFF run's mesh is mapped back to the capture's frame
    first). Also "delivered": the same figures, every face counted, of the mesh `warpnerf mesh`
    writes by default (culled by the training cameras, cleaned), and for "materials"
    "raw_every_face": of the raw level set with the points under the disk counted too
    (:func:`_delivered_figures`). ``clean`` (a fraction of the area,
    :func:`warpnerf.mesh.clean_mesh`) also reports the figures of the mesh without its floating
    pieces, under "cleaned". For "materials",
    "visible" adds the completeness and Chamfer over the reference surface the training cameras
    see and the errors per shape (:func:`_materials_breakdown`; of the cleaned mesh with
    ``clean``), and "delivered" the median signed distance per shape
    (:func:`shape_signed_medians`).

    Depth error (:func:`depth_error`, "materials" only: a point cloud has no ray hits, so the
    depth figures are None): on the first ``views`` val images (0: all), rendered by the run.
    ``snapshot``: the run's snapshot at that many training seconds instead of its last
    checkpoint. ``progress``: the marching-cubes grid's evaluation on stderr
    (:class:`~warpnerf.train.progress.Progress`).
    """
    from .surface_level import mesh_level

    if not 8 <= resolution <= 1024:
        raise UserError(f"--mesh-resolution must be in [8, 1024], got {resolution}")
    if not 100 <= points <= 10_000_000:
        raise UserError(f"--geometry-points must be in [100, 1e7], got {points}")
    if views < 0:
        raise UserError(f"--geometry-views must be >= 0, got {views}")
    if clean is not None and not 0.0 <= clean < 1.0:
        raise UserError(f"--clean MIN_FRACTION must be in [0, 1), got {clean}")
    check_level(level)
    cfg, model, _ = load_run(run, device, snapshot)
    if model.kind != "sdf":
        raise UserError(
            f"{run}: --geometry needs an SDF run ({sdf_field_names()}), not {cfg.field}"
        )
    analytic = reference == "materials"
    ref = materials_reference(points) if analytic else _load_reference(reference)
    cull = mesh_culling(model, cfg)
    level, rule = mesh_level(model, cfg, level, lambda: cull["refined"])
    res = {"run": str(run), "reference": str(reference),
           **surface_figures(model, cfg, reference, ref, level, resolution, points, clean, cull,
                             progress, what=str(run))}  # fmt: skip
    res.update(points=int(points), resolution=resolution, level=level)
    if rule is not None:
        res.update(level_rule=rule.pop("rule"), level_rendered=rule)
    res.update(_geometry_depth(model, cfg, views) if analytic else _NO_DEPTH)
    return res


def surface_figures(model, cfg, reference, ref, level: float = 0.0, resolution: int = 256,
                    points: int = 50_000, clean: float | None = None, cull: dict | None = None,
                    progress: bool = False, what: str = "the run") -> dict:  # fmt: skip
    """:func:`evaluate_geometry`'s figures of one level set, f = ``level``, of a loaded SDF run
    (``model``, ``cfg``): of the raw level set, "cleaned" (with ``clean``), "raw_every_face"
    and "delivered" (:func:`_delivered_figures`, culled by ``cull``, :func:`mesh_culling`,
    computed when None), and for ``reference`` "materials" "visible". ``ref``: the reference
    points [n, 3]; ``what`` names the run in errors."""
    from ..mesh import extract_mesh
    from .progress import Progress

    analytic = reference == "materials"
    a, field = cfg.aabb, model.field
    with Progress(resolution**3, "eval geometry: SDF grid", unit="pt", unit_scale=True,
                  enabled=progress) as bar:  # fmt: skip
        v, f = extract_mesh(bar.counting(lambda p: field.sdf(p.to(cfg.device))), [-a] * 3,
                            [a] * 3, resolution, level, device=cfg.device)  # fmt: skip
    if len(f) == 0:
        at = "zero level set" if level == 0 else f"level set at {level:g}"
        raise UserError(f"{what}: the SDF has no {at} inside its box; nothing to compare")
    cull = mesh_culling(model, cfg) if cull is None else cull
    below = MATERIALS_BELOW if analytic else None
    res = _surface_distances(v, f, ref, points, cfg, below)
    if clean is not None:
        from ..mesh import clean_mesh

        vc, fc, info = clean_mesh(v, f, clean)
        same = info["components_removed"] == 0
        dist = {k: res[k] for k in ("accuracy", "completeness", "chamfer")} if same else (
            _surface_distances(vc, fc, ref, points, cfg, below))  # fmt: skip
        res["cleaned"] = {"clean": clean, **dist, "mesh_faces": int(len(fc)),
                          **{k: info[k] for k in ("components", "components_removed",
                                                  "area_removed_fraction")}}  # fmt: skip
    res.update(_delivered_figures(v, f, ref, points, cfg, below, cull))
    if analytic:  # visible-surface figures and per-shape errors (of the cleaned mesh if any)
        vb, fb = (vc, fc) if clean is not None else (v, f)
        train = cull["train"] if cull["train"] is not None else load_data(cfg, "train")
        res["visible"] = _materials_breakdown(vb, fb, ref, points, cfg, train)
    return res


def mesh_culling(model, cfg) -> dict:
    """What the delivered mesh of an SDF run is culled by (:func:`_delivered_figures`), found
    once for any number of level sets: {"train": the training split (None when its data is not
    at hand), "refined": it with the run's refined poses, "weight_grid": the training rays'
    :class:`~warpnerf.train.visibility.WeightGrid` over the scene cube or None, "weights_note":
    why none}."""
    import contextlib

    from .visibility import training_weight_grid

    train, refined, wgrid, wnote = None, None, None, None
    with contextlib.suppress(UserError):  # the training data may be gone: no culling then
        train = load_data(cfg, "train")
    if train is None:
        wnote = "the run's training data is not at hand"
    else:  # (NDC too: the rays and the grid are in the field's frame)
        a = float(cfg.aabb)
        refined = with_refined_poses(model, train, "train")
        wgrid, wnote = training_weight_grid(model, cfg, refined, [-a] * 3, [a] * 3)
    return {"train": train, "refined": refined, "weight_grid": wgrid, "weights_note": wnote}


def _delivered_figures(v, f, ref, points, cfg, below, cull) -> dict:
    """The figures a user who opens the mesh meets, every vertex and face counted: "delivered"
    (the mesh `warpnerf mesh` writes by default: the faces where no training ray puts weight
    and those no training camera sees culled (``cull``, :func:`mesh_culling`), components
    under 1 % of the area dropped, :func:`warpnerf.mesh.surface_mesh`; the grid's figures under
    "weight_grid", or why there is none under "weights_note"; for materials, ``below`` given,
    "signed_median" per shape, :func:`shape_signed_medians`) and, where the main figures leave
    points out (materials: under the disk), "raw_every_face" (the raw level set). Bounds in the
    mesh's frame (the data's world frame for Blender scenes). ``v`` is the level set in the box
    [-cfg.aabb, cfg.aabb]^3, the field's frame."""
    from ..mesh import DEFAULT_CLEAN, surface_mesh

    out = {}
    if below is not None:
        out["raw_every_face"] = {
            **_surface_distances(v, f, ref, points, cfg),
            "bounds_min": v.min(0).tolist(),
            "bounds_max": v.max(0).tolist(),
        }
    wgrid = cull["weight_grid"]
    cams = cull["train"] if cfg.ndc_camera() is None else None
    vd, fd, info = surface_mesh(v, f, cams, DEFAULT_CLEAN, device=cfg.device, weight_grid=wgrid)
    if wgrid is not None:
        info["weight_grid"] = wgrid.info
    else:
        info["weights_note"] = cull["weights_note"]
    d = {"accuracy": None, "completeness": None, "chamfer": None, "mesh_faces": 0}
    if len(fd):
        d = {
            **_surface_distances(vd, fd, ref, points, cfg),
            "bounds_min": vd.min(0).tolist(),
            "bounds_max": vd.max(0).tolist(),
        }
        if below is not None:
            sample = _mesh_sample(vd, fd, points)  # (once for both)
            d["signed_median"] = shape_signed_medians(vd, fd, points, sample=sample)
            d["disk_top_by_radius"] = disk_top_profile(vd, fd, points, sample=sample)
    out["delivered"] = {**d, **info}
    return out


_NO_DEPTH = {"depth_error_mean": None, "depth_error_median": None, "depth_pixels": None,
             "depth_note": "a point-cloud reference has no ray hits: no depth error"}  # fmt: skip


def _load_reference(path):
    from .sdf import load_points

    return load_points(path)[0]


def _geometry_depth(model, cfg, views: int) -> dict:
    """:func:`depth_error` against the materials scene on the run's val images."""
    if cfg.ndc_camera() is not None or cfg.scene is not None:
        return {**_NO_DEPTH, "depth_note": "the run's rays are in a normalised capture frame, "
                "not the analytic scene's: no depth error"}  # fmt: skip
    res = depth_error(model, cfg, load_data(cfg, "val"), materials_depth, views,
                      shapes=(MATERIALS_NAMES, materials_shape_ids))  # fmt: skip
    res["depth_note"] = (
        "|expected depth / opacity - analytic first hit| on val pixels the reference hits with "
        "opacity > 0.5; depth_by_shape: by the shape hit, signed_median of rendered - true "
        "(> 0: behind the true surface)"
    )
    return res
