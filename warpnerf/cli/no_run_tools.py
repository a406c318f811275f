"""`warpnerf demo`, `bench` and `data`: the commands that take no run folder.

The rule between the CLI modules: a command whose input is a trained run folder goes in
run_tools.py (eval, render, mesh, export; view in view.py, beside the live viewer's flags), a
`train` command in train.py, any other command here."""

from __future__ import annotations

from ..errors import UserError
from ..outputs import json_dumps
from ._common import check_out, parse_device


def cmd_demo(args) -> int:
    from ..box_demo import run_demo

    check_out(args.out)
    m = run_demo(
        args.out,
        iters=args.iters,
        size=args.size,
        frames=args.frames,
        video_size=args.video_size,
        device=parse_device(args.device),
        progress=not args.quiet,
    )
    print(f"wrote {args.out}/metrics.json, videos and images")
    print(
        json_dumps(
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


def cmd_bench(args) -> int:
    from ..bench import run_bench

    if args.json:
        check_out(args.json, "--json", file=True)
    one_size = args.rays is not None or args.samples is not None
    if one_size and args.kernel not in ("composite", "all"):
        raise UserError("--rays and --samples size the composite benchmark only")
    run_bench(args.kernel, device=parse_device(args.device), json_path=args.json,
              quick=args.quick, rays=args.rays, samples=args.samples)  # fmt: skip
    return 0


def cmd_data(args) -> int:
    from ..data.loading import data_summary

    if args.holdout == 1:
        raise UserError("--holdout must be 0 (none) or >= 2")
    info = data_summary(args.dir, args.format, args.downscale, args.holdout,
                        allow_outside=args.allow_outside_paths)  # fmt: skip
    print(json_dumps(info))
    return 0
