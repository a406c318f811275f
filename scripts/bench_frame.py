"""Frame time of a grid run's val views: the tracer (``render_marched``'s default without
gradients, :func:`warpnerf.render_traced.render_traced`) against the older rounds path
(``tracer="rounds"``), with each one's PSNR against the val images and the PSNR between their
images (the same image: >= ~50 dB). Runs on the CPU too (its smoke test); timings are for the GPU.

python3 scripts/bench_frame.py RUN [--data PATH] [--device cuda] [--images 0] [--repeat 3]
    [--variants rounds,traced,traced-all,rounds-N] [--min-steps 8] [--max-steps 128]
    [--chunk N] [--half] [--json F] [--profile N]

``rounds-N``: the rounds path marching N samples a live ray a round (more as rays finish), so
that rays stop marching once opaque; ``samples_per_frame`` gives each variant's counters (samples
marched, coloured) a frame. A ``+fwd`` suffix (``rounds+fwd``, ``rounds-16+fwd``; hash_sdf runs)
renders the normals by forward differences whatever the run trained with. The rounds variants
colour as the library renders (``render_marched``'s default: from ``RENDER_COLOR_EPS``, 1e-3,
in the image, or a 100th of the ray's heaviest sample where less, the others taking the
coloured ones' mean colour along their ray); ``+epsE`` (``rounds+eps1e-4``,
``rounds-32+fwd+eps1e-2``) takes E for 1e-3, and ``+black`` counts the others black
(``rounds+eps1e-5+black``: the rule before 2026-12-03, and the tracer's; on 2026-12-03 an
``+epsE`` variant without a fill was black, and E was a plain threshold). ``+wsp`` runs the SDF
network's softplus by the Warp kernels (``warpnerf.ops.activations``, the A/B of issue 47) instead
of torch's op, ``+cen`` reads its input [2 u - 1, features] from the encoding's kernel
(``hash_encode(..., centred=True)``) instead of a concatenation.

Each variant renders every selected view ``--repeat`` times after one warm-up frame (the first
view, untimed); a frame's time is from a device sync before to one after (as ``warpnerf eval``'s
``render_ms``). Variants run one after another per view (interleaved), so a drift of the
machine's speed touches them alike.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time

import torch

from warpnerf.metrics import psnr
from warpnerf.ops.activations import activation_kernels
from warpnerf.ops.encoding import encoding_kernels
from warpnerf.ops.tracer import MAX_STEPS, MIN_STEPS
from warpnerf.render import RENDER_COLOR_EPS, render_chunks, render_marched
from warpnerf.render_traced import render_traced
from warpnerf.train.nerf import dataset_rays, load_data, load_run, with_refined_poses

VARIANTS = ("rounds", "traced", "traced-all")


def forward_differences(field, fn):
    """``fn`` run with the surface field's normals by forward differences (``+fwd``: 3 more SDF
    evaluations a coloured sample instead of central differences' 6), whatever the run trained
    with (with ``--sdf-density neus`` the density's gradient too, so the marching's weights
    change as well); the field's own setting is restored after each call."""
    if not hasattr(field, "forward_differences"):
        raise SystemExit("+fwd: a hash_sdf run's variant (its field takes finite differences)")

    def run(o, d, sl):
        old, field.forward_differences = field.forward_differences, True
        try:
            return fn(o, d, sl)
        finally:
            field.forward_differences = old

    return run


def parse_variant(name: str):
    """(base, fwd, eps, fill) of a variant's name, e.g. "rounds-32+fwd+eps1e-4+black" ->
    ("rounds-32", True, 0.0001, "black"); None when it is not one (eps and black: the rounds
    path's only; eps in (0, 1))."""
    base, *mods = name.split("+")
    for k in ("wsp", "cen"):  # (kernel switches: any variant, once)
        mods = [m for m in mods if m != k] if mods.count(k) == 1 else mods
    fwd, eps, fill = "fwd" in mods, RENDER_COLOR_EPS, "black" if "black" in mods else "mean"
    if fill == "black" and not base.startswith("rounds"):
        return None
    for m in mods:
        if m in ("fwd", "black"):
            continue
        try:
            eps = float(m[3:]) if m.startswith("eps") else float("nan")
        except ValueError:
            return None
        if not 0.0 < eps < 1.0 or not base.startswith("rounds"):
            return None
    rounds_n = base.startswith("rounds-") and base[7:].isdecimal() and int(base[7:]) > 0
    twice = len(mods) != len(set(mods)) or sum(m.startswith("eps") for m in mods) > 1
    if twice or not (base in VARIANTS or rounds_n):
        return None
    return base, fwd, eps, fill


