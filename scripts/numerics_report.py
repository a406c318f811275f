"""Float32 kernel error against the float64 twin as the number of samples per ray grows.

For every kernel family, on the same (float32-rounded) inputs: the float32 Warp kernel, and the
float64 Warp kernel where one exists, against the pure-PyTorch float64 twin
(``warpnerf.reference``). Errors: ``max_abs`` = max |kernel - twin| over all entries, and
``max_rel`` = max_abs / max |twin| (normwise, so entries near 0 do not blow it up).

    python3 scripts/numerics_report.py --device cpu --json docs/data/numerics_cpu.json
    python3 scripts/numerics_report.py --device cuda --json docs/data/numerics_h100.json

Families: compositing forward (rgb, opacity, depth) and gradients (v_sigmas, v_rgbs, and the
background's, i.e. the final transmittance), stratified and importance sampling (edge positions),
hash encoding (features and the table gradient), ray generation and ray/box intersection,
occupancy marching (rays whose sample count differs from the brute-force twin in float32 and
in float64) and sphere tracing (hit t against the closed form and the float64 torch tracer, as
the iteration cap grows). Prints Markdown tables and writes JSON.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import sys
import time

import torch

F32, F64 = torch.float32, torch.float64
SIZES = (8, 64, 512, 4096, 16384)
FAMILIES = ("composite", "sampling", "encoding", "rays", "march", "sphere_trace")


# Every kernel output and gradient compared below, and how many of them were NaN or Inf.
CHECKED = {"values": 0, "non_finite": 0}


def err(a: torch.Tensor, e: torch.Tensor) -> dict:
    a, e = a.detach().double().cpu(), e.detach().double().cpu()
    CHECKED["values"] += a.numel()
    CHECKED["non_finite"] += int((~torch.isfinite(a)).sum())
    if not bool(torch.isfinite(a).all()):
        return {"max_abs": float("nan"), "max_rel": float("nan"), "non_finite": True}
    d = float((a - e).abs().max()) if e.numel() else 0.0
    scale = float(e.abs().max()) if e.numel() else 0.0
    return {"max_abs": d, "max_rel": d / scale if scale > 0 else 0.0}


def cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            model = next(line for line in f if line.startswith("model name")).split(":", 1)[1]
        return f"{model.strip()}, {os.cpu_count()} cores"
    except (OSError, StopIteration):
        return platform.processor() or "cpu"


def n_rays_for(n: int, budget: int) -> int:
    return max(4, min(256, budget // n))


# --------------------------------------------------------------------------------------------------
# compositing


def composite_case(n_rays: int, n: int, dev, seed: int = 0):
    """Stratified jittered samples on [2, 6]; total optical depth per ray log-spaced from 0.01
    (transparent) to 30 (opaque); random colours, backgrounds and upstream gradients."""
    import warpnerf as W

    g = torch.Generator().manual_seed(seed)
    near = torch.full((n_rays,), 2.0, device=dev)
    smp = W.stratified_samples(near, near + 4.0, n, perturb=True, seed=seed, packed=True)
    m = smp.t_starts.shape[0]
    tau_total = torch.logspace(-2, math.log10(30.0), n_rays, dtype=F64)
    sig = (tau_total / 4.0)[smp.ray_indices.cpu()] * torch.rand(m, generator=g, dtype=F64) * 2
    return {
        "smp": smp,
        "sigmas": sig.float().to(dev),
        "rgbs": torch.rand(m, 3, generator=g).to(dev),
        "bg": torch.rand(n_rays, 3, generator=g).to(dev),
        "up": [
            torch.randn(n_rays, 3, generator=g).to(dev),
            torch.randn(n_rays, generator=g).to(dev),
            torch.randn(n_rays, generator=g).to(dev),
        ],
        "n_rays": n_rays,
    }


def composite_run(lib, c, dtype):
    smp = c["smp"]
    sig = c["sigmas"].to(dtype).requires_grad_()
    rgbs = c["rgbs"].to(dtype).requires_grad_()
    bg = c["bg"].to(dtype).requires_grad_()
    out = lib.render_packed(
        smp.t_starts.to(dtype),
        smp.t_ends.to(dtype),
        smp.ray_indices,
        sig,
        rgbs,
        c["n_rays"],
        bg,
        packed_info=smp.packed_info,
    )
    grads = torch.autograd.grad(out, (sig, rgbs, bg), [u.to(dtype) for u in c["up"]])
    return dict(
        zip(("rgb", "depth", "opacity", "v_sigmas", "v_rgbs", "v_background"), [*out, *grads])
    )


def composite_family(dev, sizes, budget):
    import warpnerf as W
    from warpnerf import reference as R
    from warpnerf.ops import composite as C

    rows = []
    for n in sizes:
        c = composite_case(n_rays_for(n, budget), n, dev)
        ref = composite_run(R, c, F64)
        paths = [
            ("f32 tiled", F32, "tiled"),
            ("f32 sequential", F32, "sequential"),
            ("f64 kernel", F64, "tiled"),
        ]
        for label, dtype, impl in paths:
            old = dict(C._IMPL)
            C._IMPL["float32_sigma"] = impl
            try:
                got = composite_run(W, c, dtype)
            finally:
                C._IMPL.update(old)
            for q in got:
                rows.append(
                    {
                        "n": n,
                        "n_rays": c["n_rays"],
                        "path": label,
                        "quantity": q,
                        **err(got[q], ref[q]),
                    }
                )
    return rows


# --------------------------------------------------------------------------------------------------
# sampling


def sampling_family(dev, sizes, budget):
    import warpnerf as W
    from warpnerf import reference as R
    from warpnerf.ops.sampling import Samples, importance_samples
    from warpnerf.reference.sampling import importance_samples as ref_importance

    rows = []
    for n in sizes:
        n_rays = n_rays_for(n, budget)
        g = torch.Generator().manual_seed(1)
        near = (torch.rand(n_rays, generator=g) * 2 + 0.5).to(dev)
        far = near + (torch.rand(n_rays, generator=g) * 5 + 0.5).to(dev)
        ref = R.stratified_samples(near.double(), far.double(), n)
        for label, dtype in (("f32 kernel", F32), ("f64 kernel", F64)):
            s = W.stratified_samples(near.to(dtype), far.to(dtype), n)
            e = err(torch.cat([s.t_starts, s.t_ends]), torch.cat([ref.t_starts, ref.t_ends]))
            rows.append(
                {
                    "family": "stratified",
                    "n": n,
                    "n_rays": n_rays,
                    "path": label,
                    "quantity": "t edges",
                    **e,
                }
            )
        # Importance: n coarse intervals (jittered), compositing-like weights, n fine positions.
        coarse = W.stratified_samples(near, far, n, perturb=True, seed=2)
        w = torch.rand(n_rays, n, generator=g) ** 8
        w[:, n // 3 : n // 3 + max(1, n // 20)] += 1.0  # a surface
        w = (w / w.sum(-1, keepdim=True)).to(dev)
        c64 = Samples(coarse.t_starts.double(), coarse.t_ends.double())
        ref = ref_importance(c64, w.double(), n)
        for label, dtype in (("f32 kernel", F32), ("f64 kernel", F64)):
            cs = Samples(coarse.t_starts.to(dtype), coarse.t_ends.to(dtype))
            out = importance_samples(cs, w.to(dtype), n)
            e = err(torch.cat([out.t_starts, out.t_ends]), torch.cat([ref.t_starts, ref.t_ends]))
            rows.append(
                {
                    "family": "importance",
                    "n": n,
                    "n_rays": n_rays,
                    "path": label,
                    "quantity": "t edges",
                    **e,
                }
            )
    return rows


# --------------------------------------------------------------------------------------------------
# hash encoding


def encoding_family(dev, sizes, budget):
    from warpnerf.ops.encoding import HashGrid, hash_encode
    from warpnerf.reference.encoding import hash_encode as ref_encode

    grid = HashGrid(n_levels=8, n_features=2, log2_size=14, base_res=16, max_res=512)
    rows = []
    for n in sizes:
        n_rays = n_rays_for(n, budget)
        g = torch.Generator().manual_seed(3)
        o = torch.rand(n_rays, 1, 3, generator=g)
        d = torch.nn.functional.normalize(torch.randn(n_rays, 1, 3, generator=g), dim=-1)
        t = torch.linspace(0, 1, n).reshape(1, n, 1)
        x = (o + t * d * 0.8).reshape(-1, 3).clamp(0, 1).to(dev)  # n points along each ray
        table = (torch.randn(grid.n_rows, 2, generator=g) * 1e-2).to(dev)
        v_out = torch.randn(x.shape[0], grid.out_dim, generator=g).to(dev)
        t64 = table.double().requires_grad_()
        ref = ref_encode(x.double(), t64, grid)
        (ref_g,) = torch.autograd.grad(ref, t64, v_out.double())
        for label, dtype in (("f32 kernel", F32), ("f64 kernel", F64)):
            tt = table.to(dtype).requires_grad_()
            out = hash_encode(x.to(dtype), tt, grid)
            (gt,) = torch.autograd.grad(out, tt, v_out.to(dtype))
            for q, a, e in (("features", out, ref), ("v_table", gt, ref_g)):
                rows.append(
                    {
                        "n": n,
                        "n_rays": n_rays,
                        "points": x.shape[0],
                        "path": label,
                        "quantity": q,
                        **err(a, e),
                    }
                )
    return rows


# --------------------------------------------------------------------------------------------------
# rays


def rays_family(dev):
    import warpnerf as W
    from warpnerf import reference as R

    g = torch.Generator().manual_seed(4)
    # four cameras 4 units from the origin looking at it (OpenGL: the camera looks down -z)
    eye = torch.nn.functional.normalize(torch.randn(4, 3, generator=g, dtype=F64), dim=-1) * 4
    z = torch.nn.functional.normalize(eye, dim=-1)
    x = torch.nn.functional.normalize(
        torch.cross(torch.tensor([0.0, 1.0, 0.0], dtype=F64).expand(4, 3), z, dim=-1), dim=-1
    )
    y = torch.cross(z, x, dim=-1)
    c2w = torch.zeros(4, 4, 4, dtype=F64)
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = x, y, z, eye
    c2w[:, 3, 3] = 1.0
    k = torch.tensor([[300.0, 300.0, 200.0, 150.0]] * 4, dtype=F64)
    c2w32, k32 = c2w.float(), k.float()
    ro, rd = R.generate_rays(c2w32.double(), k32.double(), 400, 300)
    rows = []
    for label, dtype in (("f32 kernel", F32), ("f64 kernel", F64)):
        o, d = W.generate_rays(c2w32.to(dev, dtype), k32.to(dev, dtype), 400, 300)
        rows.append(
            {
                "op": "generate_rays",
                "n": o.shape[0],
                "path": label,
                "quantity": "directions",
                **err(d, rd),
            }
        )
    box = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]
    o32, d32 = ro.float(), rd.float()
    r0, r1, rh = R.ray_aabb_intersect(o32.double(), d32.double(), box)
    for label, dtype in (("f32 kernel", F32), ("f64 kernel", F64)):
        t0, t1, hit = W.ray_aabb_intersect(o32.to(dev, dtype), d32.to(dev, dtype), box)
        both = (hit.cpu() & rh).nonzero().squeeze(1)
        e = err(torch.cat([t0.cpu()[both], t1.cpu()[both]]), torch.cat([r0[both], r1[both]]))
        rows.append(
            {
                "op": "ray_aabb",
                "n": o32.shape[0],
                "path": label,
                "quantity": f"t_near, t_far ({len(both)} hits)",
                "hit_mismatch": int((hit.cpu() != rh).sum()),
                **e,
            }
        )
    return rows


# --------------------------------------------------------------------------------------------------
# occupancy marching


def march_family(dev, sizes):
    from warpnerf.ops import occupancy as O
    from warpnerf.reference import occupancy as RO

    res, box = 32, [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]
    g = torch.Generator().manual_seed(5)
    # blobs: cells within random spheres are occupied (about 20% of the grid)
    c = (torch.arange(res) + 0.5) / res * 2 - 1
    xyz = torch.stack(torch.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)
    centers, radii = torch.rand(12, 3, generator=g) * 1.6 - 0.8, torch.rand(12, generator=g) * 0.3
    occ = ((xyz[:, None] - centers).norm(dim=-1) < radii + 0.1).any(-1)
    bits = O.grid_pack_bits(occ.float().to(dev), 0.5)
    n_rays = 512
    o = torch.nn.functional.normalize(torch.randn(n_rays, 3, generator=g), dim=-1) * 3
    d = torch.nn.functional.normalize(torch.randn(n_rays, 3, generator=g) * 0.5 - o, dim=-1)
    d[:32] = torch.nn.functional.normalize(d[:32] * torch.tensor([1.0, 1e-4, 1.0]), dim=-1)
    o, d = o.to(dev), d.to(dev)
    rows = []
    for n in sizes:
        dt = 2 * math.sqrt(3) / n  # n steps along the box diagonal
        s, _ = O.march_rays(o, d, 0.0, 10.0, bits, res, box, dt, max_samples=4 * n)
        cnt = s.packed_info[:, 1].cpu().long()
        row = {
            "n": n,
            "n_rays": n_rays,
            "samples": int(cnt.sum()),
            "occupancy": float(occ.float().mean()),
        }
        for label, oo, dd in (("f32 twin", o, d), ("f64 twin", o.double(), d.double())):
            sr, _ = RO.march_rays(oo, dd, 0.0, 10.0, bits, res, box, dt, max_samples=4 * n)
            cr = sr.packed_info[:, 1].cpu().long()
            key = label.split()[0]
            row[f"rays_count_mismatch_{key}"] = int((cnt != cr).sum())
            row[f"abs_count_diff_{key}"] = int((cnt - cr).abs().sum())
            same = torch.equal(cnt, cr)
            row[f"t_max_abs_{key}"] = err(s.t_starts, sr.t_starts)["max_abs"] if same else None
        rows.append(row)
    return rows


# --------------------------------------------------------------------------------------------------
# sphere tracing


def sphere_family(dev, caps, eps_values):
    from warpnerf.fields.sdf_scene import SDFScene
    from warpnerf.ops.sphere_trace import sphere_trace
    from warpnerf.reference.sphere_trace import sphere_trace as ref_trace
    from warpnerf.sphere_tracing import CAP, HIT

    center, radius = torch.tensor([0.1, -0.2, 0.05], dtype=F64), 0.8
    scene = SDFScene().sphere(radius, center=center.tolist())
    g = torch.Generator().manual_seed(6)
    n_rays = 2048
    o = torch.nn.functional.normalize(torch.randn(n_rays, 3, generator=g, dtype=F64), dim=-1) * 4
    aim = center + (torch.rand(n_rays, 3, generator=g, dtype=F64) - 0.5) * 2.2 * radius
    d = torch.nn.functional.normalize(aim - o, dim=-1)
    o32, d32 = o.float(), d.float()
    oc, dd = o32.double() - center, d32.double()
    a, b = (dd * dd).sum(-1), (oc * dd).sum(-1)
    disc = b**2 - a * ((oc**2).sum(-1) - radius**2)
    t_exact = (-b - torch.sqrt(disc.clamp_min(0))) / a
    cos = torch.sqrt(disc.clamp_min(0) / a) / radius  # |n . d| at the hit
    rows = []
    for eps in eps_values:
        for cap in caps:
            kw = dict(eps=eps, max_iters=cap)
            tr = sphere_trace(o32.to(dev), d32.to(dev), scene, 0.0, 10.0, **kw)
            ref = ref_trace(o32.double(), d32.double(), scene, 0.0, 10.0, **kw)
            st, t = tr.status.cpu(), tr.t.double().cpu()
            hit = st == HIT
            clear = hit & (cos > 0.1)
            both = hit & (ref.status == HIT)
            rows.append(
                {
                    "eps": eps,
                    "max_iters": cap,
                    "n_rays": n_rays,
                    "hits": int(hit.sum()),
                    "cap": int((st == CAP).sum()),
                    "mean_iters": float(tr.iters.float().mean()),
                    "t_err_clear_hits": err(t[clear], t_exact[clear])["max_abs"],
                    "t_err_all_hits": err(t[hit], t_exact[hit])["max_abs"],
                    # the stopping rule's own bound is eps / |n . d|: this ratio should be <= 1
                    "t_err_over_bound": err(t[hit] * cos[hit] / eps, t_exact[hit] * cos[hit] / eps)[
                        "max_abs"
                    ],
                    "t_err_vs_f64_tracer": err(t[both], ref.t[both])["max_abs"],
                    "status_mismatch_vs_f64_tracer": int((st != ref.status).sum()),
                    "false_hits": int((hit & (disc < 0)).sum()),
                }
            )
    return rows


# --------------------------------------------------------------------------------------------------
# output


def fmt(x) -> str:
    if x is None:
        return "-"
    if isinstance(x, float):
        if x == 0 or not math.isfinite(x):
            return "0" if x == 0 else str(x)
        return f"{x:.3g}" if 1e-2 <= abs(x) < 1e5 else f"{x:.1e}"
    return str(x)


def table(rows, cols) -> str:
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(r.get(c)) for c in cols) + " |" for r in rows]
    return "\n".join(lines)


def pivot(rows, quantities, paths) -> list:
    """One row per (n, path) with max_abs / max_rel per quantity."""
    out = []
    for n in sorted({r["n"] for r in rows}):
        for p in paths:
            row = {"n": n, "path": p}
            for r in rows:
                if r["n"] == n and r["path"] == p and r["quantity"] in quantities:
                    row[r["quantity"]] = f"{fmt(r['max_abs'])} / {fmt(r['max_rel'])}"
            if len(row) > 2:
                out.append(row)
    return out


MARCH_COLS = ("n", "samples", "rays_count_mismatch_f32", "t_max_abs_f32",
              "rays_count_mismatch_f64", "abs_count_diff_f64")  # fmt: skip
SPHERE_COLS = ("eps", "max_iters", "hits", "cap", "mean_iters", "t_err_clear_hits",
               "t_err_all_hits", "t_err_over_bound", "t_err_vs_f64_tracer",
               "status_mismatch_vs_f64_tracer", "false_hits")  # fmt: skip


def markdown(report) -> str:
    """The report's tables in Markdown (families that were not run are left out)."""
    t, m = report["tables"], report["meta"]
    paths = ("f32 tiled", "f32 sequential", "f64 kernel")
    fwd, grad = ("rgb", "opacity", "depth"), ("v_sigmas", "v_rgbs", "v_background")
    sections = [
        ("composite", "Compositing forward, max abs / max rel vs the float64 twin",
         lambda r: pivot(r, fwd, paths), ("n", "path", *fwd)),
        ("composite", "Compositing gradients, max abs / max rel",
         lambda r: pivot(r, grad, paths), ("n", "path", *grad)),
        ("sampling", "Stratified sampling (t edges)",
         lambda r: [x for x in r if x["family"] == "stratified"],
         ("n", "n_rays", "path", "max_abs", "max_rel")),
        ("sampling", "Importance sampling (n coarse + n fine; t edges)",
         lambda r: [x for x in r if x["family"] == "importance"],
         ("n", "n_rays", "path", "max_abs", "max_rel")),
        ("encoding", "Hash encoding (n points per ray)", list,
         ("n", "points", "path", "quantity", "max_abs", "max_rel")),
        ("rays", "Rays", list,
         ("op", "n", "path", "quantity", "max_abs", "max_rel", "hit_mismatch")),
        ("march", "Occupancy marching (n = steps per box diagonal) vs the brute-force twin", list,
         MARCH_COLS),
        ("sphere_trace", "Sphere tracing (float32 kernel; n = max_iters), hit t error", list,
         SPHERE_COLS),
    ]  # fmt: skip
    parts = [
        f"device: {m['device_name']}; {m['date']}; cpu_blocks={m['cpu_blocks']}",
        "",
        f"NaN/Inf among the {m['values_checked']} kernel outputs and gradients compared: "
        f"{m['non_finite_values']}",
        "",
    ]
    for family, title, select, cols in sections:
        if t.get(family):
            parts += [f"{title}:", "", table(select(t[family]), cols), ""]
    return "\n".join(parts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--json", default=None, help="write the report here")
    ap.add_argument("--sizes", default=",".join(map(str, SIZES)))
    ap.add_argument("--budget", type=int, default=1 << 17, help="samples per size (rays x n)")
    ap.add_argument("--families", default=",".join(FAMILIES), help="subset to run")
    ap.add_argument(
        "--cpu-blocks",
        action="store_true",
        help="run the tiled kernels' multi-lane code on the CPU (as on a GPU)",
    )
    args = ap.parse_args(argv)
    if args.device == "cuda" and not torch.cuda.is_available():
        print("error: --device cuda but CUDA is not available", file=sys.stderr)
        return 2
    import warp as wp

    wp.config.enable_cpu_blocks = bool(args.cpu_blocks)
    dev = torch.device(args.device)
    sizes = [int(s) for s in args.sizes.split(",")]
    t0 = time.perf_counter()
    tables = {}
    runs = {
        "composite": lambda: composite_family(dev, sizes, args.budget),
        "sampling": lambda: sampling_family(dev, sizes, args.budget),
        "encoding": lambda: encoding_family(dev, sizes, args.budget),
        "rays": lambda: rays_family(dev),
        "march": lambda: march_family(dev, sizes),
        "sphere_trace": lambda: sphere_family(dev, sizes, (1e-4, 1e-6)),
    }
    for name in args.families.split(","):
        fn = runs[name]
        t = time.perf_counter()
        tables[name] = fn()
        print(f"[{name}: {time.perf_counter() - t:.1f} s]", file=sys.stderr, flush=True)
    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else cpu_name()
    report = {
        "meta": {
            "device": args.device,
            "device_name": f"{args.device} ({name})",
            "date": datetime.date.today().isoformat(),
            "command": "python3 scripts/numerics_report.py " + " ".join(argv or sys.argv[1:]),
            "torch": torch.__version__,
            "warp": wp.config.version,
            "cpu_blocks": bool(args.cpu_blocks),
            "seconds": round(time.perf_counter() - t0, 1),
            "values_checked": CHECKED["values"],
            "non_finite_values": CHECKED["non_finite"],
            "definitions": {
                "max_abs": "max |kernel - float64 twin| over all entries",
                "max_rel": "max_abs / max |float64 twin| (normwise)",
            },
        },
        "tables": tables,
    }
    print(markdown(report))
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        tmp = args.json + ".tmp"
        with open(tmp, "w") as f:
            json.dump(report, f, indent=1)
        os.replace(tmp, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
