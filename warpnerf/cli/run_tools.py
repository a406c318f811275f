"""`warpnerf eval`, `render`, `mesh` and `export`: the commands whose input is a trained run
folder (mesh also takes an analytic SDF scene instead). Commands that take no run folder go in
no_run_tools.py, `train` commands in train.py, `view` in view.py."""

from __future__ import annotations

import contextlib
import functools
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..errors import UserError
from ..outputs import check_foreign, json_dumps, remove_own
from ._common import check_existing, check_out, parse_device


def _renders(run, command: str) -> None:
    """UserError unless ``run``'s method renders through the NeRF pipeline (eval, render,
    export); a path that is no run folder is left to the loader's own message."""
    from ..train.methods import METHODS, method_of_run

    if not Path(run).is_dir():
        return
    method = method_of_run(run)
    if not method.renders:
        takes = ", ".join(m.what for m in METHODS.values() if m.renders)
        tools = [f"`warpnerf train {method.commands[0]} --resume`", "`warpnerf view`"]
        tools += ["`warpnerf mesh`"] if method.mesh is not None else []
        raise UserError(f"{run}: a {method.what} run; `warpnerf {command}` takes {takes} runs "
                        f"(use {', '.join(tools)})")  # fmt: skip


@contextlib.contextmanager
def _training_note(run, command: str):
    """While another process (a training) holds ``run``'s lock, one note on stderr when the
    command reads the run's checkpoint: the run is still training, by whom, and the step read.
    The lock stops a second writer only; reading a run that trains is allowed (its checkpoints
    are replaced whole), but what is read is the step saved last, not the end of the run."""
    from ..outputs import lock_holder, watch_checkpoint_reads

    pid = lock_holder(run) if run is not None and Path(run).is_dir() else None
    if pid is None:
        yield
        return
    top, said = Path(run).resolve(), []

    def note(path, ckpt) -> None:
        where = Path(path).resolve()
        if said or (top != where and top not in where.parents):
            return
        said.append(True)
        print(f"warpnerf {command}: note: {run} is still training (lock held by pid {pid}); "
              f"reading its checkpoint at step {ckpt.get('step')}", file=sys.stderr)  # fmt: skip

    with watch_checkpoint_reads(note):
        yield


def _same_path(a, b) -> bool:
    try:
        return Path(a).resolve() == Path(b).resolve()
    except (OSError, RuntimeError):
        return False


def _reads_run(cmd):
    """A tool on ``args.run`` (eval, render, mesh, export): says when that run is still
    training (:func:`_training_note`)."""

    @functools.wraps(cmd)
    def tool(args) -> int:
        run, out = getattr(args, "run", None), getattr(args, "out", None)
        if run is not None and out and _same_path(run, out):  # (eval --out RUN: its own lock
            run = None  # refuses it, in one line)
        with _training_note(run, cmd.__name__.removeprefix("cmd_")):
            return cmd(args)

    return tool


@_reads_run
def cmd_eval(args) -> int:
    from ..train.geometry_eval import evaluate_geometry
    from ..train.nerf_eval import evaluate_run

    check_existing(args.run)
    _renders(args.run, "eval")
    if args.geometry is not None:  # reads the run, writes nothing: prints the figures
        device = parse_device(args.device) if args.device else None
        _check_clean(args.clean)
        print(json_dumps(evaluate_geometry(args.run, args.geometry, args.mesh_resolution,
                                           args.geometry_points, device, clean=args.clean,
                                           views=args.geometry_views, progress=not args.quiet,
                                           level=args.level)))  # fmt: skip
        return 0
    if args.clean is not None:
        raise UserError("--clean needs --geometry (eval) or the mesh command")
    if args.level != 0.0:
        raise UserError("--level needs --geometry (eval) or the mesh command")
    if args.out:
        check_out(args.out)
    elif Path(args.run).is_dir():
        sub = f"eval_{args.split}" + ("_sphere" if args.renderer == "sphere" else "")
        check_out(Path(args.run) / sub, "eval output")
    m = evaluate_run(
        args.run,
        args.split,
        device=parse_device(args.device) if args.device else None,
        max_images=args.max_images,
        out_dir=args.out,
        chunk=args.chunk,
        march_step=args.march_step,
        round_samples=args.round_samples,
        render_half=True if args.half else None,
        render_tracer=args.tracer,
        renderer=args.renderer,
        progress=not args.quiet,
        spp=args.spp,
    )
    keys = ("split", "step", "n_images", "renderer", "spp", "psnr", "ssim", "render_ms_median")
    sub = f"eval_{args.split}" + ("_sphere" if args.renderer == "sphere" else "")
    folder = Path(args.out) if args.out else Path(args.run) / sub  # (evaluate_run's)
    print(json_dumps({**{k: m[k] for k in keys}, "out": str(folder),
                      "metrics_json": str(folder / "metrics.json")}))  # fmt: skip
    return 0


