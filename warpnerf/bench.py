"""``warpnerf bench``: kernels against their PyTorch twins, measured in the same run.

For each size: median time of the Warp op and of the pure-PyTorch twin (``warpnerf.reference``),
both float32, forward and forward+backward; throughput; the fewest bytes the op can move (each
input read once per pass, each output and gradient written once: :func:`composite_bytes`) over
the time, as GB/s and as a share of the device copy bandwidth measured in the same run; and the
max abs error of the Warp float32 outputs and gradients against the float64 twin on the same
inputs.
"""

from __future__ import annotations

import json
import platform
import statistics
import time

import torch

from . import reference
from .ops import render_packed, stratified_samples

__all__ = [
    "run_bench", "composite_bytes", "measure_copy_bandwidth", "KERNELS", "markdown_rows",
    "label_axes",
]  # fmt: skip

KERNELS = ("composite", "march", "encoding", "sphere-trace", "all")


def _sync(dev):
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _warp_vs_torch(row: dict, run, warp_fn, torch_fn, dev, repeats: int) -> None:
    """Adds the forward and forward+backward times (ms) of the Warp op and its PyTorch twin, and
    the speed-ups, to ``row``; ``run(fn, backward)`` returns the timed closure."""
    for name, fn in (("warp", warp_fn), ("torch", torch_fn)):
        row[f"{name}_fwd_ms"] = 1e3 * _time(run(fn, False), dev, repeats)
        row[f"{name}_fwdbwd_ms"] = 1e3 * _time(run(fn, True), dev, repeats)
    row["speedup_fwd"] = row["torch_fwd_ms"] / row["warp_fwd_ms"]
    row["speedup_fwdbwd"] = row["torch_fwdbwd_ms"] / row["warp_fwdbwd_ms"]


