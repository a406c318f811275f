"""Geometry of a VolSDF run on the materials scene against its analytic geometry (README of the
data: 8 spheres of radius 0.32 at z = 0.32, x in {-1.05, -0.35, 0.35, 1.05}, y in {-0.4, 0.4};
a ground disk of radius 1.6 at z = 0).

    python scripts/materials_geometry.py RUN [--resolution 256] [--json out.json]

Reports, in world units: Chamfer distances between the marching-cubes mesh of the learned SDF
and points sampled on the analytic surfaces (both directions; the mesh side restricted to
z > -0.1 since a closed SDF must give the infinitely thin disk some thickness underneath), and
the mean absolute error of the rendered expected depth on the val views, on pixels whose analytic
ray hits the geometry and whose rendered opacity exceeds 0.5.
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import torch

from warpnerf.mesh import extract_mesh, sample_surface
from warpnerf.ops import generate_rays
from warpnerf.train.nerf import load_data, load_run, render_rays_of
from warpnerf.train.nerf_eval import (
    MATERIALS_DISK,
    MATERIALS_RADIUS,
    MATERIALS_SPHERES,
    materials_reference,
)
from warpnerf.train.sdf import chamfer

CENTERS, R, DISK = MATERIALS_SPHERES, MATERIALS_RADIUS, MATERIALS_DISK


def analytic_points(n: int, seed: int = 0) -> np.ndarray:
    return materials_reference(n, seed)


def analytic_depth(o: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Distance along unit rays to the first analytic surface, inf on a miss."""
    t_best = torch.full(o.shape[:1], math.inf, dtype=o.dtype, device=o.device)
    for c in CENTERS:
        oc = o - torch.tensor(c, dtype=o.dtype, device=o.device)
        b = (oc * d).sum(-1)
        disc = b * b - (oc * oc).sum(-1) + R * R
        t = -b - torch.sqrt(disc.clamp_min(0))
        t_best = torch.where((disc > 0) & (t > 0) & (t < t_best), t, t_best)
    t = -o[:, 2] / d[:, 2]
    p = o + t.unsqueeze(-1) * d
    ok = (t > 0) & (p[:, 0] ** 2 + p[:, 1] ** 2 <= DISK * DISK)
    return torch.where(ok & (t < t_best), t, t_best)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--json", default=None)
    ap.add_argument("--val-images", type=int, default=20)
    args = ap.parse_args()
    cfg, model, _ = load_run(args.run)
    field = model.coarse
    b = 1.7
    v, f = extract_mesh(lambda p: field.sdf(p.to(cfg.device)), [-b, -b, -0.4], [b, b, 1.0],
                        args.resolution, 0.0, device=cfg.device)  # fmt: skip
    gt = torch.as_tensor(analytic_points(100_000))
    res = {"run": args.run, "faces": int(len(f)), "beta": float(field.beta)}
    if len(f):
        m = torch.as_tensor(sample_surface(v, f, 100_000), dtype=torch.float32)
        m_top = m[m[:, 2] > -0.1]
        mesh_to_gt, gt_to_mesh = chamfer(m_top, gt)
        res.update(chamfer=0.5 * (mesh_to_gt + gt_to_mesh), mesh_to_gt=mesh_to_gt,
                   gt_to_mesh=gt_to_mesh)  # fmt: skip
    val = load_data(cfg, "val")
    errs = []
    with torch.no_grad():
        for i in range(min(args.val_images, val.images.shape[0])):
            o, d = generate_rays(val.c2w[i], val.intrinsics[i], val.width, val.height)
            out = render_rays_of(model, cfg, o, d, chunk=cfg.chunk)
            t_gt = analytic_depth(o, d)
            # expected depth over opacity: the depth of the visible surface
            dep = out["depth"] / out["opacity"].clamp_min(1e-6)
            ok = torch.isfinite(t_gt) & (out["opacity"] > 0.5)
            errs.append((dep[ok] - t_gt[ok]).abs().cpu())
    e = torch.cat(errs)
    res.update(
        depth_abs_err_mean=float(e.mean()),
        depth_abs_err_median=float(e.median()),
        depth_pixels=int(e.numel()),
        units="world units (spheres have radius 0.32)",
    )
    print(json.dumps(res))
    if args.json:
        from warpnerf.io import write_json

        write_json(args.json, res)


if __name__ == "__main__":
    main()
