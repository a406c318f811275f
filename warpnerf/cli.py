"""The ``warpnerf`` command line: ``warpnerf --help`` lists the subcommands."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import signal
import sys
import threading
from pathlib import Path

import numpy as np

from .errors import Interrupted, UserError


def _device(name: str) -> str:
    import torch

    if name not in ("cpu", "cuda") and not name.startswith("cuda:"):
        raise UserError(f"--device must be cpu or cuda, got {name!r}")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise UserError("--device cuda: no CUDA device is available to PyTorch here")
    return name


def _positive(kind):
    def parse(text):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a {kind.__name__}, got {text!r}") from None
        if not (v > 0 and math.isfinite(v)):
            raise argparse.ArgumentTypeError(f"must be positive and finite, got {text}")
        return v

    return parse


def _nonnegative(text):
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return v


def _finite(text):
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be finite, got {text}")
    return v


def _nonnegative_float(text):
    v = _finite(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return v


def _check_out(path, flag: str = "--out", file: bool = False) -> None:
    """UserError unless ``path`` can be written as a folder (or, with ``file``, as a file): it is
    not an existing file (folder) and its nearest existing parent is a folder."""
    p = Path(path)
    if file and p.is_dir():
        raise UserError(f"{flag} {path} is a folder, not a file")
    for q in p.parents if file else (p, *p.parents):
        if q.is_dir():
            return
        if q.exists():
            raise UserError(f"{flag} {path}: {q} is a file, not a folder")


def _saved_config(run) -> dict:
    """RUN/config.json as a dict; {} when absent or unreadable (the run loaders say why)."""
    try:
        saved = json.loads((Path(run) / "config.json").read_text())
    except (OSError, ValueError):
        return {}
    return saved if isinstance(saved, dict) else {}


def cmd_demo(args) -> int:
    from .demo import run_demo

    _check_out(args.out)
    m = run_demo(
        args.out,
        iters=args.iters,
        size=args.size,
        frames=args.frames,
        video_size=args.video_size,
        device=_device(args.device),
        progress=not args.quiet,
    )
    print(f"wrote {args.out}/metrics.json, videos and images")
    print(
        json.dumps(
            {
                k: m[k]
                for k in (
                    "center",
                    "side_lengths",
                    "center_max_abs_error",
                    "side_max_abs_error",
                    "val_psnr",
                    "total_seconds",
                )
            }
        )
    )
    return 0


def cmd_train_box(args) -> int:
    from .train.box_fit import BoxFitConfig, run_box_fit_on_folder

    _check_out(args.out)
    if args.resume:
        device = _resume_device(args)
        cfg = BoxFitConfig(iters=args.iters, max_seconds=args.max_seconds)
        res = run_box_fit_on_folder(
            None,
            args.out,
            cfg,
            device=device,
            frames=args.frames,
            progress=not args.quiet,
            resume=True,
        )
        print(json.dumps(res))
        return 0
    if args.data is None:
        raise UserError("--data DIR is required (a Blender-format folder)")
    cfg = BoxFitConfig(
        iters=args.iters or 400,
        batch=args.batch,
        n_samples=args.samples,
        near=args.near,
        far=args.far,
        lr=args.lr,
        seed=args.seed,
        ckpt_every=args.ckpt_every,
        max_seconds=args.max_seconds,
    )
    if not cfg.far > cfg.near >= 0:
        raise UserError(f"need 0 <= --near < --far, got --near {cfg.near} and --far {cfg.far}")
    res = run_box_fit_on_folder(
        args.data,
        args.out,
        cfg,
        device=_device(args.device or "cpu"),
        frames=args.frames,
        progress=not args.quiet,
    )
    print(json.dumps(res))
    return 0


# Flags a resume may carry; every other train-nerf flag is fixed by the run's config.json.
_RESUME_FLAGS = {
    "out",
    "resume",
    "iters",
    "device",
    "max_seconds",
    "quiet",
    "func",
    "command",
    "model",
    "frames",  # train box: the spiral video written at the end, not part of the fit
}


def _resume_device(args):
    """Checks a --resume command line; returns the --device override (None: the run's own).

    Only --iters, --device and --max-seconds may differ from the defaults of the subcommand that
    was used (the run's saved config holds everything else)."""
    if args.iters is None:
        raise UserError("--resume needs --iters (the total number of steps to reach)")
    defaults = build_parser().parse_args(["train", args.model, "--out", "x"])
    fixed = [
        k for k, v in vars(args).items() if k not in _RESUME_FLAGS and v != getattr(defaults, k, v)
    ]
    if fixed:
        names = ", ".join("--" + k.replace("_", "-") for k in sorted(fixed))
        raise UserError(
            f"with --resume the run's saved config is used; drop {names} "
            "(only --iters, --device and --max-seconds may change)"
        )
    return _device(args.device) if args.device else None


def cmd_train_nerf(args) -> int:
    from .train.nerf import NeRFConfig, train_nerf

    if args.model == "volsdf" and args.field != "volsdf":
        raise UserError("train volsdf trains the volsdf field; use train nerf for --field mlp|hash")
    _check_out(args.out)
    if args.resume:
        device = _resume_device(args)
        field = _saved_config(args.out).get("field", "volsdf")
        if args.model == "volsdf" and field != "volsdf":
            raise UserError(
                f"{args.out}: a NeRF run with --field {field}, not a VolSDF run; continue it with "
                f"`warpnerf train nerf --out {args.out} --resume --iters N`"
            )
        cfg = NeRFConfig(iters=args.iters, max_seconds=args.max_seconds)
        hist = train_nerf(cfg, args.out, resume=True, progress=not args.quiet, device=device)
    else:
        if args.data is None:
            raise UserError("--data DIR is required (or --data builtin for the built-in scene)")
        cfg = NeRFConfig(
            data=args.data,
            data_format=args.format,
            holdout=args.holdout,
            ndc=args.ndc,
            iters=args.iters or 20000,
            batch=args.batch,
            field=args.field,
            lr=args.lr,
            lr_final=args.lr_final,
            hash_levels=args.hash_levels,
            hash_log2_size=args.hash_log2_size,
            hash_max_res=args.hash_max_res,
            hidden=args.hidden,
            aabb=args.aabb or 0.0,
            beta=getattr(args, "beta", 0.1),
            beta_min=getattr(args, "beta_min", 1e-4),
            learn_beta=not getattr(args, "fixed_beta", False),
            eikonal_weight=getattr(args, "eikonal_weight", 0.1),
            n_coarse=args.samples,
            n_fine=args.fine_samples if args.coarse_fine else 0,
            view_dependence=args.view_dependence,
            n_layers=args.layers,
            width=args.width,
            pos_freqs=args.pos_freqs,
            dir_freqs=args.dir_freqs,
            near=args.near,
            far=args.far,
            downscale=args.downscale,
            max_images=args.max_images,
            val_every=args.val_every,
            val_images=args.val_images,
            ckpt_every=args.ckpt_every,
            seed=args.seed,
            device=_device(args.device or "cpu"),
            builtin_size=args.builtin_size,
            max_seconds=args.max_seconds,
            tf32=args.tf32,
            t_threshold=args.t_threshold,
            grid_res=getattr(args, "grid_res", 0),  # None: the field's default
            grid_every=getattr(args, "grid_every", 16),
            grid_warmup=getattr(args, "grid_warmup", 256),
            occ_threshold=getattr(args, "occ_threshold", 0.01),
            march_step=getattr(args, "march_step", None) or 0.0,
            max_samples=getattr(args, "max_samples", 1024),
            target_samples=getattr(args, "target_samples", 0),
            round_samples=getattr(args, "round_samples", 0),
        )
        hist = train_nerf(cfg, args.out, progress=not args.quiet)
    last = {
        "step": hist["step"][-1] if hist["step"] else 0,
        "train_psnr": hist["psnr"][-1] if hist["psnr"] else None,
        "val_psnr": hist["val_psnr"][-1] if hist["val_psnr"] else None,
        "seconds": hist["seconds"][-1] if hist["seconds"] else 0.0,
    }
    print(json.dumps(last))
    return 0


def cmd_train_sdf(args) -> int:
    from .train.sdf import SDFConfig, train_sdf

    _check_out(args.out)
    if args.resume:
        dev = _resume_device(args)
        cfg = SDFConfig(iters=args.iters, max_seconds=args.max_seconds)
        m = train_sdf(cfg, args.out, resume=True, progress=not args.quiet, device=dev)
    else:
        if args.points is None:
            raise UserError("--points FILE.npz|FILE.ply (or 'builtin') is required")
        cfg = SDFConfig(
            points=args.points,
            iters=args.iters or 2000,
            batch=args.batch,
            n_random=args.batch,
            lr=args.lr,
            eikonal_weight=args.eikonal_weight,
            normal_weight=args.normal_weight,
            n_layers=args.layers,
            width=args.width,
            skip=max(1, args.layers // 2),
            pos_freqs=args.pos_freqs,
            resolution=args.resolution,
            max_seconds=args.max_seconds,
            seed=args.seed,
            device=_device(args.device or "cpu"),
        )
        m = train_sdf(cfg, args.out, progress=not args.quiet)
    keys = ("step", "seconds", "chamfer", "vertices", "faces")
    out = {k: m[k] for k in keys}
    out["eikonal_residual_box_mean"] = m["eikonal_residual_box"]["mean"]
    print(json.dumps(out))
    return 0


def cmd_eval(args) -> int:
    from .train.nerf_eval import evaluate_run

    if args.out:
        _check_out(args.out)
    elif Path(args.run).is_dir():
        _check_out(Path(args.run) / f"eval_{args.split}", "eval output")
    m = evaluate_run(
        args.run,
        args.split,
        device=_device(args.device) if args.device else None,
        max_images=args.max_images,
        out_dir=args.out,
        chunk=args.chunk,
        march_step=args.march_step,
        round_samples=args.round_samples,
        render_half=True if args.half else None,
    )
    keys = ("split", "step", "n_images", "psnr", "ssim", "render_ms_median")
    print(json.dumps({k: m[k] for k in keys}))
    return 0


def _size(text):
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH such as 400x400, got {text!r}") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"width and height must be positive, got {text!r}")
    return w, h


def cmd_render(args) -> int:
    from .train.nerf_eval import render_run

    if Path(args.run).is_dir():
        _check_out(Path(args.run) / f"render_{args.path}", "render output")
    res = render_run(
        args.run,
        args.path,
        args.frames,
        args.size,
        device=_device(args.device) if args.device else None,
    )
    print(json.dumps(res))
    return 0


def _mesh_source(args):
    """(field_fn, lower, upper, marching-cubes level, user level, what, map of the vertices back to
    the data's units or None) for `warpnerf mesh`."""
    dev = _device(args.device or "cpu")
    if (args.run is None) == (args.sdf is None):
        raise UserError("give a run folder or --sdf SCENE (one of them)")
    if args.sdf is not None:
        from .fields.sdf_scene import SDFScene, many_primitives_scene, torus_scene

        builtin = {"torus": torus_scene, "scene": many_primitives_scene}
        scene = builtin[args.sdf]() if args.sdf in builtin else SDFScene.load(args.sdf)
        b = args.bounds or 2.0
        level = args.level or 0.0
        return (lambda p: scene.sdf(p)), [-b] * 3, [b] * 3, level, level, f"sdf {args.sdf}", None
    from .train.nerf import load_run
    from .train.sdf import MODEL, load_sdf_run

    run = Path(args.run)
    if _saved_config(run).get("model") == MODEL:
        cfg, model, ckpt = load_sdf_run(run, dev if args.device else None)
        c, s = ckpt["normalisation"]["center"], ckpt["normalisation"]["scale"]
        b = args.bounds or 1.0  # in the normalised frame; vertices are mapped back below
        fn = lambda p: model(p.to(cfg.device))  # noqa: E731
        back = lambda v: v / s + np.asarray(c)  # noqa: E731  (the point cloud's units)
        return fn, [-b] * 3, [b] * 3, args.level or 0.0, args.level or 0.0, f"sdf run {run}", back
    cfg, fields_, _ = load_run(run, dev if args.device else None)
    field = fields_["fine"] or fields_["coarse"]
    b = args.bounds or (cfg.aabb if cfg.aabb > 0 else 1.5)
    back = None
    if cfg.scene is not None:  # COLMAP/LLFF: vertices back to the capture's world units
        from .data.capture import normalised_to_world

        ndc = cfg.ndc_camera()
        back = lambda v: normalised_to_world(v, cfg.scene["transform"], ndc)  # noqa: E731
    lo, hi = [-b] * 3, [b] * 3
    if cfg.ndc_camera() is not None:  # NDC box; z = 1 is infinity
        lo[2], hi[2] = -1.0, 0.99
    if cfg.field == "volsdf":  # the SDF's zero level set
        level = args.level or 0.0
        return (lambda p: field.sdf(p.to(cfg.device))), lo, hi, level, level, \
            f"volsdf {run}", back  # fmt: skip
    level = 10.0 if args.level is None else args.level

    def density(p):
        return field.density(p)[0]

    # marching cubes of -density at -level: inside (dense) is negative like an SDF
    fn = lambda p: -density(p.to(cfg.device))  # noqa: E731
    return fn, lo, hi, -level, level, f"nerf {run}", back


def cmd_mesh(args) -> int:
    import time

    from .mesh import extract_mesh, screenshot, write_ply

    if args.resolution < 8 or args.resolution > 1024:
        raise UserError(f"--resolution must be in [8, 1024], got {args.resolution}")
    if not args.out.endswith(".ply"):
        raise UserError(f"--out must be a .ply file, got {args.out}")
    _check_out(args.out, file=True)
    fn, lo, hi, level, shown_level, what, back = _mesh_source(args)
    t0 = time.perf_counter()
    dev = _device(args.device or "cpu")
    try:
        v, f = extract_mesh(fn, lo, hi, args.resolution, level, device=dev)
    except ValueError as e:
        raise UserError(f"{what}: {e}") from None
    secs = time.perf_counter() - t0
    if len(f) == 0:
        raise UserError(f"{what}: no surface at level {shown_level} inside the box {lo} .. {hi}")
    if back is not None:  # normalised frame -> the data's own units
        v = back(v).astype(np.float32)
        keep = np.isfinite(v).all(1)  # NDC vertices at infinity
        if not keep.all():
            remap = np.cumsum(keep) - 1
            f = remap[f[keep[f].all(1)]]
            v = v[keep]
    write_ply(args.out, v, f)
    png = str(Path(args.out).with_suffix(".png"))
    if args.no_screenshot:
        Path(png).unlink(missing_ok=True)  # never leave a screenshot of an older mesh beside it
    else:
        try:
            screenshot(png, v, f)
        except ImportError as e:  # pyvista is a dependency; tolerate machines without it
            print(f"warning: no screenshot ({e})", file=sys.stderr)
            png = None
    res = {
        "source": what,
        "out": args.out,
        "screenshot": None if args.no_screenshot else png,  # None also when pyvista is missing
        "vertices": len(v),
        "faces": len(f),
        "bounds_min": v.min(0).tolist(),
        "bounds_max": v.max(0).tolist(),
        "resolution": args.resolution,
        "level": shown_level,
        "seconds": secs,
    }
    print(json.dumps(res))
    return 0


def cmd_bench(args) -> int:
    from .bench import run_bench

    if args.json:
        _check_out(args.json, "--json", file=True)
    run_bench(args.kernel, device=_device(args.device), json_path=args.json, quick=args.quick)
    return 0


def _data_format_flags(p) -> None:
    """--format and --holdout (`data`, `train nerf`, `train volsdf`)."""
    from .data.datasets import FORMATS

    p.add_argument("--format", default="auto", choices=FORMATS, help="data format (auto: detect)")
    p.add_argument(
        "--holdout",
        type=_nonnegative,
        default=8,
        help="COLMAP/LLFF: every Nth image (sorted names) is val/test; 0 = none (default 8)",
    )


def cmd_data(args) -> int:
    from .data.datasets import data_summary

    if args.holdout == 1:
        raise UserError("--holdout must be 0 (none) or >= 2")
    info = data_summary(args.dir, args.format, args.downscale, args.holdout)
    print(json.dumps(info))
    return 0


def _nerf_flags(tn) -> None:
    """The flags `train nerf` and `train volsdf` share."""
    tn.add_argument(
        "--data",
        help="Blender, nerfstudio, COLMAP or LLFF folder, or 'builtin' (the built-in scene)",
    )
    _data_format_flags(tn)
    tn.add_argument(
        "--ndc",
        default="auto",
        choices=["auto", "on", "off"],
        help="COLMAP/LLFF: NDC rays (auto: on for forward-facing captures)",
    )
    tn.add_argument("--out", required=True, help="run folder (config, checkpoint, history)")
    tn.add_argument("--resume", action="store_true", help="continue the run in --out exactly")
    tn.add_argument(
        "--device",
        default=None,
        help="cpu (default for a new run) or cuda; on --resume, default the run's own",
    )
    tn.add_argument("--iters", type=_positive(int), default=None, help="total steps (20000)")
    tn.add_argument("--batch", type=_positive(int), default=1024, help="rays per step")
    tn.add_argument(
        "--field",
        default="mlp",
        choices=["mlp", "hash", "volsdf"],
        help="mlp: NeRF's MLP (default); hash: hash-grid encoding + small MLPs (trains in "
        "minutes); volsdf: neural SDF with VolSDF's density (see `train volsdf`)",
    )
    tn.add_argument("--lr", type=_positive(float), default=None, help="5e-4 (mlp), 1e-2 (hash)")
    tn.add_argument("--lr-final", type=_positive(float), default=None, help="lr/10 (mlp), lr/20")
    tn.add_argument("--samples", type=_positive(int), default=64, help="coarse samples per ray")
    tn.add_argument("--coarse-fine", action="store_true", help="add the fine network")
    tn.add_argument("--fine-samples", type=_positive(int), default=64)
    tn.add_argument("--view-dependence", action=argparse.BooleanOptionalAction, default=True)
    tn.add_argument("--layers", type=_positive(int), default=8)
    tn.add_argument("--width", type=_positive(int), default=256)
    tn.add_argument("--pos-freqs", type=_nonnegative, default=10)
    tn.add_argument("--dir-freqs", type=_nonnegative, default=4)
    tn.add_argument("--hash-levels", type=_positive(int), default=16)
    tn.add_argument("--hash-log2-size", type=_positive(int), default=19, help="rows per level")
    tn.add_argument("--hash-max-res", type=_positive(int), default=2048)
    tn.add_argument("--hidden", type=_positive(int), default=64, help="hash field MLP width")
    tn.add_argument(
        "--aabb",
        type=_positive(float),
        default=None,
        help="hash field: half-size of the scene cube (default 1.5; the built-in scene's own)",
    )
    tn.add_argument("--near", type=_finite, default=None, help="default 2 (1 for builtin)")
    tn.add_argument("--far", type=_finite, default=None, help="default 6 (4 for builtin)")
    tn.add_argument("--downscale", type=_positive(int), default=1)
    tn.add_argument("--max-images", type=_nonnegative, default=0, help="0 = all training images")
    tn.add_argument("--builtin-size", type=_positive(int), default=48)
    tn.add_argument("--val-every", type=_positive(int), default=1000)
    tn.add_argument("--val-images", type=_nonnegative, default=2)
    tn.add_argument("--ckpt-every", type=_positive(int), default=1000)
    tn.add_argument("--seed", type=int, default=0)
    tn.add_argument(
        "--max-seconds",
        type=_nonnegative_float,
        default=0.0,
        help="stop after this much training time (0: run all --iters)",
    )
    tn.add_argument("--tf32", action="store_true", help="TF32 matrix products on CUDA")
    tn.add_argument(
        "--t-threshold",
        type=_finite,
        default=1e-4,
        help="early ray termination below this transmittance (0: off)",
    )
    tn.add_argument("--quiet", action="store_true")


def _grid_flags(tn) -> None:
    """Occupancy-grid flags (`train nerf` only: the grid needs the hash field)."""
    tn.add_argument(
        "--grid-res",
        type=_nonnegative,
        default=None,
        help="occupancy grid cells per axis, even (default 128 with --field hash; 0: no grid, "
        "stratified/hierarchical samples instead)",
    )
    tn.add_argument("--grid-every", type=_positive(int), default=16, help="steps between updates")
    tn.add_argument(
        "--grid-warmup", type=_nonnegative, default=256, help="steps of full-grid updates"
    )
    tn.add_argument(
        "--occ-threshold", type=_positive(float), default=0.01, help="step opacity of empty cells"
    )
    tn.add_argument(
        "--march-step", type=_positive(float), default=None, help="default: box diagonal / 1024"
    )
    tn.add_argument("--max-samples", type=_positive(int), default=1024, help="per ray, with a grid")
    tn.add_argument(
        "--round-samples",
        type=_nonnegative,
        default=0,
        help="with a grid, renders march in rounds of this many samples per ray (0: one round)",
    )
    tn.add_argument(
        "--target-samples",
        type=_nonnegative,
        default=0,
        help="with a grid: adapt rays per step to composite about this many samples (0: fixed "
        "--batch)",
    )


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="warpnerf",
        description="Differentiable volume rendering with NVIDIA Warp kernels and PyTorch.",
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    d = sub.add_parser(
        "demo",
        help="main job: fit an analytic box to rendered views, write a "
        "spiral video, images and metrics.json (built-in scene, no data needed)",
    )
    d.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    d.add_argument("--device", default="cpu", help="cpu or cuda")
    d.add_argument("--iters", type=_positive(int), default=300)
    d.add_argument("--size", type=_positive(int), default=64, help="training image size")
    d.add_argument("--frames", type=_positive(int), default=40, help="spiral video frames")
    d.add_argument("--video-size", type=_positive(int), default=128)
    d.add_argument("--quiet", action="store_true", help="no progress bar")
    d.set_defaults(func=cmd_demo)

    t = sub.add_parser("train", help="train a model: nerf, or box (fit an SDF box to images)")
    tsub = t.add_subparsers(dest="model", metavar="MODEL", required=True)
    tb = tsub.add_parser("box", help="fit the rainbow SDF box to a Blender-format folder")
    tb.add_argument("--data", help="folder with transforms*.json and PNG images")
    tb.add_argument("--out", required=True, help="run folder (config, checkpoint, result)")
    tb.add_argument("--resume", action="store_true", help="continue the fit in --out exactly")
    tb.add_argument(
        "--device",
        default=None,
        help="cpu (default for a new fit) or cuda; on --resume, default the run's own",
    )
    tb.add_argument("--iters", type=_positive(int), default=None, help="total steps (400)")
    tb.add_argument("--batch", type=_positive(int), default=4096)
    tb.add_argument("--samples", type=_positive(int), default=64)
    tb.add_argument("--near", type=_finite, default=0.0)
    tb.add_argument("--far", type=_finite, default=5.0)
    tb.add_argument("--lr", type=_positive(float), default=0.02)
    tb.add_argument("--ckpt-every", type=_positive(int), default=100)
    tb.add_argument("--seed", type=int, default=0)
    tb.add_argument(
        "--max-seconds",
        type=float,
        default=0.0,
        help="stop after this much fitting time (0: run all --iters)",
    )
    tb.add_argument("--frames", type=_nonnegative, default=40, help="spiral video frames (0: none)")
    tb.add_argument("--quiet", action="store_true")
    tb.set_defaults(func=cmd_train_box)

    tn = tsub.add_parser("nerf", help="train a NeRF (coarse, or coarse/fine) on a dataset")
    _nerf_flags(tn)
    _grid_flags(tn)
    tn.set_defaults(func=cmd_train_nerf)

    tv = tsub.add_parser(
        "volsdf", help="train VolSDF (neural SDF + Laplace density) on a dataset; = train nerf "
        "--field volsdf with VolSDF's defaults"
    )  # fmt: skip
    _nerf_flags(tv)
    tv.add_argument("--beta", type=_positive(float), default=0.1, help="initial Laplace scale")
    tv.add_argument("--beta-min", type=_positive(float), default=1e-4)
    tv.add_argument("--fixed-beta", action="store_true", help="keep beta at --beta")
    tv.add_argument("--eikonal-weight", type=_finite, default=0.1)
    tv.set_defaults(func=cmd_train_nerf, field="volsdf", pos_freqs=6, coarse_fine=True)

    ts = tsub.add_parser("sdf", help="fit a neural SDF to a point cloud (eikonal loss) + mesh")
    ts.add_argument("--points", help="FILE.npz (verts|points [, normals]) or FILE.ply, or builtin")
    ts.add_argument("--out", required=True, help="run folder")
    ts.add_argument("--resume", action="store_true")
    ts.add_argument("--device", default=None)
    ts.add_argument("--iters", type=_positive(int), default=None, help="total steps (2000)")
    ts.add_argument("--batch", type=_positive(int), default=4096, help="points per step")
    ts.add_argument("--lr", type=_positive(float), default=1e-3)
    ts.add_argument("--eikonal-weight", type=_finite, default=0.1)
    ts.add_argument("--normal-weight", type=_finite, default=1.0, help="when normals are given")
    ts.add_argument("--layers", type=_positive(int), default=6)
    ts.add_argument("--width", type=_positive(int), default=128)
    ts.add_argument("--pos-freqs", type=_nonnegative, default=6)
    ts.add_argument("--resolution", type=int, default=128, help="marching-cubes grid")
    ts.add_argument("--max-seconds", type=_nonnegative_float, default=0.0)
    ts.add_argument("--seed", type=int, default=0)
    ts.add_argument("--quiet", action="store_true")
    ts.set_defaults(func=cmd_train_sdf)

    e = sub.add_parser("eval", help="PSNR/SSIM of a trained run on a split, side-by-side PNGs")
    e.add_argument("run", help="run folder written by 'warpnerf train nerf'")
    e.add_argument("--split", default="val", choices=["train", "val", "test"])
    e.add_argument("--device", default=None, help="default: the run's device")
    e.add_argument("--max-images", type=_nonnegative, default=0, help="0 = all images of the split")
    e.add_argument(
        "--chunk", type=_positive(int), default=None, help="rays rendered at once (run's own)"
    )
    e.add_argument(
        "--march-step", type=_positive(float), default=None, help="grid runs: another step"
    )
    e.add_argument("--round-samples", type=_nonnegative, default=None, help="grid runs: another")
    e.add_argument("--half", action="store_true", help="grid runs on CUDA: float16 MLPs")
    e.add_argument("--out", default=None, help="output folder (default RUN/eval_SPLIT)")
    e.set_defaults(func=cmd_eval)

    r = sub.add_parser("render", help="colour and depth videos of a trained run along a path")
    r.add_argument("run")
    r.add_argument("--path", default="spiral", choices=["spiral", "orbit"])
    r.add_argument("--frames", type=_positive(int), default=40)
    r.add_argument("--size", type=_size, default=None, help="WxH (default: training size)")
    r.add_argument("--device", default=None)
    r.set_defaults(func=cmd_render)

    m = sub.add_parser("mesh", help="marching cubes of an SDF scene or a trained run -> PLY + PNG")
    m.add_argument("run", nargs="?", help="a NeRF run folder (density level set)")
    m.add_argument("--sdf", help="SDF scene: a JSON file, or 'torus' / 'scene' (built-in)")
    m.add_argument("--resolution", type=int, default=256, help="grid nodes per axis")
    m.add_argument("--level", type=_finite, default=None, help="0 for SDFs; density for runs (10)")
    m.add_argument("--bounds", type=_positive(float), default=None, help="half-size of the cube")
    m.add_argument("--out", required=True, help="mesh.ply (a PNG screenshot goes beside it)")
    m.add_argument("--device", default=None)
    m.add_argument("--no-screenshot", action="store_true")
    m.set_defaults(func=cmd_mesh)

    dp = sub.add_parser(
        "data", help="check a dataset folder and print a JSON summary (format, splits, cameras)"
    )
    dp.add_argument("dir", help="Blender, nerfstudio, COLMAP or LLFF folder")
    _data_format_flags(dp)
    dp.add_argument("--downscale", type=_positive(int), default=1)
    dp.set_defaults(func=cmd_data)

    b = sub.add_parser("bench", help="benchmark kernels against their PyTorch twins")
    b.add_argument(
        "kernel",
        nargs="?",
        default="composite",
        choices=["composite", "march", "encoding", "sphere-trace", "all"],
    )
    b.add_argument("--device", default="cpu")
    b.add_argument("--json", default=None, help="write the results as JSON here")
    b.add_argument("--quick", action="store_true", help="smallest sizes only")
    b.set_defaults(func=cmd_bench)
    return p


@contextlib.contextmanager
def _sigterm_exits():
    """SIGTERM outside a training loop (loading, meshing, rendering, writing) raises SystemExit(143)
    instead of killing the process outright, so atomic writers remove their temporary files. The
    training loops install their own handler while they run (finish the step, checkpoint)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise SystemExit(128 + signum)

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    try:
        with _sigterm_exits():
            return int(args.func(args) or 0)
    except UserError as e:
        print(f"warpnerf {args.command}: error: {e}", file=sys.stderr)
        return 2
    except Interrupted as e:  # training checkpointed its last step before stopping
        print(f"warpnerf {args.command}: interrupted by {e}", file=sys.stderr)
        return 128 + e.signum
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
