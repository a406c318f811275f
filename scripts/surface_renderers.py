"""Volume rendering against sphere tracing of a trained SDF run (hash_sdf, volsdf) on the same val
images: PSNR, SSIM, ms per frame of both, the mean |depth difference| where both see the surface,
and (--sweep) the sphere tracer's step scale, refinement steps and hit tolerance against PSNR.

    python scripts/surface_renderers.py RUN [--images 10] [--json out.json] [--sweep]

Timings: each renderer renders the first image once untimed (caches, kernel loads), then every
image ``--repeats`` times (median kept); the device is synchronised around each frame. Volume
rendering uses the run's own settings (chunk, march step, rounds); sphere tracing
``warpnerf.train.nerf_eval.sphere_traced_rays_of`` (what ``warpnerf eval --renderer sphere`` runs).
The last line printed is the JSON.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from warpnerf.metrics import psnr, ssim
from warpnerf.train.nerf import dataset_rays, load_data, load_run, render_rays_of
from warpnerf.train.nerf_eval import sphere_traced_rays_of


def _timed(fn, repeats, sync):
    times, out = [], None
    for _ in range(repeats):
        sync()
        t0 = time.perf_counter()
        out = fn()
        sync()
        times.append(1e3 * (time.perf_counter() - t0))
    return out, statistics.median(times)


def _summary(rows):
    keys = [k for k in rows[0] if k != "image"]
    return {k: statistics.fmean(r[k] for r in rows) for k in keys} | {"per_image": rows}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run")
    p.add_argument("--images", type=int, default=10, help="first N val images (0 = all)")
    p.add_argument("--split", default="val")
    p.add_argument("--device", default=None)
    p.add_argument("--repeats", type=int, default=3, help="timed renders per image (median)")
    p.add_argument("--sweep", action="store_true", help="also sweep the tracer's settings")
    p.add_argument("--json", default=None, help="also write the JSON here")
    a = p.parse_args(argv)
    cfg, model, ckpt = load_run(a.run, a.device)
    if model.kind != "sdf":
        raise SystemExit(f"{a.run}: not an SDF run (field {cfg.field})")
    ds = load_data(cfg, a.split)
    n = ds.images.shape[0] if a.images <= 0 else min(a.images, ds.images.shape[0])
    h, w = ds.height, ds.width
    sync = torch.cuda.synchronize if cfg.device.startswith("cuda") else (lambda: None)
    rays = [dataset_rays(cfg, ds, image=i) for i in range(n)]
    renderers = {
        "volume": lambda o, d: render_rays_of(model, cfg, o, d, chunk=cfg.chunk),
        "sphere": lambda o, d: sphere_traced_rays_of(model, cfg, o, d),
    }
    res = {"run": a.run, "step": ckpt["step"], "device": cfg.device, "images": n, "size": [w, h]}
    if cfg.device.startswith("cuda"):
        res["gpu"] = torch.cuda.get_device_name()
    outs = {}
    with torch.no_grad():
        for name, fn in renderers.items():
            fn(*rays[0])  # warm-up, untimed
            rows, outs[name] = [], []
            for i, (o, d) in enumerate(rays):
                out, ms = _timed(lambda o=o, d=d, fn=fn: fn(o, d), a.repeats, sync)
                rgb, gt = out["rgb"].reshape(h, w, 3), ds.images[i]
                row = {"image": i, "psnr": psnr(rgb, gt), "ssim": ssim(rgb, gt), "ms": ms}
                if name == "sphere":
                    row["iters"] = float(out["iters"].float().mean())
                    row["hit_fraction"] = out["n_hit"] / o.shape[0]
                rows.append(row)
                outs[name].append({k: out[k].reshape(-1) for k in ("depth", "opacity")})
            res[name] = _summary(rows)
            res[name]["ms_median"] = statistics.median(r["ms"] for r in rows)
        diffs, both, disagree = [], 0, 0
        for v, s in zip(outs["volume"], outs["sphere"]):
            vhit, shit = v["opacity"] > 0.5, s["opacity"] > 0
            m = vhit & shit
            diffs.append((v["depth"][m] / v["opacity"][m] - s["depth"][m]).abs().cpu())
            both += int(m.sum())
            disagree += int((vhit ^ shit).sum())
        dd = torch.cat(diffs)
        res["depth_abs_diff_mean"] = float(dd.mean()) if dd.numel() else None
        res["depth_abs_diff_median"] = float(dd.median()) if dd.numel() else None
        res["both_hit_fraction"] = both / (n * h * w)
        res["hit_disagreement_fraction"] = disagree / (n * h * w)  # volume opacity > 0.5 xor hit
        res["speedup_sphere_over_volume"] = res["volume"]["ms_median"] / res["sphere"]["ms_median"]
        if a.sweep:
            res["sweep"] = _sweep(model, cfg, ds, rays, sync)
    line = json.dumps(res)
    if a.json:
        with open(a.json, "w") as f:
            f.write(line + "\n")
    print(json.dumps({k: v for k, v in res.items() if k not in ("volume", "sphere", "sweep")}))
    for name in ("volume", "sphere"):
        print(name, json.dumps({k: v for k, v in res[name].items() if k != "per_image"}))
    for row in res.get("sweep", []):
        print("sweep", json.dumps(row))
    print(line)


def _sweep(model, cfg, ds, rays, sync):
    """PSNR and ms of the sphere tracer's settings (one timed render per image); ``cone`` is in
    half-pixels (x 0.5 / fx), ``eps`` in box half-sizes (x aabb)."""
    h, w = ds.height, ds.width
    half_pixel = 0.5 / float(ds.intrinsics[0, 0])
    rows = []
    grid = [dict(step_scale=s, refine_steps=r) for s in (1.0, 0.9, 0.8, 0.7) for r in (0, 1, 3)]
    grid += [dict(eps=e) for e in (1e-4, 1e-3, 2e-3, 3e-3, 5e-3)]
    grid += [dict(eps=1e-4, cone=c) for c in (0.5, 1.0, 2.0)]
    grid += [dict(max_iters=m) for m in (32, 48, 128)]
    for kw in grid:
        trace = dict(kw)
        trace["eps"] = kw.get("eps", 1e-3) * cfg.aabb
        trace["cone"] = kw.get("cone", 0.0) * half_pixel
        ps, ms = [], []
        with torch.no_grad():
            for i, (o, d) in enumerate(rays):
                out, t = _timed(lambda o=o, d=d, kw=trace: sphere_traced_rays_of(model, cfg, o, d,
                                                                                 **kw),
                                1, sync)  # fmt: skip
                ps.append(psnr(out["rgb"].reshape(h, w, 3), ds.images[i]))
                ms.append(t)
        rows.append({**kw, "psnr": statistics.fmean(ps), "ms_median": statistics.median(ms),
                     "iters": float(out["iters"].float().mean())})  # fmt: skip
    return rows


if __name__ == "__main__":
    main()