def renderer(name, model, cfg, a):
    """render(o, d) -> dict for a variant: the rounds path with the run's settings, or the
    tracer with --min-steps/--max-steps and its colour rule; a ``+fwd`` suffix renders a
    surface field's normals by forward differences, ``+epsE`` colours the samples weighing at
    least E in the image (the rounds path)."""
    base, fwd, eps, fill = parse_variant(name)
    if "+wsp" in name or "+cen" in name:  # the SDF network's softplus by the Warp kernels
        # (ops/activations.py), its input [2 u - 1, features] from the encoding's kernel
        wsp, cen = "+wsp" in name, "+cen" in name
        inner = renderer(name.replace("+wsp", "").replace("+cen", ""), model, cfg, a)

        def run(o, d, sl):
            with activation_kernels("warp" if wsp else "torch"), encoding_kernels(centred=cen):
                return inner(o, d, sl)

        return run
    if fwd:
        plain = name.replace("+fwd", "")
        return forward_differences(model.coarse, renderer(plain, model, cfg, a))
    kw = dict(background=cfg.background, t_threshold=cfg.t_threshold, half=a.half)
    if base == "rounds" or base.startswith("rounds-"):  # rounds-N: N samples a live ray a round
        rs = cfg.round_samples if base == "rounds" else int(base.split("-", 1)[1])
        return lambda o, d, sl: render_marched(
            model.grid, model.coarse, o[sl], d[sl], cfg.near, cfg.far, tracer="rounds",
            max_samples=cfg.max_samples, round_samples=rs, color_eps=eps, color_fill=fill, **kw,
        )  # fmt: skip
    colors = "all" if name == "traced-all" else "weighted"
    return lambda o, d, sl: render_traced(
        model.grid, model.coarse, o[sl], d[sl], cfg.near, cfg.far, colors=colors,
        min_steps=a.min_steps, max_steps=a.max_steps, **kw,
    )  # fmt: skip


