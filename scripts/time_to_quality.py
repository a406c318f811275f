"""Time to quality: a run trained with ``--snapshots`` evaluated at each snapshot (all val images by
default), as a table (JSON + Markdown) and a plot of val PSNR (and, for SDF runs with a geometric
reference, Chamfer distance) against training seconds.

    warpnerf train volsdf --data lego --field hash_sdf ... --snapshots 15,30,60,120,300 \
        --max-seconds 300 --out RUN
    python scripts/time_to_quality.py eval RUN OUT.json [--label L] [--images 0] [--chunk 400000]
        [--spp 1,4]
        [--geometry materials] [--mesh-resolution 384]
    python scripts/time_to_quality.py plot OUT.json [OUT2.json ...] --png docs/x.png [--title T]
    python scripts/time_to_quality.py run DIR [--budgets 5,15,30,60,120,300] [--label L]
        [--geometry materials] -- train nerf --data ../shared/data/lego --field hash --device cuda
        (trains DIR/run with --snapshots BUDGETS --max-seconds max(BUDGETS), then eval and plot:
        DIR/ttq.json, the table on stdout, DIR/ttq.png)

Why one run: the learning-rate, beta and grid schedules are functions of the step, so the state at
the snapshot taken when the training time first reaches S seconds is the state a run stopped by
``--max-seconds S`` ends with (up to the step that crosses S); the training time counts kernel
compilation and the grid's warm-up, and excludes validation and snapshot writing.
"""

from __future__ import annotations

import json
import re
import tempfile
from pathlib import Path

from warpnerf.bench import label_axes
from warpnerf.outputs import atomic_path, write_json
from warpnerf.train.step_times import step_times


def snapshots(run) -> list:
    """Seconds of the run's snapshots, sorted."""
    pat = re.compile(r"^t([0-9.e+-]+)s\.pt$")
    out = []
    for p in (Path(run) / "snapshots").glob("t*s.pt"):
        m = pat.match(p.name)
        if m:
            out.append(float(m.group(1)))
    return sorted(out)


def evaluate(run, out, label, images, chunk, geometry, mesh_resolution, spp=(None,)):
    """Each snapshot scored on the val split; ``spp``: rays a pixel of each scoring (`eval
    --spp`; None: the run's), the first gives ``psnr``/``ssim`` (and ``spp``), each other N adds
    ``psnr_sppN``/``ssim_sppN``/``render_ms_median_sppN``."""
    from warpnerf.train.nerf import load_run
    from warpnerf.train.nerf_eval import evaluate_geometry, evaluate_run

    rows = []
    for s in snapshots(run):
        cfg, _, ckpt = load_run(run, snapshot=s)
        h = ckpt["history"]
        row = {"budget_s": s, "step": ckpt["step"], "train_seconds": h["seconds"][-1]}
        # where the training time went, step by step (the gap between a profiled step and a
        # run's mean: grid updates, checkpoints, new captured shapes)
        grid_every = int(getattr(cfg, "grid_every", 0) or 0) if getattr(cfg, "grid_res", 0) else 0
        row["step_times"] = step_times(h["seconds"], grid_every,
                                       int(getattr(cfg, "ckpt_every", 0) or 0))  # fmt: skip
        if "beta" in h and h["beta"]:
            row["beta"] = h["beta"][-1]
        for k, n in enumerate(spp):
            with tempfile.TemporaryDirectory() as tmp:
                m = evaluate_run(run, "val", max_images=images, out_dir=tmp, snapshot=s,
                                 chunk=chunk, spp=n)  # fmt: skip
            if k == 0:
                row.update(psnr=m["psnr"], ssim=m["ssim"], images=m["n_images"], spp=m["spp"],
                           render_ms_median=m["render_ms_median"])  # fmt: skip
            else:
                ns = m["spp"]
                row.update({f"psnr_spp{ns}": m["psnr"], f"ssim_spp{ns}": m["ssim"],
                            f"render_ms_median_spp{ns}": m["render_ms_median"]})  # fmt: skip
        if geometry:
            g = evaluate_geometry(run, geometry, mesh_resolution, snapshot=s)
            row.update({k: g[k] for k in g if k not in ("run", "reference")})
        rows.append(row)
        print(json.dumps(row), flush=True)
    write_json(out, {"run": str(run), "label": label or str(run), "rows": rows,
                     "geometry": geometry})  # fmt: skip
    for r in rows:  # the step times (train/step_times.py), a line a snapshot
        st = r["step_times"]
        if st.get("steps"):
            ex = ", ".join(f"{k} {v:.2f}" for k, v in st["excess_ms_per_step"].items())
            print(f"steps to {r['budget_s']:g} s: mean {st['mean_ms']:.2f} ms, median "
                  f"{st['median_ms']:.2f}, p99 {st['p99_ms']:.1f}; the mean's excess (ms a step): "
                  f"{ex}")  # fmt: skip
    md = ["| training s | steps | val PSNR | val SSIM | frame ms |"
          + (" Chamfer | accuracy | completeness |" if geometry else ""),
          "|---|---|---|---|---|" + ("---|---|---|" if geometry else "")]  # fmt: skip
    for r in rows:
        line = (f"| {r['budget_s']:g} | {r['step']} | {r['psnr']:.2f} | {r['ssim']:.4f} | "
                f"{r['render_ms_median']:.1f} |")  # fmt: skip
        if geometry:
            line += f" {r['chamfer']:.4f} | {r['accuracy']:.4f} | {r['completeness']:.4f} |"
        md.append(line)
    print("\n".join(md))


