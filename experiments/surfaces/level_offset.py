"""Where a surface run's zero level sits against the surface its renders show (issue 49, third
round), for a trained SDF run (`train volsdf`, field volsdf or hash_sdf):

a. |grad f| on the zero level set (the vertices of the mesh `warpnerf mesh` delivers; the
   field's own gradient: autograd for volsdf, finite differences for hash_sdf);
b. f at the rendered expected depth of opaque training rays (opacity > 0.5; the rays of the
   `--level rendered` rule, and the rule's level), and there the rendered minus the analytic
   depth;
c. the rendered expected depth minus the analytic first hit on val pixels (signed: negative,
   the render lies in front of the truth): do the renders shrink the spheres too?
d. `warpnerf eval RUN --geometry materials --level L` for each L of --levels: the delivered
   mesh's Chamfer, accuracy, completeness and median signed distance per shape.

Each as median, p10, p90 (and n), overall and per shape of the materials scene (the nearest
analytic shape to a vertex; the shape the analytic first hit lands on for a ray). The shapes
need the analytic truth: --truth materials (the default when the run's data folder is named
materials); --truth none gives a and b overall and the rule's level only. --parts runs some of
a-d (a call on a GPU machine may have a time limit). --data: the run's data moved.

    python experiments/surfaces/level_offset.py RUN [--data DIR] [--views 10] [--json OUT]
        [--levels 0 rendered 0.01 0.02 0.03 -0.01] [--resolution 384] [--parts abcd]

Prints a summary, then one JSON line with every figure (also written to --json).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import torch

LEVELS = ["0", "rendered", "0.01", "0.02", "0.03", "-0.01"]


def stats(x) -> dict:
    """n, median, p10, p90 of the values x [m] (None for an empty set)."""
    x = torch.as_tensor(x).double().reshape(-1).cpu()
    if x.numel() == 0:
        return {"n": 0, "median": None, "p10": None, "p90": None}
    q = torch.quantile(x[:: max(1, x.numel() // 1_000_000)], torch.tensor([0.1, 0.9]).double())
    return {"n": int(x.numel()), "median": float(x.median()), "p10": float(q[0]),
            "p90": float(q[1])}  # fmt: skip


def by_shape(values, ids) -> dict:
    """{"all": stats, shape name: stats} of values [m] grouped by materials shape ids [m]
    (-1: no shape, "none")."""
    from warpnerf.data.materials_truth import MATERIALS_NAMES

    values, ids = torch.as_tensor(values).reshape(-1).cpu(), torch.as_tensor(ids).reshape(-1)
    out = {"all": stats(values)}
    for i, name in enumerate(MATERIALS_NAMES):
        out[name] = stats(values[ids == i])
    if bool((ids < 0).any()):
        out["none"] = stats(values[ids < 0])
    return out


def hit_shapes(o, d, t) -> torch.Tensor:
    """[m] materials shape id of the points o + t d (-1 where t is not finite: no hit)."""
    from warpnerf.data.materials_truth import materials_shape_ids

    ok = torch.isfinite(t)
    ids = torch.full(t.shape, -1, dtype=torch.long)
    if bool(ok.any()):
        p = (o[ok] + t[ok].unsqueeze(-1) * d[ok]).cpu().numpy()
        ids[ok.cpu()] = torch.as_tensor(materials_shape_ids(p))
    return ids


def part_a(model, cfg, cull, resolution: int, truth: bool) -> dict:
    """|grad f| at the vertices of the zero level set's delivered mesh."""
    from warpnerf.data.materials_truth import MATERIALS_BELOW, materials_shape_ids
    from warpnerf.mesh import DEFAULT_CLEAN, extract_mesh, surface_mesh

    a, field = cfg.aabb, model.field
    v, f = extract_mesh(lambda p: field.sdf(p.to(cfg.device)), [-a] * 3, [a] * 3, resolution,
                        0.0, device=cfg.device)  # fmt: skip
    cams = cull["train"] if cfg.ndc_camera() is None else None
    v, f, _ = surface_mesh(v, f, cams, DEFAULT_CLEAN, device=cfg.device,
                           weight_grid=cull["weight_grid"])  # fmt: skip
    p = torch.as_tensor(v, dtype=torch.float32, device=cfg.device)
    with torch.no_grad():
        g = torch.cat([field.gradient(p[s : s + 65536]).norm(dim=-1).cpu()
                       for s in range(0, len(p), 65536)])  # fmt: skip
    if not truth:
        return {"grad_norm": {"all": stats(g)}, "vertices": len(v)}
    ids = torch.as_tensor(materials_shape_ids(v))
    ids[torch.as_tensor(v[:, 2] < MATERIALS_BELOW)] = -1  # (under the disk: no shape)
    return {"grad_norm": by_shape(g, ids), "vertices": len(v)}