def profile_frames(fn, cfg, ds, n: int, sync) -> dict:
    """``n`` renders of the first view under torch.profiler: the device (CUDA) or host (CPU)
    time a frame of the 15 costliest operators, their sum over the kernels alone (the device's
    busy time a frame), launches a frame, and the samples the frame composited."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    cuda = cfg.device.startswith("cuda")
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with torch.no_grad():
        o, d = dataset_rays(cfg, ds, image=0)
        out = render_chunks(o.shape[0], cfg.chunk, lambda sl: fn(o, d, sl))
        sync()
        with profile(activities=acts) as prof:
            for _ in range(n):
                render_chunks(o.shape[0], cfg.chunk, lambda sl: fn(o, d, sl))
            sync()
    ka = prof.key_averages()
    key = "self_device_time_total" if cuda else "self_cpu_time_total"
    top = sorted(ka, key=lambda k: -getattr(k, key, 0.0))[:15]
    kernels = [k for k in ka if k.device_type == DeviceType.CUDA]
    counters = {k: int(v) for k, v in out.items() if k.startswith("n_")
                and (isinstance(v, int) or (torch.is_tensor(v) and v.dim() == 0))}  # fmt: skip
    busy = sum(k.self_device_time_total for k in kernels) / 1e3 / n if cuda else None
    launches = sum(k.count for k in ka if k.key in ("cudaLaunchKernel", "cuLaunchKernel"))
    sync_keys = ("aten::_local_scalar_dense", "cudaStreamSynchronize", "cudaDeviceSynchronize")
    syncs = sum(k.count for k in ka if k.key in sync_keys)
    return {
        "frames": n,
        "device_busy_ms_per_frame": busy,
        "launches_per_frame": launches / n,
        "host_syncs_per_frame": syncs / n,
        "counters": counters,  # (the renderer's: samples marched and kept, rounds)
        "top_ms_per_frame": {k.key: getattr(k, key) / 1e3 / n for k in top},
    }


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run")
    p.add_argument("--data", default=None, help="the dataset folder (default: the run's)")
    p.add_argument("--device", default=None, help="cpu or cuda (default: the run's)")
    p.add_argument("--split", default="val")
    p.add_argument("--images", type=int, default=0, help="views (0: all of the split)")
    p.add_argument("--repeat", type=int, default=3, help="timed renders per view and variant")
    p.add_argument("--variants", default="rounds,traced,traced-all")
    p.add_argument("--min-steps", type=int, default=MIN_STEPS, help="tracer: samples per live "
                   "ray and round, at least")  # fmt: skip
    p.add_argument("--max-steps", type=int, default=MAX_STEPS, help="tracer: samples per live "
                   "ray and round, at most")  # fmt: skip
    p.add_argument("--chunk", type=int, default=None, help="rays at once (default: the run's)")
    p.add_argument("--half", action="store_true", help="float16 MLPs (CUDA)")
    p.add_argument("--json", default=None, help="also write the results here")
    p.add_argument("--profile", type=int, default=0, help="then N frames of the first view "
                   "with the first variant under torch.profiler: device time a frame by kernel, "
                   "and the samples a frame (the run's own rendering)")  # fmt: skip
    a = p.parse_args()
    names = a.variants.split(",")

    if not all(parse_variant(n) for n in names) or "rounds" not in names:
        raise SystemExit(
            f"--variants: some of {VARIANTS} or rounds-N (the rounds path with N "
            "samples a live ray a round), each optionally +fwd (hash_sdf: normals "
            "by forward differences) and, for rounds variants, +epsE (colour the samples "
            "weighing at least E, 0 < E < 1) and +black (the others count black, not the "
            "coloured ones' mean colour), with rounds (the reference)"
        )
    cfg, model, _ = load_run(a.run, a.device)
    if model.grid is None:
        raise SystemExit("a run with an occupancy grid is needed")
    changed = {k: v for k, v in (("data", a.data), ("chunk", a.chunk)) if v}
    if changed:  # (the run's config with the flags given: a checked, frozen copy)
        cfg = dataclasses.replace(cfg, **changed).check_values().freeze()
    ds = with_refined_poses(model, load_data(cfg, a.split), a.split)
    n = ds.images.shape[0] if not a.images else min(a.images, ds.images.shape[0])
    sync = torch.cuda.synchronize if cfg.device.startswith("cuda") else (lambda: None)
    fns = {k: renderer(k, model, cfg, a) for k in names}
    ms = {k: [] for k in names}
    quality = {k: [] for k in names}
    same = {k: [] for k in names if k != "rounds"}
    rounds = []
    counts = {k: {} for k in names}  # each variant's sample counters, summed over the views
    with torch.no_grad():
        o, d = dataset_rays(cfg, ds, image=0)
        for k in names:  # warm-up: kernels compiled, allocator primed
            render_chunks(o.shape[0], cfg.chunk, lambda sl, k=k: fns[k](o, d, sl))
        for i in range(n):
            o, d = dataset_rays(cfg, ds, image=i)
            gt = ds.images[i].to(o.device)
            shape = gt.shape
            imgs = {}
            for _ in range(a.repeat):
                for k in names:
                    sync()
                    t0 = time.perf_counter()
                    out = render_chunks(o.shape[0], cfg.chunk,
                                        lambda sl, k=k, o=o, d=d: fns[k](o, d, sl))  # fmt: skip
                    sync()
                    ms[k].append(1e3 * (time.perf_counter() - t0))
                    imgs[k] = out
            for k in names:
                for c, v in imgs[k].items():
                    if c.startswith("n_") and isinstance(v, int):
                        counts[k][c] = counts[k].get(c, 0) + v
                quality[k].append(psnr(imgs[k]["rgb"].reshape(shape), gt))
                if k != "rounds":
                    ref = imgs["rounds"]["rgb"].reshape(shape)
                    same[k].append(psnr(imgs[k]["rgb"].reshape(shape), ref))
            rounds.append(imgs.get("traced", imgs[names[-1]]).get("n_rounds"))
    res = {
        "run": a.run, "device": cfg.device, "views": n, "repeat": a.repeat, "half": a.half,
        "min_steps": a.min_steps, "max_steps": a.max_steps, "chunk": cfg.chunk,
        "frame_ms_median": {k: statistics.median(v) for k, v in ms.items()},
        "psnr_vs_gt": {k: statistics.mean(v) for k, v in quality.items()},
        "psnr_vs_rounds_min": {k: min(v) for k, v in same.items()},
        "psnr_vs_rounds_mean": {k: statistics.mean(v) for k, v in same.items()},
        "tracer_rounds_per_frame": rounds,
        "samples_per_frame": {k: {c: v / n for c, v in cs.items()} for k, cs in counts.items()},
    }  # fmt: skip
    if cfg.device.startswith("cuda"):
        res["gpu"] = torch.cuda.get_device_name()
    if a.profile > 0:
        res["profile"] = profile_frames(fns[names[0]], cfg, ds, a.profile, sync)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)
    print(json.dumps(res))


if __name__ == "__main__":
    main()
