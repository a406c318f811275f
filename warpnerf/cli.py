"""The ``warpnerf`` command line: ``warpnerf --help`` lists the subcommands."""

from __future__ import annotations

import argparse
import json
import sys

from .errors import UserError


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
        if not v > 0:
            raise argparse.ArgumentTypeError(f"must be positive, got {text}")
        return v

    return parse


def cmd_demo(args) -> int:
    from .demo import run_demo

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

    cfg = BoxFitConfig(
        iters=args.iters,
        batch=args.batch,
        n_samples=args.samples,
        near=args.near,
        far=args.far,
        lr=args.lr,
        seed=args.seed,
    )
    if not cfg.far > cfg.near:
        raise UserError(f"--far ({cfg.far}) must be greater than --near ({cfg.near})")
    res = run_box_fit_on_folder(
        args.data,
        args.out,
        cfg,
        device=_device(args.device),
        frames=args.frames,
        progress=not args.quiet,
    )
    print(json.dumps(res))
    return 0


def cmd_bench(args) -> int:
    from .bench import run_bench

    run_bench(args.kernel, device=_device(args.device), json_path=args.json, quick=args.quick)
    return 0


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

    t = sub.add_parser("train", help="train a model on data (box: fit an SDF box to images)")
    tsub = t.add_subparsers(dest="model", metavar="MODEL", required=True)
    tb = tsub.add_parser("box", help="fit the rainbow SDF box to a Blender-format folder")
    tb.add_argument("--data", required=True, help="folder with transforms*.json and PNG images")
    tb.add_argument("--out", required=True, help="output folder")
    tb.add_argument("--device", default="cpu")
    tb.add_argument("--iters", type=_positive(int), default=400)
    tb.add_argument("--batch", type=_positive(int), default=4096)
    tb.add_argument("--samples", type=_positive(int), default=64)
    tb.add_argument("--near", type=float, default=0.0)
    tb.add_argument("--far", type=float, default=5.0)
    tb.add_argument("--lr", type=_positive(float), default=0.02)
    tb.add_argument("--seed", type=int, default=0)
    tb.add_argument("--frames", type=int, default=40, help="spiral video frames (0: none)")
    tb.add_argument("--quiet", action="store_true")
    tb.set_defaults(func=cmd_train_box)

    b = sub.add_parser("bench", help="benchmark kernels against their PyTorch twins")
    b.add_argument("kernel", nargs="?", default="composite", choices=["composite", "all"])
    b.add_argument("--device", default="cpu")
    b.add_argument("--json", default=None, help="write the results as JSON here")
    b.add_argument("--quick", action="store_true", help="smallest sizes only")
    b.set_defaults(func=cmd_bench)
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    try:
        return int(args.func(args) or 0)
    except UserError as e:
        print(f"warpnerf {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