def _time(fn, dev, repeats: int, warmup: int = 2) -> float:
    """Median seconds of ``fn()`` over ``repeats`` runs (CUDA events on GPU)."""
    for _ in range(warmup):
        fn()
    _sync(dev)
    times = []
    for _ in range(repeats):
        if dev.type == "cuda":
            a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            a.record()
            fn()
            b.record()
            b.synchronize()
            times.append(a.elapsed_time(b) / 1e3)
        else:
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def measure_copy_bandwidth(dev, nbytes: int) -> float:
    """Device copy bandwidth in bytes/s, counting bytes read plus bytes written."""
    src = torch.rand(nbytes // 4, device=dev)
    dst = torch.empty_like(src)
    t = _time(lambda: dst.copy_(src), dev, repeats=10)
    return 2 * src.numel() * 4 / t


def composite_bytes(n_rays: int, n: int, backward: bool) -> int:
    """Fewest bytes float32 packed compositing can move (what "% copy BW" divides by).

    Forward: read t_starts, t_ends, sigmas, rgbs (24 B/sample) and packed_info (8 B/ray), write
    rgb, depth, opacity (20 B/ray). Backward: read the same inputs again (24 B/sample: autograd
    runs it later, nothing stays on chip) and packed_info, v_rgb, v_depth, v_opacity (28 B/ray),
    write v_sigmas, v_rgbs (16 B/sample). Forward+backward: 64 B/sample + 56 B/ray. Not counted:
    what an implementation saves for its backward (per-sample transmittance, per-ray totals; see
    :func:`composite_traffic`) and the shared [1, 3] background. (Before issue 47 this counted
    the per-sample transmittance too: 28 + 44 = 72 B/sample and 64 B/ray.)
    """
    fwd = 24 * n + 28 * n_rays
    bwd = 40 * n + 28 * n_rays
    return fwd + (bwd if backward else 0)


def composite_traffic(kind: str, n_rays: int, n: int, extra_chunks: int, backward: bool) -> int:
    """Bytes the kernels ``kind`` (``composite_kernels``) move in one call, estimated from their
    code at DRAM level: :func:`composite_bytes` plus what each saves for the backward and the
    gradients' zero-fill. All save T_m and n_eff (8 B/ray, written then read). ``tiled``: the
    optical depth at each chunk's first sample but the first (``extra_chunks`` floats, written
    then read); ``sequential``: the per-sample transmittance (4 B/sample written then read). (The
    issue-5 kernels, compared in issue 47's A/B, also had the bridge zero-fill v_sigmas and v_rgbs
    before their backward: 16 B/sample more; docs/design/kernels.md keeps the figures.)"""
    fwd = composite_bytes(n_rays, n, False) + 8 * n_rays
    bwd = composite_bytes(n_rays, n, True) - composite_bytes(n_rays, n, False) + 8 * n_rays
    if kind == "tiled":
        fwd, bwd = fwd + 4 * extra_chunks, bwd + 4 * extra_chunks
    else:
        fwd, bwd = fwd + 4 * n, bwd + 4 * n
    return fwd + (bwd if backward else 0)


# The compositing kernels compared (label, composite_kernels kind, block_dim): the default and
# one thread per ray. (The issue-5 kernels' row, composite_packed_v1, was removed with them after
# issue 47's A/B was measured on 2026-12-02; docs/design/kernels.md keeps the figures.)
COMPOSITE_VARIANTS = (
    ("composite_packed", "tiled", 32),
    ("composite_packed_seq", "sequential", 32),
)


def _composite_inputs(n_rays: int, n_samples: int, dev):
    g = torch.Generator(device="cpu").manual_seed(0)
    near = torch.full((n_rays,), 2.0, device=dev)
    far = torch.full((n_rays,), 6.0, device=dev)
    smp = stratified_samples(near, far, n_samples, perturb=True, seed=1, packed=True)
    n = smp.t_starts.shape[0]
    # Densities spread over five decades so rays range from transparent to opaque.
    sig_cpu = torch.exp(torch.empty(n).uniform_(-4.0, 4.0, generator=g)) * 0.3
    return {
        "smp": smp,
        "sigmas": sig_cpu.to(dev).requires_grad_(),
        "rgbs": torch.rand(n, 3, generator=g).to(dev).requires_grad_(),
        "bg": torch.tensor([1.0, 1.0, 1.0], device=dev),
        "v_rgb": torch.randn(n_rays, 3, generator=g).to(dev),
        "v_depth": torch.randn(n_rays, generator=g).to(dev),
    }


def _composite_case(n_rays: int, n_samples: int, dev, repeats: int, variants) -> list:
    """One row per variant of ``variants`` ((label, kind, block_dim)) at this size: its times,
    its errors against the float64 twin; the PyTorch twin's times (measured once) in each row.
    Timed as the library's renderers call it: ``render_packed(..., check=False)`` (the index
    check of ``check=True`` is timed alone, ``check_ms``)."""
    from .ops import composite as C

    c = _composite_inputs(n_rays, n_samples, dev)
    smp, sigmas, rgbs = c["smp"], c["sigmas"], c["rgbs"]
    n = smp.t_starts.shape[0]
    args = (smp.t_starts, smp.t_ends, smp.ray_indices)
    kw = {"background": c["bg"], "packed_info": smp.packed_info}

    def run(fn, backward, **extra):
        def go():
            rgb, depth, _ = fn(*args, sigmas, rgbs, n_rays, **kw, **extra)
            if backward:
                torch.autograd.backward((rgb, depth), (c["v_rgb"], c["v_depth"]))
                sigmas.grad = rgbs.grad = None

        return go

    twin = {}
    for name, backward in (("torch_fwd_ms", False), ("torch_fwdbwd_ms", True)):
        twin[name] = 1e3 * _time(run(reference.render_packed, backward), dev, repeats)
    check = lambda: C.check_packed_info(smp.packed_info, smp.ray_indices, n, n_rays)  # noqa: E731
    counts = smp.packed_info[:, 1].long()
    rows = []
    for label, kind, block in variants:
        chunk = 4 * block  # kernels/composite_tiled.py: SPL samples per lane
        extra_chunks = int(((counts + chunk - 1) // chunk - 1).clamp_min(0).sum())
        row = {"kernel": label, "n_rays": n_rays, "samples_per_ray": n_samples, "n_samples": n}
        with C.composite_kernels(kind, block):
            for name, backward in (("warp_fwd_ms", False), ("warp_fwdbwd_ms", True)):
                row[name] = 1e3 * _time(run(render_packed, backward, check=False), dev, repeats)
            row.update(_composite_errors(args, c, n_rays))
        row.update(twin)
        row["speedup_fwd"] = row["torch_fwd_ms"] / row["warp_fwd_ms"]
        row["speedup_fwdbwd"] = row["torch_fwdbwd_ms"] / row["warp_fwdbwd_ms"]
        row["check_ms"] = 1e3 * _time(check, dev, repeats)
        row["samples_per_s_fwdbwd"] = n / (row["warp_fwdbwd_ms"] / 1e3)
        row["bytes_fwd"] = composite_bytes(n_rays, n, False)
        row["bytes_fwdbwd"] = composite_bytes(n_rays, n, True)
        row["bytes_moved_fwdbwd"] = composite_traffic(kind, n_rays, n, extra_chunks, True)
        rows.append(row)
    return rows


def _composite_errors(args, c, n_rays: int) -> dict:
    """Max abs errors of the float32 op's outputs and gradients against the float64 twin."""
    kw = {"background": c["bg"], "packed_info": c["smp"].packed_info}
    sigmas, rgbs, up = c["sigmas"], c["rgbs"], (c["v_rgb"], c["v_depth"])
    rgb, depth, _ = render_packed(*args, sigmas, rgbs, n_rays, **kw, check=False)
    gs, gc = torch.autograd.grad((rgb, depth), (sigmas, rgbs), up)
    s64 = sigmas.detach().double().requires_grad_()
    c64 = rgbs.detach().double().requires_grad_()
    args64 = [a.double() if a.is_floating_point() else a for a in args]
    kw64 = {"background": c["bg"].double(), "packed_info": kw["packed_info"]}
    r64, d64, _ = reference.render_packed(*args64, s64, c64, n_rays, **kw64)
    gs64, gc64 = torch.autograd.grad((r64, d64), (s64, c64), [u.double() for u in up])

    def err(a, b):
        return float((a.detach().double() - b.detach()).abs().max())

    return {
        "max_err_rgb": err(rgb, r64),
        "max_err_depth": err(depth, d64),
        "max_err_v_sigmas": err(gs, gs64),
        "max_err_v_rgbs": err(gc, gc64),
    }


def encoding_bytes(n: int, grid, backward: bool) -> int:
    """Fewest bytes of the float32 hash encoding: forward reads positions (12 B/point) and the
    table once, writes L * F features (4 B each); backward reads positions and v_out, zeroes
    and writes v_table. The 8 corner gathers per level are random accesses on top of this (so the
    kernels are latency/gather bound, and this % of bandwidth is a lower bound on traffic)."""
    feat = 4 * grid.out_dim * n
    table = 4 * grid.n_rows * grid.n_features
    fwd = 12 * n + table + feat
    bwd = 12 * n + feat + 2 * table
    return fwd + (bwd if backward else 0)


def _encoding_case(n: int, grid, dev, repeats: int, points: str = "uniform"):
    from .ops.encoding import encoding_kernels, hash_encode
    from .reference.encoding import hash_encode as ref_encode

    g = torch.Generator(device="cpu").manual_seed(0)
    x = torch.rand(n, 3, generator=g)
    if points == "surface":  # as a training step's samples: near a surface, many per cell
        u = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
        x = 0.5 + u * (0.3 + 0.01 * torch.rand(n, 1, generator=g))
    x = x.to(dev)
    table = (torch.rand(grid.n_rows, grid.n_features, generator=g) * 2 - 1).to(dev)
    table.requires_grad_()
    v_out = torch.randn(n, grid.out_dim, generator=g).to(dev)

    def run(fn, backward):
        def go():
            out = fn(x, table, grid)
            if backward:
                out.backward(v_out)
                table.grad = None

        return go

    row = {"kernel": "hash_encode", "n_points": n, "levels": grid.n_levels, "rows": grid.n_rows,
           "points": points}  # fmt: skip
    _warp_vs_torch(row, run, hash_encode, ref_encode, dev, repeats)
    with encoding_kernels(pairs=False):  # the table's backward with one atomic per feature
        row["warp_fwdbwd_ms_single_atomics"] = 1e3 * _time(run(hash_encode, True), dev, repeats)
    row["points_per_s_fwdbwd"] = n / (row["warp_fwdbwd_ms"] / 1e3)
    row["bytes_fwd"] = encoding_bytes(n, grid, False)
    row["bytes_fwdbwd"] = encoding_bytes(n, grid, True)
    out = hash_encode(x, table, grid)
    (gt,) = torch.autograd.grad(out, table, v_out)
    t64 = table.detach().double().requires_grad_()
    o64 = ref_encode(x.double(), t64, grid)
    (gt64,) = torch.autograd.grad(o64, t64, v_out.double())
    row["max_err_out"] = float((out.detach().double() - o64.detach()).abs().max())
    row["max_err_v_table"] = float((gt.double() - gt64).abs().max())
    return row


def _encoding_grids(dev, quick: bool):
    from .ops.encoding import HashGrid

    if dev.type == "cuda":
        cases = [
            (1 << 18, HashGrid(), "uniform"),
            (1 << 20, HashGrid(), "uniform"),
            (1 << 20, HashGrid(log2_size=21), "uniform"),
            (1 << 19, HashGrid(), "surface"),
        ]
    else:
        cases = [
            (1 << 12, HashGrid(log2_size=14, max_res=256), "uniform"),
            (1 << 14, HashGrid(log2_size=14, max_res=256), "uniform"),
            (1 << 14, HashGrid(log2_size=14, max_res=256), "surface"),
        ]
    return cases[:1] if quick else cases


def _camera_rays(size: int, dev, radius: float = 4.0):
    """Rays of one size x size camera on a sphere of ``radius`` looking at the origin (lego's
    camera distance), fov 0.69 rad."""
    from .data.cameras import intrinsics_from_fov, look_at
    from .ops import generate_rays

    c2w = look_at((0.6 * radius, -0.64 * radius, 0.48 * radius)).to(dev)
    return generate_rays(c2w, intrinsics_from_fov(size, size, 0.69).to(dev), size, size)


def ball_bits(res: int, radius: float, dev):
    """Bitfield of the cells of a res^3 grid over [-1.5, 1.5]^3 whose centre lies in a ball."""
    from .ops.occupancy import grid_pack_bits

    c = (torch.arange(res, device=dev, dtype=torch.float32) + 0.5) / res * 3.0 - 1.5
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    inside = (x * x + y * y + z * z).reshape(-1) <= radius * radius
    return grid_pack_bits(inside.float(), 0.5)


def march_bytes(n_rays: int, n: int) -> int:
    """Fewest bytes of the two marching passes: each reads origins, directions, t_lo, t_hi
    (32 B/ray); the count pass writes counts and k_next (8 B/ray), the fill pass reads offsets
    (4 B/ray) and writes t_starts, t_ends, ray_indices (12 B/sample). Bitfield reads are cached."""
    return 2 * 32 * n_rays + 12 * n_rays + 12 * n


def _march_case(size: int, radius: float, res: int, dev, repeats: int):
    """Marching a size^2 camera through a res^3 grid whose occupied cells form a ball."""
    from .ops.occupancy import march_rays as uncut
    from .ops.occupancy import occupied_cells, unpack_bits
    from .reference.occupancy import march_rays as ref_march

    aabb = [-1.5, -1.5, -1.5, 1.5, 1.5, 1.5]
    dt = 3.0 * 3**0.5 / 1024
    o, d = _camera_rays(size, dev)
    bits = ball_bits(res, radius, dev)
    n_rays = o.shape[0]

    occ = occupied_cells(bits, res)

    def march_rays(o, d, *a):  # what a grid marches: each ray cut to the occupied cells' box
        return uncut(o, d, *a, occupied=occ)

    def run(fn):
        return lambda: fn(o, d, 2.0, 6.0, bits, res, aabb, dt)

    smp, _ = run(march_rays)()
    n = smp.t_starts.shape[0]
    row = {
        "kernel": "march",
        "n_rays": n_rays,
        "grid_res": res,
        "occupancy": float(unpack_bits(bits).float().mean()),
        "samples_per_ray": n / n_rays,
        "n_samples": n,
        "warp_ms": 1e3 * _time(run(march_rays), dev, repeats),
        "warp_ms_uncut": 1e3 * _time(run(uncut), dev, repeats),
    }
    twin_rays = 1 << 14  # the brute-force twin enumerates every lattice step (memory)
    sub = slice(0, n_rays, max(n_rays // twin_rays, 1))
    osub, dsub = o[sub].contiguous(), d[sub].contiguous()
    t_torch = _time(lambda: ref_march(osub, dsub, 2.0, 6.0, bits, res, aabb, dt), dev, 2, 1)
    row["torch_ms_scaled"] = 1e3 * t_torch * n_rays / osub.shape[0]
    row["speedup"] = row["torch_ms_scaled"] / row["warp_ms"]
    row["rays_per_s"] = n_rays / (row["warp_ms"] / 1e3)
    row["bytes"] = march_bytes(n_rays, n)
    # float32 kernel against the float64 brute force on the same rays: samples in a different
    # cell (rounding at cell boundaries) and the largest difference of matching samples.
    s32, _ = march_rays(osub, dsub, 2.0, 6.0, bits, res, aabb, dt)
    s64, _ = ref_march(osub.double(), dsub.double(), 2.0, 6.0, bits, res, aabb, dt)
    c32, c64 = s32.packed_info[:, 1].long(), s64.packed_info[:, 1].long()
    row["count_mismatch"] = int((c32 - c64).abs().sum())
    same = torch.repeat_interleave(c32 == c64, c32)
    same64 = torch.repeat_interleave(c32 == c64, c64)
    diff = (s32.t_starts[same].double() - s64.t_starts[same64]).abs()
    row["max_err_t"] = float(diff.max()) if diff.numel() else 0.0
    return row


def _sphere_trace_case(size: int, dev, repeats: int):
    """Sphere tracing the 32-primitive scene from one camera, against the torch twin."""
    from .fields.sdf_scene import many_primitives_scene
    from .ops.sphere_trace import sphere_trace
    from .reference.sphere_trace import sphere_trace as ref_trace

    scene = many_primitives_scene()
    o, d = _camera_rays(size, dev, radius=5.0)
    n = o.shape[0]
    row = {"kernel": "sphere_trace", "n_rays": n, "primitives": len(scene.primitives)}
    tr = sphere_trace(o, d, scene, 0.0, 12.0)
    row["evals_per_ray"] = float(tr.iters.float().mean())
    row["warp_ms"] = 1e3 * _time(lambda: sphere_trace(o, d, scene, 0.0, 12.0), dev, repeats)
    row["torch_ms"] = 1e3 * _time(lambda: ref_trace(o, d, scene, 0.0, 12.0), dev, 2, 1)
    row["speedup"] = row["torch_ms"] / row["warp_ms"]
    row["rays_per_s"] = n / (row["warp_ms"] / 1e3)
    # bytes: rays in (24 B), t, status, iters, points, normals, ids out (40 B); scene is cached
    row["bytes"] = 64 * n
    ref = ref_trace(o.double(), d.double(), scene, 0.0, 12.0)
    both = tr.hit & ref.hit
    row["status_mismatch"] = int((tr.status.long() != ref.status.long()).sum())
    row["max_err_t"] = float((tr.t[both].double() - ref.t[both]).abs().max()) if both.any() else 0
    return row


def _sizes(dev, quick: bool, rays=None, samples=None):
    """Compositing sizes (rays, samples per ray): the default list, or the one size given."""
    if rays is not None or samples is not None:
        default_rays = 1 << 20 if dev.type == "cuda" else 1 << 12
        return [(default_rays if rays is None else rays, 128 if samples is None else samples)]
    if dev.type == "cuda":
        sizes = [(1 << 14, 128), (1 << 17, 128), (1 << 20, 128)]
    else:
        sizes = [(1 << 10, 64), (1 << 12, 128)]
    return sizes[:1] if quick else sizes


def run_bench(
    kernel: str = "composite", device: str = "cpu", json_path=None, quick=False, rays=None,
    samples=None,
):  # fmt: skip
    """Runs the benchmark, prints a Markdown table and returns (and optionally writes) the JSON.
    ``rays``, ``samples``: one compositing size instead of the default list."""
    from .outputs import write_json

    dev = torch.device(device)
    if dev.type == "cuda":
        if dev.index is None:
            dev = torch.device("cuda", torch.cuda.current_device())
        torch.cuda.set_device(dev)
        name = torch.cuda.get_device_name(dev)
        bw = measure_copy_bandwidth(dev, 1 << 30)
    else:
        name = platform.processor() or platform.machine()
        bw = measure_copy_bandwidth(dev, 1 << 27)
    repeats = 20 if dev.type == "cuda" else 3
    rows = []
    if kernel in ("composite", "all"):
        for n_rays, n_s in _sizes(dev, quick, rays, samples):
            for row in _composite_case(n_rays, n_s, dev, repeats, COMPOSITE_VARIANTS):
                for part in ("fwd", "fwdbwd"):
                    rate = row[f"bytes_{part}"] / (row[f"warp_{part}_ms"] / 1e3)
                    row[f"GBps_{part}"] = rate / 1e9
                    row[f"bw_pct_{part}"] = 100 * rate / bw
                rows.append(row)
    if kernel in ("march", "all"):
        if dev.type == "cuda":
            cases = [(400, r, 128) for r in (0.25, 0.5, 0.8, 1.2, 3.0)] + [(800, 0.8, 128)]
        else:
            cases = [(100, r, 64) for r in (0.25, 0.8, 3.0)]
        for size, radius, res in cases[:2] if quick else cases:
            row = _march_case(size, radius, res, dev, repeats)
            row["bw_pct"] = 100 * row["bytes"] / (row["warp_ms"] / 1e3) / bw
            rows.append(row)
    if kernel in ("sphere-trace", "all"):
        for size in (
            ((400,) if dev.type == "cuda" else (64,))
            if quick
            else ((400, 800) if dev.type == "cuda" else (64, 128))
        ):
            row = _sphere_trace_case(size, dev, repeats)
            row["bw_pct"] = 100 * row["bytes"] / (row["warp_ms"] / 1e3) / bw
            rows.append(row)
    if kernel in ("encoding", "all"):
        for n, grid, points in _encoding_grids(dev, quick):
            row = _encoding_case(n, grid, dev, repeats, points)
            row["bw_pct_fwd"] = 100 * row["bytes_fwd"] / (row["warp_fwd_ms"] / 1e3) / bw
            row["bw_pct_fwdbwd"] = 100 * row["bytes_fwdbwd"] / (row["warp_fwdbwd_ms"] / 1e3) / bw
            rows.append(row)
    result = {
        "device": str(dev),
        "device_name": name,
        "torch": torch.__version__,
        "copy_bandwidth_GBps": bw / 1e9,
        "dtype": "float32 (errors against the float64 PyTorch twin)",
        "rows": rows,
    }
    print(markdown_table(result))
    if json_path:
        write_json(json_path, result, replace_foreign=True)  # the file the user named
    return result


_COMPOSITE_COLS = [
    ("rays x samples", lambda r: f"{r['n_rays']} x {r['samples_per_ray']}"),
    ("warp fwd ms", "{warp_fwd_ms:.3f}"),
    ("warp fwd+bwd ms", "{warp_fwdbwd_ms:.3f}"),
    ("torch fwd ms", "{torch_fwd_ms:.3f}"),
    ("torch fwd+bwd ms", "{torch_fwdbwd_ms:.3f}"),
    ("speedup fwd / fwd+bwd", "{speedup_fwd:.1f}x / {speedup_fwdbwd:.1f}x"),
    ("GB/s fwd / fwd+bwd", "{GBps_fwd:.4g} / {GBps_fwdbwd:.4g}"),
    ("% copy BW fwd / fwd+bwd", "{bw_pct_fwd:.1f} / {bw_pct_fwdbwd:.1f}"),
    ("B/sample moved fwd+bwd (est.)", lambda r: f"{r['bytes_moved_fwdbwd'] / r['n_samples']:.1f}"),
    ("max err rgb / v_sigmas (vs f64)", "{max_err_rgb:.1e} / {max_err_v_sigmas:.1e}"),
]


def _composite_notes(rows) -> list:
    """What the compositing table's bytes count, and the index check's time, per size."""
    lines = [
        "Bytes counted (composite_bytes, the fewest: inputs read once per pass, outputs and "
        "gradients written once): forward 24 B/sample + 28 B/ray, forward+backward 64 B/sample "
        "+ 56 B/ray; GB/s = those bytes / time, % copy BW = GB/s / copy bandwidth. Timed as the "
        "renderers call render_packed (check=False)."
    ]
    seen = set()
    for r in rows:
        key = (r["n_rays"], r["samples_per_ray"])
        if key in seen or "check_ms" not in r:
            continue
        seen.add(key)
        lines.append(
            f"{key[0]} x {key[1]}: {r['bytes_fwd'] / 1e9:.4g} GB forward, "
            f"{r['bytes_fwdbwd'] / 1e9:.4g} GB forward+backward; the index check of "
            f"check=True (not timed above): {r['check_ms']:.3f} ms"
        )
    return lines


_TABLES = {
    "composite": _COMPOSITE_COLS,
    "march": [
        ("rays", "{n_rays}"),
        ("grid", "{grid_res}^3"),
        ("occupancy", "{occupancy:.3f}"),
        ("samples/ray", "{samples_per_ray:.1f}"),
        ("warp ms (count+fill)", "{warp_ms:.3f}"),
        ("same, rays not cut to the occupied box", "{warp_ms_uncut:.3f}"),
        ("torch brute force ms (scaled)", "{torch_ms_scaled:.1f}"),
        ("speedup", "{speedup:.0f}x"),
        ("Mrays/s", lambda r: f"{r['rays_per_s'] / 1e6:.1f}"),
        ("% copy BW", "{bw_pct:.1f}"),
        ("count diff (sum over rays) / max t err (vs f64)", "{count_mismatch} / {max_err_t:.1e}"),
    ],
    "encoding": [
        ("points", lambda r: f"{r['n_points']} {r.get('points', 'uniform')}"),
        ("levels x rows", "{levels} x {rows}"),
        ("warp fwd ms", "{warp_fwd_ms:.3f}"),
        ("torch fwd ms", "{torch_fwd_ms:.3f}"),
        ("warp fwd+bwd ms", "{warp_fwdbwd_ms:.3f}"),
        (
            "same, one atomic per feature",
            lambda r: (
                f"{r['warp_fwdbwd_ms_single_atomics']:.3f}"
                if "warp_fwdbwd_ms_single_atomics" in r
                else "-"
            ),
        ),
        ("torch fwd+bwd ms", "{torch_fwdbwd_ms:.3f}"),
        ("speedup fwd / fwd+bwd", "{speedup_fwd:.1f}x / {speedup_fwdbwd:.1f}x"),
        ("Mpoints/s fwd+bwd", lambda r: f"{r['points_per_s_fwdbwd'] / 1e6:.1f}"),
        ("% copy BW fwd+bwd (lower bound)", "{bw_pct_fwdbwd:.1f}"),
        ("max err out / v_table (vs f64)", "{max_err_out:.1e} / {max_err_v_table:.1e}"),
    ],
    "sphere-trace": [
        ("rays", "{n_rays}"),
        ("primitives", "{primitives}"),
        ("evals/ray", "{evals_per_ray:.1f}"),
        ("warp ms", "{warp_ms:.3f}"),
        ("torch ms", "{torch_ms:.1f}"),
        ("speedup", "{speedup:.0f}x"),
        ("Mrays/s", lambda r: f"{r['rays_per_s'] / 1e6:.1f}"),
        ("% copy BW", "{bw_pct:.2f}"),
        ("status mismatches / max t err (vs f64)", "{status_mismatch} / {max_err_t:.1e}"),
    ],
}


def _family(row) -> str:
    k = row["kernel"]
    if k.startswith("composite"):
        return "composite"
    return {"hash_encode": "encoding", "sphere_trace": "sphere-trace"}.get(k, k)


def markdown_rows(rows, columns) -> str:
    """A Markdown table of ``rows`` (dicts): ``columns`` is a list of (header, cell), a cell a
    format string over the row's keys ("{psnr:.2f}") or a function of the row."""
    lines = ["| " + " | ".join(h for h, _ in columns) + " |", "|---" * len(columns) + "|"]
    for r in rows:
        cells = [f(r) if callable(f) else f.format(**r) for _, f in columns]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def label_axes(
    ax, xlabel: str, ylabel: str, title: str, legend: str = "lower right", minor: bool = True
) -> None:
    """The measuring tools' style of a matplotlib plot: labels, title, a light grid (on the
    minor ticks too when ``minor``) and a small legend at ``legend``."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, which="both" if minor else "major", alpha=0.3)
    ax.legend(fontsize=8, loc=legend)


def markdown_table(result) -> str:
    """One Markdown table per kernel family present in ``result["rows"]``."""
    lines = [
        f"Device: {result['device_name']} ({result['device']}), measured copy bandwidth "
        f"{result['copy_bandwidth_GBps']:.0f} GB/s (read+write)"
    ]
    for fam, cols in _TABLES.items():
        rows = [r for r in result["rows"] if _family(r) == fam]
        if not rows:
            continue
        lines += ["", markdown_rows(rows, [("kernel", "{kernel}"), *cols])]
        if fam == "composite":
            lines += ["", *_composite_notes(rows)]
    return "\n".join(lines)


if __name__ == "__main__":  # pragma: no cover
    print(json.dumps(run_bench(quick=True)["rows"], indent=1))