@_reads_run
def cmd_render(args) -> int:
    from ..train.nerf_eval import render_run

    check_existing(args.run)
    _renders(args.run, "render")
    if Path(args.run).is_dir():
        name = args.path if args.path in ("spiral", "orbit") else Path(args.path).stem
        sub = f"render_{name}" + ("_sphere" if args.renderer == "sphere" else "")
        check_out(Path(args.run) / sub, "render output")
    res = render_run(
        args.run,
        args.path,
        args.frames,
        args.size,
        device=parse_device(args.device) if args.device else None,
        renderer=args.renderer,
        progress=not args.quiet,
        spp=args.spp,
    )
    print(json_dumps(res))
    return 0


class _MeshSource(NamedTuple):
    fn: Callable  # points [n, 3] on ``device`` -> field values [n]
    lower: list
    upper: list
    level: float | None  # marching cubes' level of ``fn`` (None: a density chosen from the grid)
    shown_level: float | None  # the level the user asked for (NeRF: a density)
    what: str
    back: Callable | None  # vertices -> the data's own units
    device: str  # where the grid is evaluated and marched: --device, else the run's device
    field: object = None  # a radiance field (forward(x, d) -> (sigma, rgb)) for --colors
    density: bool = False  # fn is minus a density (a NeRF): its values are -sigma
    cameras: object = None  # () -> training cameras (c2w, intrinsics, width, height) to cull by
    weights: object = None  # (lower, upper, progress) -> (weight grid to cull by or None, why)
    level_rule: dict | None = None  # --level rendered: the figures of the level chosen


def _mesh_source(args) -> _MeshSource:
    """What `warpnerf mesh` extracts: an SDF scene (on --device, default cpu) or a run (on its
    own device unless --device moves it)."""
    dev = parse_device(args.device or "cpu")
    if (args.run is None) == (args.sdf is None):
        raise UserError("give a run folder or --sdf SCENE (one of them)")
    if args.sdf is not None:
        from ..fields.sdf_scene import SDFScene, many_primitives_scene, torus_scene

        builtin = {"torus": torus_scene, "scene": many_primitives_scene}
        from ..train.surface_level import plain_level

        scene = builtin[args.sdf]() if args.sdf in builtin else SDFScene.load(args.sdf)
        b = args.bounds or 2.0
        level = plain_level(args.level, f"the SDF scene {args.sdf}") or 0.0
        return _MeshSource(lambda p: scene.sdf(p), [-b] * 3, [b] * 3, level, level,
                           f"sdf {args.sdf}", None, dev)  # fmt: skip
    from ..train.methods import method_of_run

    check_existing(args.run)
    method = method_of_run(args.run)
    if method.mesh is None:
        raise UserError(f"{args.run}: a {method.what} run has no surface for `warpnerf mesh` "
                        f"(it is {method.what}'s own analytic shape)")  # fmt: skip
    opened = method.open_run(args.run, dev if args.device else None)
    m = method.mesh(opened, args.bounds, args.level)
    return _MeshSource(m["fn"], m["lower"], m["upper"], m["level"], m["shown_level"],
                       f"{m['what']} {args.run}", m["back"], m["device"], m["field"],
                       m["density"], m["cameras"], m.get("weights"),
                       m.get("level_rule"))  # fmt: skip


