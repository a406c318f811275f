"""Val PSNR against training time from NeRF runs' history.json files: a PNG and a Markdown table.

python scripts/plot_nerf_curves.py docs/data/lego_seed_history.json:"seed-like" ... --out x.png
"""

from __future__ import annotations

import argparse
import json


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="+", help="HISTORY_JSON:LABEL")
    p.add_argument("--out", required=True)
    p.add_argument("--title", default="lego val PSNR (2 val images) vs training time, H100")
    args = p.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=120)
    print("| run | step | training s | val PSNR (2 images) |\n|---|---|---|---|")
    for spec in args.runs:
        path, label = spec.rsplit(":", 1)
        h = json.load(open(path))
        secs = {s: t for s, t in zip(h["step"], h["seconds"])}
        xs = [secs[s] for s in h["val_step"]]
        ax.plot(xs, h["val_psnr"], marker="o", ms=3, label=label)
        for s, x, v in zip(h["val_step"], xs, h["val_psnr"]):
            print(f"| {label} | {s} | {x:.0f} | {v:.2f} |")
    ax.set_xlabel("training time (s, validation excluded)")
    ax.set_ylabel("val PSNR (dB)")
    ax.set_title(args.title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    from warpnerf.outputs import atomic_path

    with atomic_path(args.out) as tmp:
        fig.savefig(tmp)


if __name__ == "__main__":
    main()
