"""Speed against error on a trained grid run: val PSNR, render time per frame and samples per ray
for several marching steps (run on the GPU; writes JSON), and the PNG from that JSON (locally).

    python3 scripts/speed_vs_error.py sweep RUN OUT.json [--images 5] [--chunk 400000]
    python3 scripts/speed_vs_error.py plot OUT.json --png docs/speed_vs_error.png \
        --curves docs/data/grid/lego_grid_300s_history.json=grid ...
"""

from __future__ import annotations

import argparse
import json
import math

from warpnerf.bench import label_axes
from warpnerf.outputs import atomic_path, write_json


def sweep(run, out, images, chunk, divisors):
    from warpnerf.train.nerf_eval import evaluate_run

    rows = []
    for div in divisors:
        step = 3.0 * math.sqrt(3.0) / div
        m = evaluate_run(run, "val", max_images=images, chunk=chunk, march_step=step,
                         out_dir=f"/tmp/sweep_{div}")  # fmt: skip
        rows.append({"steps_per_diagonal": div, "march_step": step, "psnr": m["psnr"],
                     "ssim": m["ssim"], "render_ms": m["render_ms_median"]})  # fmt: skip
        print(json.dumps(rows[-1]), flush=True)
    write_json(out, {"run": str(run), "images": images, "rows": rows})


def plot(paths, png, curves=()):
    """Left: render time vs val PSNR per marching step (one JSON per line, optional extra points
    under "points"). Right (when ``curves`` are history JSONs): val PSNR against training time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2 if curves else 1, figsize=(11 if curves else 6.4, 4.2))
    ax = axes[0] if curves else axes
    for p in paths:
        d = json.load(open(p))
        rows = d["rows"]
        xs, ys = [r["render_ms"] for r in rows], [r["psnr"] for r in rows]
        ax.plot(xs, ys, "o-", label=d.get("label", "grid marching: steps per box diagonal"))
        for r in rows:
            ax.annotate(str(r["steps_per_diagonal"]), (r["render_ms"], r["psnr"]),
                        textcoords="offset points", xytext=(4, -10), fontsize=8)  # fmt: skip
        for pt in d.get("points", []):
            ax.plot([pt["render_ms"]], [pt["psnr"]], "s", label=pt["label"])
    ax.axvline(10.0, color="gray", ls=":", lw=1)
    ax.set_xscale("log")
    label_axes(
        ax,
        "render time per 400x400 frame (ms, H100, median)",
        "val PSNR (dB)",
        "lego, hash field: render speed against error",
        "lower right",
    )
    if curves:
        ax = axes[1]
        for c in curves:
            path, label = c.split("=", 1) if "=" in c else (c, c)
            h = json.load(open(path))
            ax.plot(h["val_seconds"], h["val_psnr"], "o-", label=label)
        ax.axhline(33.0, color="gray", ls=":", lw=1)
        ax.axhline(35.0, color="gray", ls=":", lw=1)
        label_axes(
            ax,
            "training time (s, H100; validation excluded)",
            "val PSNR during training (dB, 2 images)",
            "lego 400x400, hash field: with and without the grid",
            "lower right",
            minor=False,
        )
    fig.tight_layout()
    with atomic_path(png) as tmp:
        fig.savefig(tmp, dpi=110)


def main():
    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("sweep")
    s.add_argument("run")
    s.add_argument("out")
    s.add_argument("--images", type=int, default=5)
    s.add_argument("--chunk", type=int, default=400000)
    s.add_argument("--divisors", default="128,256,512,1024,2048")
    q = sub.add_parser("plot")
    q.add_argument("json", nargs="+")
    q.add_argument("--png", required=True)
    q.add_argument("--curves", nargs="*", default=(), help="history.json[=label] files")
    a = p.parse_args()
    if a.cmd == "sweep":
        sweep(a.run, a.out, a.images, a.chunk, [int(x) for x in a.divisors.split(",")])
    else:
        plot(a.json, a.png, a.curves)


if __name__ == "__main__":
    main()
