"""`warpnerf train box|nerf|volsdf|sdf`: the commands and their flags."""

from __future__ import annotations

import argparse

from ..errors import UserError
from ..io import json_dumps
from ..train.box_fit import BoxFitConfig
from ..train.nerf_config import NeRFConfig
from ..train.sdf import SDFConfig
from ._common import (
    _check_out,
    _data_format_flags,
    _device,
    _finite,
    _nonnegative,
    _nonnegative_float,
    _positive,
    _saved_config,
    _seed,
)


def cmd_train_box(args) -> int:
    from ..train.box_fit import run_box_fit_on_folder

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
        print(json_dumps(res))
        return 0
    if args.data is None:
        raise UserError("--data DIR is required (a Blender-format folder)")
    cfg = BoxFitConfig(
        iters=args.iters or BoxFitConfig.iters,
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
    print(json_dumps(res))
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
    # the subcommand's own parser (set as a default by cli.parser): its defaults, unparsed
    defaults = args.subparser.parse_args(["--out", "x"])
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
    from ..train.nerf import train_nerf

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
            iters=args.iters or NeRFConfig.iters,
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
    print(json_dumps(last))
    return 0


def cmd_train_sdf(args) -> int:
    from ..train.sdf import train_sdf

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
            iters=args.iters or SDFConfig.iters,
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
    print(json_dumps(out))
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
    tn.add_argument(
        "--iters", type=_positive(int), default=None, help=f"total steps ({NeRFConfig.iters})"
    )
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
    tn.add_argument("--val-every", type=_positive(int), default=NeRFConfig.val_every)
    tn.add_argument("--val-images", type=_nonnegative, default=2)
    tn.add_argument("--ckpt-every", type=_positive(int), default=NeRFConfig.ckpt_every)
    tn.add_argument("--seed", type=_seed, default=0)
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
