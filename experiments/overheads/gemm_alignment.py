"""Issue 47: do the fields' first MLP layers pay for an input width that is not a multiple of 4?
hash_sdf's SDF network reads 3 + 32 = 35 columns and its colour network 3 + 15 + 16 = 34, the
NeRF hash field's colour network 15 + 16 = 31; in a surface frame's profile (H200, 2026-12-03,
docs/design/training.md "Issue 47, seventh round") one TF32 GEMM ran cuBLAS's ``align1``
kernel (2.2 ms a frame), the one a leading dimension that is no multiple of 16 bytes gets. This
times each layer's forward + backward as the fields run it (the concatenation of its inputs,
then the Linear) against the same with zero columns concatenated up to the next multiple of
``--align`` and the weight padded with zero columns per call (the same outputs: the checkpoint's
shapes need not change), alternating in one process.

    python experiments/overheads/gemm_alignment.py [--device cuda] [--rows 262144] [--json F]
"""

from __future__ import annotations

import argparse
import json
import statistics

import torch
import torch.nn.functional as F

from warpnerf.bench import _time  # median seconds (CUDA events on a GPU)

# (name, widths of the concatenated inputs, the layer's outputs)
LAYERS = (
    ("hash_sdf sdf_mlp[0]", (3, 32), 64),
    ("hash_sdf color_mlp[0]", (3, 15, 16), 64),
    ("hash nerf color[0]", (15, 16), 64),
)


def _layer(parts, w, b, pad: int):
    x = torch.cat([*parts, parts[0].new_zeros(parts[0].shape[0], pad)] if pad else parts, -1)
    return F.linear(x, F.pad(w, (0, pad)) if pad else w, b)


def measure(device: str, rows: int, align: int, repeat: int) -> dict:
    dev = torch.device(device)
    torch.backends.cuda.matmul.allow_tf32 = True  # (the GPU preset's --tf32)
    torch.manual_seed(0)
    res = {"device": device, "rows": rows, "align": align, "repeat": repeat, "layers": {}}
    if dev.type == "cuda":
        res["gpu"] = torch.cuda.get_device_name(dev)
    for name, widths, out in LAYERS:
        k = sum(widths)
        pad = -k % align
        parts = [torch.randn(rows, c, device=dev, requires_grad=True) for c in widths]
        w = torch.randn(out, k, device=dev, requires_grad=True)
        b = torch.zeros(out, device=dev, requires_grad=True)
        g = torch.randn(rows, out, device=dev)
        y0, y1 = _layer(parts, w, b, 0), _layer(parts, w, b, pad)
        err = (y0 - y1).abs().max().item()

        def step(p, parts=parts, w=w, b=b, g=g):
            for t in (*parts, w, b):
                t.grad = None
            _layer(parts, w, b, p).backward(g)

        ms = {0: [], pad: []}
        for _ in range(3):  # warm, then alternate
            step(0), step(pad)
        for _ in range(5):
            for p in (0, pad):
                ms[p].append(1e3 * _time(lambda p=p: step(p), dev, repeat, warmup=0))
        a, z = statistics.median(ms[0]), statistics.median(ms[pad])
        res["layers"][name] = {"width": k, "padded_width": k + pad, "ms": a, "ms_padded": z,
                               "ratio": z / a, "max_abs_diff": err}  # fmt: skip
        print(f"{name}: width {k} {a:.3f} ms, padded to {k + pad} {z:.3f} ms ({z / a:.2f}x), "
              f"outputs differ by {err:.1e}")  # fmt: skip
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--rows", type=int, default=1 << 18)
    ap.add_argument("--align", type=int, default=4, help="pad the width to a multiple of this")
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    res = measure(a.device, a.rows, a.align, a.repeat)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
