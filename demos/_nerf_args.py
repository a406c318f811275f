"""Shared flags of the NeRF demos (03, 04, 05, 10): data, sizes and the model, built from
NeRFConfig's fields (warpnerf.options) with the demos' smaller defaults."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import torch

from warpnerf.options import CHECKS, add_flags, from_flags
from warpnerf.train import NeRFConfig

positive = CHECKS[("int", "positive")]

# the NeRFConfig fields the demos show, and the demos' own (smaller, faster) defaults
FLAGS = ("data", "iters", "batch", "n_coarse", "n_layers", "width", "lr", "lr_final", "downscale",
         "near", "far", "builtin_size", "device")  # fmt: skip
DEFAULTS = dict(iters=500, n_coarse=32, n_layers=4, width=64, lr=5e-3, lr_final=5e-4,
                builtin_size=32)  # fmt: skip


def parser(description: str, out: str, flags=FLAGS, **defaults) -> argparse.ArgumentParser:
    """The demo's flags, built from NeRFConfig (warpnerf.options): ``flags`` (field names) with
    the demos' defaults, updated by ``defaults``."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--out", default=out)
    p.add_argument("--eval-images", type=int, default=8, help="val images scored (0 = all)")
    add_flags(p, NeRFConfig, include=flags, defaults={**DEFAULTS, **defaults})
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
    kw = from_flags(NeRFConfig, args, include=[f.name for f in dataclasses.fields(NeRFConfig)])
    kw.update(
        skip=max(1, args.n_layers // 2),
        val_every=max(args.iters, 1),
        val_images=0,
        ckpt_every=max(args.iters, 1),
    )
    kw.update(overrides)
    return NeRFConfig(**kw)