def plot(paths, png, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = [json.load(open(p)) for p in paths]
    geo = any(d.get("geometry") for d in data)
    fig, axes = plt.subplots(1, 2 if geo else 1, figsize=(11 if geo else 6.4, 4.2))
    ax = axes[0] if geo else axes
    colors = [f"C{i}" for i in range(len(data))]  # one colour per run in both panels
    ticks = sorted({r["budget_s"] for d in data for r in d["rows"]})

    def log_x(ax):
        ax.set_xscale("log")
        ax.set_xticks(ticks, [f"{t:g}" for t in ticks])
        ax.minorticks_off()

    for d, c in zip(data, colors):
        rows = d["rows"]
        ax.plot([r["budget_s"] for r in rows], [r["psnr"] for r in rows], "o-", color=c,
                label=d["label"])  # fmt: skip
    log_x(ax)
    label_axes(
        ax,
        "training seconds (wall clock, compilation and grid warm-up included)",
        "val PSNR (dB)",
        title,
        "lower right",
    )
    if geo:
        ax = axes[1]
        delivered = any("chamfer" in (r.get("delivered") or {}) for d in data for r in d["rows"])
        for d, c in zip(data, colors):  # the delivered mesh (solid) where measured, and the
            # raw level set (dashed, unlabelled: the run's colour says which)
            labelled = False
            rows = [r for r in d["rows"] if "chamfer" in (r.get("delivered") or {})]
            if rows:
                labelled = True
                ax.plot([r["budget_s"] for r in rows], [r["delivered"]["chamfer"] for r in rows],
                        "o-", color=c, label=d["label"])  # fmt: skip
            rows = [r for r in d["rows"] if "chamfer" in r]
            if rows:
                ax.plot([r["budget_s"] for r in rows], [r["chamfer"] for r in rows], "o--",
                        color=c, alpha=0.5, label=None if labelled else d["label"])  # fmt: skip
        log_x(ax)
        ax.set_yscale("log")
        label_axes(
            ax,
            "training seconds",
            "mesh Chamfer distance (world units)",
            "delivered mesh (solid), raw level set (dashed)"
            if delivered
            else "geometry against the analytic shapes",
            "upper right",
        )
    fig.tight_layout()
    with atomic_path(png) as tmp:
        fig.savefig(tmp, dpi=110, format="png")


def train_and_evaluate(out_dir, budgets, train_argv, label, images, chunk, geometry, res,
                       spp=(None,)):  # fmt: skip
    """One training with snapshots at ``budgets`` (its last one the time limit), then
    :func:`evaluate` and :func:`plot` into ``out_dir``."""
    from warpnerf.cli.parser import main as cli
    from warpnerf.train.loop import parse_snapshots

    secs = parse_snapshots(budgets)
    if not train_argv or train_argv[0] != "train":
        raise SystemExit("after --, give a `warpnerf train ...` command line (e.g. train nerf ...)")
    run = Path(out_dir) / "run"
    # --iters 100000 (the learning rate decays over it) unless the command line says otherwise,
    # as in the documented GPU runs; the time limit is the last budget
    snaps = ",".join(f"{t:g}" for t in secs)
    argv = [*train_argv[:2], "--iters", "100000", *train_argv[2:], "--out", str(run),
            "--snapshots", snaps, "--max-seconds", f"{max(secs):g}"]  # fmt: skip
    if cli(argv) != 0:
        raise SystemExit(f"training failed: warpnerf {' '.join(argv)}")
    js = Path(out_dir) / "ttq.json"
    evaluate(run, js, label, images, chunk, geometry, res, spp)
    plot([js], Path(out_dir) / "ttq.png", label or "val PSNR against training time")


def main():

    from warpnerf.cli.parser import tool_parser

    p, sub, argv, train_argv = tool_parser(__doc__)
    r = sub.add_parser("run")
    r.add_argument("dir")
    r.add_argument("--budgets", default="5,15,30,60,120,300")
    e = sub.add_parser("eval")
    e.add_argument("run")
    e.add_argument("out")
    for q in (r, e):  # how the snapshots are scored
        q.add_argument("--label", default=None)
        q.add_argument("--images", type=int, default=0, help="val images (0: all)")
        q.add_argument("--chunk", type=int, default=None)
        q.add_argument("--geometry", default=None, help="SDF runs: materials or a point cloud")
        q.add_argument("--mesh-resolution", type=int, default=384)
        q.add_argument("--spp", default="run", help="rays a pixel of each scoring, a comma list "
                       "(run: the run's --train-spp; 1,4: psnr_spp4 too)")  # fmt: skip
    q = sub.add_parser("plot")
    q.add_argument("json", nargs="+")
    q.add_argument("--png", required=True)
    q.add_argument("--title", default="val PSNR against training time")
    a = p.parse_args(argv)
    spp = ()
    if a.cmd in ("run", "eval"):
        try:
            spp = tuple(None if x == "run" else int(x) for x in a.spp.split(","))
        except ValueError:
            raise SystemExit(f"--spp: a comma list of integers, got {a.spp!r}") from None
    if a.cmd == "run":
        train_and_evaluate(a.dir, a.budgets, train_argv, a.label, a.images, a.chunk, a.geometry,
                           a.mesh_resolution, spp)  # fmt: skip
    elif a.cmd == "eval":
        evaluate(a.run, a.out, a.label, a.images, a.chunk, a.geometry, a.mesh_resolution, spp)
    else:
        plot(a.json, a.png, a.title)


if __name__ == "__main__":
    main()
