"""Shared flags of the NeRF demos (03, 04, 05): data, sizes and the model, mapped to NeRFConfig."""

from __future__ import annotations

import argparse

import torch

from warpnerf.train import NeRFConfig


def parser(description: str, out: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--data", default="builtin", help="dataset folder (default: built-in scene)")
    p.add_argument("--out", default=out)
    p.add_argument("--device", default="cpu")
    p.add_argument("--iters", type=int, default=500)
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--samples", type=int, default=32)
    p.add_argument("--layers", type=int, default=4)
    p.add_argument("--width", type=int, default=64)
    p.add_argument("--lr", type=float, default=5e-3)
    p.add_argument("--lr-final", type=float, default=5e-4)
    p.add_argument("--downscale", type=int, default=1)
    p.add_argument("--near", type=float, default=None)
    p.add_argument("--far", type=float, default=None)
    p.add_argument("--builtin-size", type=int, default=32)
    p.add_argument("--eval-images", type=int, default=8, help="val images scored (0 = all)")
    return p


def config(args, **overrides) -> NeRFConfig:
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("error: --device cuda: no CUDA device available")
    builtin = args.data == "builtin"
    near = args.near if args.near is not None else (1.0 if builtin else 2.0)
    far = args.far if args.far is not None else (4.0 if builtin else 6.0)
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
        near=near,
        far=far,
        builtin_size=args.builtin_size,
        device=args.device,
        val_every=max(args.iters, 1),
        val_images=0,
        ckpt_every=max(args.iters, 1),
    )
    kw.update(overrides)
    return NeRFConfig(**kw)
