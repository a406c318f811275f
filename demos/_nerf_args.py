"""Shared flags of the NeRF demos (03, 04, 05): data, sizes and the model, mapped to NeRFConfig."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch

from warpnerf.train import NeRFConfig


def positive(text):
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return v


def parser(description: str, out: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--data", default="builtin", help="dataset folder (default: built-in scene)")
    p.add_argument("--out", default=out)
    p.add_argument("--device", default="cpu")
    p.add_argument("--iters", type=positive, default=500)
    p.add_argument("--batch", type=positive, default=1024)
    p.add_argument("--samples", type=positive, default=32)
    p.add_argument("--layers", type=positive, default=4)
    p.add_argument("--width", type=positive, default=64)
    p.add_argument("--lr", type=float, default=5e-3)
    p.add_argument("--lr-final", type=float, default=5e-4)
    p.add_argument("--downscale", type=positive, default=1)
    p.add_argument("--near", type=float, default=None)
    p.add_argument("--far", type=float, default=None)
    p.add_argument("--builtin-size", type=positive, default=32)
    p.add_argument("--eval-images", type=int, default=8, help="val images scored (0 = all)")
    return p


def config(args, **overrides) -> NeRFConfig:
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("error: --device cuda: no CUDA device available")
    if args.data == "builtin" and args.downscale != 1:
        raise SystemExit("error: --downscale applies to --data folders, not the built-in scene")
    if args.eval_images < 0:
        raise SystemExit("error: --eval-images must be >= 0")
    if Path(args.out).exists() and not Path(args.out).is_dir():
        raise SystemExit(f"error: --out {args.out} is a file")
    if not all(math.isfinite(v) for v in (args.near, args.far, args.lr, args.lr_final) if v):
        raise SystemExit("error: --near, --far, --lr and --lr-final must be finite")
    kw = dict(
        data=args.data,
        iters=args.iters,
        batch=args.batch,
        n_coarse=args.samples,
        n_layers=args.layers,
        width=args.width,
        skip=max(1, args.layers // 2),
        lr=args.lr,
        lr_final=args.lr_final,
        downscale=args.downscale,
        near=args.near,
        far=args.far,
        builtin_size=args.builtin_size,
        device=args.device,
        val_every=max(args.iters, 1),
        val_images=0,
        ckpt_every=max(args.iters, 1),
    )
    kw.update(overrides)
    return NeRFConfig(**kw)