def part_b(model, cfg, cull, rays: int, truth: bool) -> dict:
    """f at the rendered depths of the rule's training rays; the rule's level."""
    from warpnerf.data.materials_truth import materials_depth
    from warpnerf.train import surface_level as sl

    o, d = sl.training_rays(cfg, cull["refined"], rays, sl.LEVEL_SEED)
    s = sl.sdf_at_rendered_depth(model, cfg, o, d)
    beta = float(torch.as_tensor(model.field.beta).detach())
    level, rule = sl.level_of(s["sdf"], beta)
    out = {"rays": int(o.shape[0]), "opaque_rays": int(s["keep"].sum()), "beta": beta,
           "rule_level": level, "rule": rule}  # fmt: skip
    if not truth:
        return {**out, "sdf_at_depth": {"all": stats(s["sdf"])}}
    ok, dd = o[s["keep"]].double(), d[s["keep"]].double()
    t_true = materials_depth(ok, dd)
    ids = hit_shapes(ok, dd, t_true)
    hit = torch.isfinite(t_true)
    diff = (s["t"].double() - t_true)[hit]
    return {**out, "sdf_at_depth": by_shape(s["sdf"], ids),
            "depth_minus_truth": by_shape(diff, ids[hit.cpu()])}  # fmt: skip


def part_c(model, cfg, views: int) -> dict:
    """Rendered minus analytic depth on val pixels, per shape hit."""
    from warpnerf.data.materials_truth import materials_depth
    from warpnerf.train.geometry_eval import rendered_depths
    from warpnerf.train.nerf_run import load_data

    r = rendered_depths(model, cfg, load_data(cfg, "val"), materials_depth, views)
    ids = hit_shapes(r["origins"], r["directions"], r["true"])
    return {"views": r["views"], "depth_minus_truth": by_shape(r["rendered"] - r["true"], ids)}


def part_d(model, cfg, cull, run, levels, rule_level, resolution: int, points: int) -> list:
    """The delivered mesh's figures at each level (eval --geometry materials --level L)."""
    from warpnerf.data.materials_truth import materials_reference
    from warpnerf.errors import UserError
    from warpnerf.train.geometry_eval import surface_figures
    from warpnerf.train.surface_level import RENDERED, parse_level

    ref, rows = materials_reference(points), []
    for text in levels:
        level = parse_level(text)
        level = rule_level if level == RENDERED else level
        row = {"level": level, "as_given": text}
        try:
            r = surface_figures(model, cfg, "materials", ref, level, resolution, points,
                                cull=cull, what=str(run))  # fmt: skip
        except UserError as e:
            rows.append({**row, "error": str(e)})
            continue
        keys = ("chamfer", "accuracy", "completeness", "mesh_faces", "signed_median")
        row.update({k: r["delivered"].get(k) for k in keys}, raw_chamfer=r["chamfer"],
                   chamfer_visible=r["visible"]["chamfer_visible"])  # fmt: skip
        rows.append(row)
    return rows


def _f(x, w=8) -> str:
    return f"{x:+.4f}".rjust(w) if isinstance(x, float) else str(x).rjust(w)


