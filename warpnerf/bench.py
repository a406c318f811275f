"""``warpnerf bench``: kernels against their PyTorch twins, measured in the same run.

For each size: median time of the Warp op and of the pure-PyTorch twin (``warpnerf.reference``),
both float32, forward and forward+backward; throughput in samples/s; bytes the Warp kernels must
move (each input read once, each output written once) over the measured device copy bandwidth;
and the max abs error of the Warp float32 outputs and gradients against the float64 twin on the
same inputs.
"""

from __future__ import annotations

import json
import platform
import statistics
import time

import torch

from . import reference
from .ops import render_packed, stratified_samples

__all__ = ["run_bench", "composite_bytes", "measure_copy_bandwidth"]


def _sync(dev):
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


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
    """Fewest bytes the float32 packed compositing kernels move.

    Forward: read t_starts, t_ends, sigmas, rgbs (24 B/sample) and packed_info (8 B/ray); write
    trans (4 B/sample), rgb, depth, opacity, n_eff (24 B/ray). Backward: read t_starts, t_ends,
    sigmas, rgbs, trans (28 B/sample) and packed_info, n_eff, v_rgb, v_depth, v_opacity
    (32 B/ray); write v_sigmas, v_rgbs (16 B/sample).
    """
    fwd = 28 * n + 32 * n_rays
    bwd = 44 * n + 32 * n_rays
    return fwd + (bwd if backward else 0)


def _composite_case(n_rays: int, n_samples: int, dev, repeats: int, check_error: bool):
    g = torch.Generator(device="cpu").manual_seed(0)
    near = torch.full((n_rays,), 2.0, device=dev)
    far = torch.full((n_rays,), 6.0, device=dev)
    smp = stratified_samples(near, far, n_samples, perturb=True, seed=1, packed=True)
    n = smp.t_starts.shape[0]
    # Densities spread over five decades so rays range from transparent to opaque.
    sig_cpu = torch.exp(torch.empty(n).uniform_(-4.0, 4.0, generator=g)) * 0.3
    sigmas = sig_cpu.to(dev).requires_grad_()
    rgbs = torch.rand(n, 3, generator=g).to(dev).requires_grad_()
    bg = torch.tensor([1.0, 1.0, 1.0], device=dev)
    v_rgb = torch.randn(n_rays, 3, generator=g).to(dev)
    v_depth = torch.randn(n_rays, generator=g).to(dev)
    args = (smp.t_starts, smp.t_ends, smp.ray_indices)
    kw = {"background": bg, "packed_info": smp.packed_info}

    def run(fn, backward):
        def go():
            rgb, depth, _ = fn(*args, sigmas, rgbs, n_rays, **kw)
            if backward:
                torch.autograd.backward((rgb, depth), (v_rgb, v_depth))
                sigmas.grad = rgbs.grad = None

        return go

    row = {"n_rays": n_rays, "samples_per_ray": n_samples, "n_samples": n}
    for name, fn in (("warp", render_packed), ("torch", reference.render_packed)):
        row[f"{name}_fwd_ms"] = 1e3 * _time(run(fn, False), dev, repeats)
        row[f"{name}_fwdbwd_ms"] = 1e3 * _time(run(fn, True), dev, repeats)
    row["speedup_fwd"] = row["torch_fwd_ms"] / row["warp_fwd_ms"]
    row["speedup_fwdbwd"] = row["torch_fwdbwd_ms"] / row["warp_fwdbwd_ms"]
    row["samples_per_s_fwdbwd"] = n / (row["warp_fwdbwd_ms"] / 1e3)
    row["bytes_fwd"] = composite_bytes(n_rays, n, False)
    row["bytes_fwdbwd"] = composite_bytes(n_rays, n, True)
    if check_error:
        rgb, depth, _ = render_packed(*args, sigmas, rgbs, n_rays, **kw)
        gs, gc = torch.autograd.grad((rgb, depth), (sigmas, rgbs), (v_rgb, v_depth))
        s64 = sigmas.detach().double().requires_grad_()
        c64 = rgbs.detach().double().requires_grad_()
        r64, d64, _ = reference.render_packed(
            *(a.double() if a.is_floating_point() else a for a in args),
            s64,
            c64,
            n_rays,
            background=bg.double(),
            packed_info=smp.packed_info,
        )
        gs64, gc64 = torch.autograd.grad((r64, d64), (s64, c64), (v_rgb.double(), v_depth.double()))

        def err(a, b):
            return float((a.detach().double() - b.detach()).abs().max())

        row["max_err_rgb"] = err(rgb, r64)
        row["max_err_depth"] = err(depth, d64)
        row["max_err_v_sigmas"] = err(gs, gs64)
        row["max_err_v_rgbs"] = err(gc, gc64)
    return row


