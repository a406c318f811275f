"""What every demo checks before it starts (its flags' minimums, the device, --out) and how a
demo that trains starts its run afresh without deleting anything warpnerf did not write."""

from __future__ import annotations

from pathlib import Path

import torch

from warpnerf.outputs import owned_files, remove_own


def check_args(p, args, **minimum) -> Path:
    """argparse errors (exit status 2) for a flag below its minimum (``name=value``), --device
    cuda without CUDA, and an --out that is a file; returns --out as a Path."""
    low = [f"--{k.replace('_', '-')} >= {v}" for k, v in minimum.items() if getattr(args, k) < v]
    if low:
        p.error(f"{', '.join(low)} required")
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        p.error("--device cuda: no CUDA device available")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        p.error(f"--out {out} is a file")
    return out


def fresh_run(run: Path) -> Path:
    """Empties ``run`` (and its subfolders) of the files warpnerf wrote there, so the demo trains
    afresh; files of other programs stay, and training then refuses them by name. (`warpnerf
    train ... --resume` continues a run instead.)"""
    if run.is_dir():
        for folder in [run, *(p for p in sorted(run.rglob("*")) if p.is_dir())]:
            remove_own(folder, owned_files(folder))
    return run


def parser(doc: str, out: str, **sizes):
    """The demo's parser with the flags every demo has: --out (default ``out``), --device, and
    integer flags such as frames=40, size=160 (``--frames``, ``--size``) with these defaults."""
    import argparse

    p = argparse.ArgumentParser(description=doc.splitlines()[0])
    p.add_argument("--out", default=out)
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    for name, default in sizes.items():
        p.add_argument("--" + name.replace("_", "-"), type=int, default=default)
    return p


def config_parser(doc: str, out: str, cls, flags, defaults, **sizes):
    """The parser of a demo that trains a config ``cls``: --out, the config's ``flags`` (from
    the dataclass, with the demo's ``defaults``) and the demo's integer ``sizes``."""
    import argparse

    from warpnerf.options import add_flags

    p = argparse.ArgumentParser(description=doc.splitlines()[0])
    p.add_argument("--out", default=out)
    add_flags(p, cls, include=flags, defaults=defaults)
    for name, default in sizes.items():
        p.add_argument("--" + name.replace("_", "-"), type=int, default=default)
    return p


def surface_summary(args, hist, metrics, renders, mesh_faces: int, **extra) -> dict:
    """The last JSON line of the surface demos (09, 11): data, steps, time, val figures, final
    beta, mesh size, renders folder, plus ``extra``."""
    return {
        "data": args.data,
        "iters": hist["step"][-1],
        "train_seconds": hist["seconds"][-1],
        "val_psnr": metrics["psnr"],
        "val_ssim": metrics["ssim"],
        "beta": hist["beta"][-1],
        "mesh_faces": int(mesh_faces),
        "renders": renders["out"],
        **extra,
    }