def summary(res: dict) -> str:
    """The figures as short tables (medians; p10 / p90 in the JSON)."""
    lines = [f"{res['run']} (step {res['step']}, {res['field']}, {res['density']} density, "
             f"beta {res['beta']:.4g})"]  # fmt: skip

    def table(title, t):
        lines.append(f"{title}: median [p10, p90] (n)")
        for name, s in t.items():
            if s["n"]:
                lines.append(f"  {name:14s}{_f(s['median'])} [{_f(s['p10'])},{_f(s['p90'])}] "
                             f"({s['n']})")  # fmt: skip

    if "a" in res:
        table("a. |grad f| on the delivered zero level set", res["a"]["grad_norm"])
    if "b" in res:
        b = res["b"]
        lines.append(f"b. rule level {b['rule_level']:+.5f} ({b['rule_level'] / b['beta']:+.2f} "
                     f"beta; {b['opaque_rays']} of {b['rays']} training rays opaque)")  # fmt: skip
        table("b. f at the rendered depth of opaque training rays", b["sdf_at_depth"])
        if "depth_minus_truth" in b:
            table("b. rendered - analytic depth, training rays", b["depth_minus_truth"])
    if "c" in res:
        table("c. rendered - analytic depth, val pixels", res["c"]["depth_minus_truth"])
    if "d" in res:
        lines.append("d. delivered mesh by level: level, Chamfer, accuracy, completeness; "
                     "median signed distance per shape")  # fmt: skip
        for r in res["d"]:
            if "error" in r:
                lines.append(f"  {r['level']:+.4f} ({r['as_given']}): {r['error']}")
                continue
            sm = " ".join(f"{k.split()[0][:6]} {_f(v, 0)}" for k, v in
                          (r["signed_median"] or {}).items())  # fmt: skip
            lines.append(f"  {r['level']:+.4f} ({r['as_given']}):{_f(r['chamfer'])}"
                         f"{_f(r['accuracy'])}{_f(r['completeness'])}  {sm}")  # fmt: skip
    lines.append("seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in res["seconds"].items()))
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run")
    p.add_argument("--data", help="the run's data folder, where it is now")
    p.add_argument("--device", help="default: the run's")
    p.add_argument("--views", type=int, default=10, help="val images for c (0: all)")
    p.add_argument("--rays", type=int, default=None, help="training rays for b (default: the "
                   "rule's, so b's level is --level rendered's)")  # fmt: skip
    p.add_argument("--levels", nargs="+", default=LEVELS, help="levels for d (numbers or "
                   "'rendered')")  # fmt: skip
    p.add_argument("--resolution", type=int, default=384, help="marching-cubes nodes per axis")
    p.add_argument("--points", type=int, default=50_000, help="points sampled on each surface")
    p.add_argument("--truth", choices=("auto", "materials", "none"), default="auto")
    p.add_argument("--parts", default="abcd", help="which of a, b, c, d to run")
    p.add_argument("--json", help="also write the JSON here")
    a = p.parse_args(argv)
    from warpnerf.train.geometry_eval import mesh_culling
    from warpnerf.train.nerf_run import load_run
    from warpnerf.train.surface_level import LEVEL_RAYS, RENDERED, parse_level, rendered_level

    for text in a.levels:  # (before any work)
        parse_level(text)
    cfg, model, ckpt = load_run(a.run, a.device)
    if model.kind != "sdf":
        raise SystemExit(f"{a.run}: not an SDF run ({cfg.field})")
    if a.data:
        cfg = dataclasses.replace(cfg, data=str(a.data)).freeze()
    truth = a.truth == "materials" or (a.truth == "auto" and Path(cfg.data).name == "materials")
    t0 = time.perf_counter()
    cull = mesh_culling(model, cfg)
    if cull["refined"] is None:
        raise SystemExit(f"{a.run}: the run's training data is not at hand ({cfg.data}); --data")
    beta = float(torch.as_tensor(model.field.beta).detach())
    res = {"run": str(a.run), "step": int(ckpt["step"]), "field": cfg.field, "beta": beta,
           "density": getattr(model.field, "density_kind", "laplace"), "truth": truth,
           "seconds": {"culling": time.perf_counter() - t0}}  # fmt: skip
    rule_level = None
    for part in "abcd":
        if part not in a.parts or (part in "cd" and not truth):
            continue
        t0 = time.perf_counter()
        if part == "a":
            res["a"] = part_a(model, cfg, cull, a.resolution, truth)
        elif part == "b":
            res["b"] = part_b(model, cfg, cull, a.rays or LEVEL_RAYS, truth)
            if (a.rays or LEVEL_RAYS) == LEVEL_RAYS:  # (the rule's own rays: its level)
                rule_level = res["b"]["rule_level"]
        elif part == "c":
            res["c"] = part_c(model, cfg, a.views)
        else:
            if rule_level is None and RENDERED in map(parse_level, a.levels):
                rule_level = rendered_level(model, cfg, cull["refined"])[0]
            res["d"] = part_d(model, cfg, cull, a.run, a.levels, rule_level, a.resolution,
                              a.points)  # fmt: skip
        res["seconds"][part] = time.perf_counter() - t0
    print(summary(res), file=sys.stderr)
    line = json.dumps(res)
    if a.json:
        Path(a.json).write_text(line + "\n")
    print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