def _sizes(dev, quick: bool):
    if dev.type == "cuda":
        sizes = [(1 << 14, 128), (1 << 17, 128), (1 << 20, 128)]
    else:
        sizes = [(1 << 10, 64), (1 << 12, 128)]
    return sizes[:1] if quick else sizes


def run_bench(kernel: str = "composite", device: str = "cpu", json_path=None, quick=False):
    """Runs the benchmark, prints a Markdown table and returns (and optionally writes) the JSON."""
    from .io import write_json

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
        from .ops import composite as C

        # The default float32 path (cooperative kernels, one block of 32 lanes per ray), a wider
        # block, and the one-thread-per-ray kernels, each against the PyTorch twin.
        variants = [("composite_packed", "tiled", 32), ("composite_packed_seq", "sequential", 32)]
        if dev.type == "cuda":
            variants.insert(1, ("composite_packed_b128", "tiled", 128))
        saved = dict(C._IMPL)
        try:
            for n_rays, n_s in _sizes(dev, quick):
                for label, impl, block in variants:
                    C._IMPL.update(float32_sigma=impl, block_dim=block)
                    row = _composite_case(n_rays, n_s, dev, repeats, check_error=True)
                    row["kernel"] = label
                    row["bw_pct_fwd"] = 100 * row["bytes_fwd"] / (row["warp_fwd_ms"] / 1e3) / bw
                    row["bw_pct_fwdbwd"] = (
                        100 * row["bytes_fwdbwd"] / (row["warp_fwdbwd_ms"] / 1e3) / bw
                    )
                    rows.append(row)
        finally:
            C._IMPL.update(saved)
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
        write_json(json_path, result)
    return result


def markdown_table(result) -> str:
    head = (
        f"Device: {result['device_name']} ({result['device']}), measured copy bandwidth "
        f"{result['copy_bandwidth_GBps']:.0f} GB/s (read+write)\n\n"
        "| kernel | rays x samples | warp fwd ms | torch fwd ms | warp fwd+bwd ms | "
        "torch fwd+bwd ms | speedup fwd / fwd+bwd | Gsamples/s fwd+bwd | % copy BW fwd+bwd | "
        "max err rgb / v_sigmas (vs f64) |\n|---|---|---|---|---|---|---|---|---|---|"
    )
    lines = [head]
    for r in result["rows"]:
        lines.append(
            f"| {r['kernel']} | {r['n_rays']} x {r['samples_per_ray']} | {r['warp_fwd_ms']:.3f} | "
            f"{r['torch_fwd_ms']:.3f} | {r['warp_fwdbwd_ms']:.3f} | {r['torch_fwdbwd_ms']:.3f} | "
            f"{r['speedup_fwd']:.1f}x / {r['speedup_fwdbwd']:.1f}x | "
            f"{r['samples_per_s_fwdbwd'] / 1e9:.3f} | {r['bw_pct_fwdbwd']:.1f} | "
            f"{r['max_err_rgb']:.1e} / {r['max_err_v_sigmas']:.1e} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":  # pragma: no cover
    print(json.dumps(run_bench(quick=True)["rows"], indent=1))