def _check_clean(clean) -> None:
    if clean is not None and not 0.0 <= clean < 1.0:
        raise UserError(f"--clean MIN_FRACTION must be in [0, 1), got {clean}")


def _clean_and_decimate(v, f, clean, decimate):
    """--clean then --decimate of a marching-cubes mesh: (v, f, report dict)."""
    from ..mesh import clean_mesh, decimate_mesh

    rep = {"faces_extracted": int(len(f))}
    try:
        if clean is not None:
            v, f, info = clean_mesh(v, f, clean)
            rep.update(clean=clean, components=info["components"],
                       components_removed=info["components_removed"],
                       area_removed_fraction=info["area_removed_fraction"])  # fmt: skip
        if decimate is not None:
            n = len(f)
            v, f = decimate_mesh(v, f, decimate)
            rep.update(decimate=decimate, faces_decimated=int(n - len(f)))
    except ImportError as e:  # pyvista is a dependency; say so on machines without it
        raise UserError(f"--decimate needs pyvista ({e})") from None
    return v, f, rep


@_reads_run
def cmd_mesh(args) -> int:
    import time

    from ..mesh import density_level, extract_mesh, level_hint, screenshot, vertex_colors, write_ply

    if args.resolution < 8 or args.resolution > 1024:
        raise UserError(f"--resolution must be in [8, 1024], got {args.resolution}")
    _check_clean(args.clean)
    if args.decimate is not None and not 0.0 < args.decimate < 1.0:
        raise UserError(f"--decimate R must be in (0, 1) (the fraction of faces removed), "
                        f"got {args.decimate}")  # fmt: skip
    if not args.out.endswith(".ply"):
        raise UserError(f"--out must be a .ply file, got {args.out}")
    check_out(args.out, file=True)
    png = str(Path(args.out).with_suffix(".png"))
    if not args.no_screenshot:  # the named .ply is the user's to replace; a PNG beside it is not
        check_foreign([png])
    src = _mesh_source(args)
    fn, lo, hi, level, shown_level, what, back, dev, field, density, cams = src[:11]
    if args.colors and field is None:
        raise UserError(f"--colors needs a NeRF or VolSDF run (a radiance field); {what} has none")
    chosen = {}
    if level is None:  # a NeRF run without --level: the density where its rays stop, from the grid

        def level(vals):
            chosen["level"], chosen["why"] = density_level(-vals, args.resolution, lo, hi)
            return -chosen["level"]

    from ..train.progress import Progress

    t0 = time.perf_counter()
    try:
        with Progress(args.resolution**3, "mesh: field on the grid", unit="pt", unit_scale=True,
                      enabled=not args.quiet) as bar:  # fmt: skip
            v, f, vals = extract_mesh(bar.counting(fn), lo, hi, args.resolution, level,
                                      device=dev, return_values=True)  # fmt: skip
    except ValueError as e:
        raise UserError(f"{what}: {e}") from None
    secs = time.perf_counter() - t0
    if chosen:  # (said in the result's JSON: "level" and "level_rule")
        shown_level = chosen["level"]
    if len(f) == 0:
        hint = level_hint(-vals if density else vals, density)  # range seen, a level to try
        raise UserError(f"{what}: no surface at level {shown_level} inside the box {lo} .. {hi}: "
                        f"{hint}")  # fmt: skip
    del vals
    t1 = time.perf_counter()
    # a run's surface as the training saw it (unless --keep-all): faces where no training ray
    # puts weight (unless --no-weight-cull) and faces no training camera sees culled, then
    # floating pieces dropped; an SDF scene's only with --clean
    clean, n_faces, cull = args.clean, int(len(f)), {}
    if args.run is not None and not args.keep_all:
        from ..mesh import DEFAULT_CLEAN, surface_mesh

        clean = DEFAULT_CLEAN if clean is None else clean
        wgrid, wnote = None, "off: --no-weight-cull"
        if src.weights is not None and not args.no_weight_cull:
            wgrid, wnote = src.weights(lo, hi, progress=not args.quiet)  # (renders the rays)
            if wgrid is None:
                print(f"warpnerf mesh: note: no culling by the training rays' weights ({wnote})",
                      file=sys.stderr)  # fmt: skip
        cams = cams() if callable(cams) else cams  # (reads the training data)
        if cams is None and field is not None:  # a NeRF/VolSDF run whose cameras are not at hand
            print("warpnerf mesh: note: no culling by the training cameras (the run's data is "
                  "not at hand, or its rays are NDC); floating pieces are still dropped",
                  file=sys.stderr)  # fmt: skip
        v, f, cull = surface_mesh(v, f, cams, clean, device=dev, weight_grid=wgrid)
        if wgrid is not None:
            cull["weight_grid"] = wgrid.info
        elif src.weights is not None:
            cull["weights_note"] = wnote
        if len(f) == 0:
            raise UserError(f"{what}: no face of the level set is seen by a training camera "
                            "where its rays put weight (--keep-all keeps them all)")  # fmt: skip
        clean = None  # (done)
    v, f, post = _clean_and_decimate(v, f, clean, args.decimate)  # (the field's own frame)
    post = {**cull, **post, "faces_extracted": n_faces}
    post_secs = time.perf_counter() - t1
    rgb = None
    if args.colors:  # of the final vertices (fn: 6 points a vertex, its normal)
        with Progress(6 * len(v), "mesh: vertex colours", unit="pt", unit_scale=True,
                      enabled=not args.quiet) as bar:  # fmt: skip
            rgb = vertex_colors(field, bar.counting(fn), v, dev)
    if back is not None:  # normalised frame -> the data's own units
        v = back(v).astype(np.float32)
        keep = np.isfinite(v).all(1)  # NDC vertices at infinity
        if not keep.all():
            remap = np.cumsum(keep) - 1
            f = remap[f[keep[f].all(1)]]
            v = v[keep]
            rgb = None if rgb is None else rgb[keep]
    write_ply(args.out, v, f, replace_foreign=True, colors=rgb)  # the file the user named
    if args.no_screenshot:  # never leave a screenshot of an older mesh (one warpnerf wrote)
        remove_own(Path(png).parent, [Path(png).name])
    else:
        try:
            screenshot(png, v, f, colors=rgb)
        except ImportError as e:  # pyvista is a dependency; tolerate machines without it
            print(f"warning: no screenshot ({e})", file=sys.stderr)
            png = None
    res = {
        "source": what,
        "out": args.out,
        "screenshot": None if args.no_screenshot else png,  # None also when pyvista is missing
        "vertices": len(v),
        "colors": rgb is not None,
        "faces": len(f),
        **post,
        "bounds_min": v.min(0).tolist(),
        "bounds_max": v.max(0).tolist(),
        "resolution": args.resolution,
        "level": shown_level,
        "seconds": secs,
    }
    if chosen:  # the level the run's densities chose, and why (--level sets it)
        res["level_rule"] = f"{chosen['why']}; --level sets it"
    if src.level_rule is not None:  # --level rendered: the level its renders chose, and why
        rule = dict(src.level_rule)
        res.update(level_rule=rule.pop("rule"), level_rendered=rule)
    if "clean" in post or args.decimate is not None:
        res["clean_decimate_seconds"] = post_secs
    print(json_dumps(res))
    return 0


@_reads_run
def cmd_export(args) -> int:
    from ..export import export_cameras, export_pointcloud

    check_existing(args.run)
    _renders(args.run, "export")
    check_out(args.out, file=True)
    if args.what == "pointcloud":
        if not args.out.endswith(".ply"):
            raise UserError(f"--out must be a .ply file, got {args.out}")
        res = export_pointcloud(args.run, args.out, args.views, args.stride, args.min_opacity,
                                parse_device(args.device) if args.device else None,
                                progress=not args.quiet)  # fmt: skip
    else:
        res = export_cameras(args.run, args.out)
    print(json_dumps(res))
    return 0
