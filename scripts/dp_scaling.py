"""Data-parallel scaling (issue 21): one GPU against several, same total batch and a larger one,
as throughput and as val PSNR against wall-clock seconds.

    python3 scripts/dp_scaling.py run OUT --name lego --budgets 15,30,60 \
        --configs 1x262144,2x262144,2x524288 -- --data .gpu/lego --field hash --device cuda \
        --tf32 --batch 4096
    python3 scripts/dp_scaling.py report OUT/scaling_lego.json [--png docs/x.png]

Each config ``GxT`` trains once (``G`` processes, one GPU each, launched through
``torch.distributed.run`` when G > 1; ``--target-samples T``, the global batch's samples per step)
with snapshots at the budgets and ``--max-seconds`` the last one. The configs run one after the
other, alone on the machine, and only once all have trained are their snapshots scored (every
val image, ``scripts/time_to_quality.py eval``; ``--eval-parallel N`` scorers at a time, one GPU
each), so scoring never shares the machine with a timed training.

Throughput is read from each run's ``history.json`` over the window from ``--skip`` seconds
(kernel compilation, the grid's warm-up) to the end: steps/s, rays/s (the global batch's rays)
and samples/s (the global batch's samples after the grid's pruning). Scaling efficiency of a
G-GPU config against the 1-GPU config with the same per-GPU batch (T/G) is
``samples/s(G) / (G x samples/s(1))``; the speed-up at the same total batch is
``samples/s(G, T) / samples/s(1, T)``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def parse_configs(text: str) -> list:
    """[(gpus, target_samples)] from "1x262144,2x262144"."""
    out = []
    for part in text.split(","):
        g, _, t = part.strip().partition("x")
        if not g.isdigit() or not t.isdigit() or int(g) < 1 or int(t) < 1:
            raise SystemExit(
                f"--configs: expected GPUSxSAMPLES items such as 2x262144, got {part!r}"
            )
        out.append((int(g), int(t)))
    return out


def tag(name: str, gpus: int, samples: int) -> str:
    return f"{name}_g{gpus}_s{samples}"


def env_for(gpus: int) -> dict:
    """The environment of a training: NVLink multicast kept off (the device machines' rule)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1", NCCL_NVLS_ENABLE="0",
               TORCH_SYMM_MEM_DISABLE_MULTICAST="1", NVSHMEM_DISABLE_NVLS="1")  # fmt: skip
    env.setdefault("OMP_NUM_THREADS", "4")
    return env


def train_command(gpus: int, samples: int, budgets: str, run: Path, flags: list) -> list:
    secs = [float(b) for b in budgets.split(",")]
    train = ["-m", "warpnerf.cli", "train", "nerf", *flags, "--iters", "100000",
             "--target-samples", str(samples), "--snapshots", budgets,
             "--max-seconds", f"{max(secs):g}", "--val-images", "0", "--quiet",
             "--no-tensorboard", "--out", str(run)]  # fmt: skip
    if gpus == 1:
        return [sys.executable, *train]
    return [sys.executable, "-m", "torch.distributed.run", "--standalone",
            f"--nproc-per-node={gpus}", *train]  # fmt: skip


def throughput(history: dict, skip: float) -> dict:
    """Steps/s, rays/s and samples/s of a run's history over seconds (skip, end]."""
    sec, batch, spr = history["seconds"], history.get("batch"), history.get("samples_per_ray")
    if not sec:
        return {}
    end = sec[-1]
    lo = skip if end > 2 * skip else 0.5 * end  # (a short run: its second half)
    first = next(i for i, s in enumerate(sec) if s > lo)  # steps after index first-1
    t0 = sec[first - 1] if first > 0 else 0.0
    n = len(sec) - first
    out = {"window_s": [t0, end], "steps": len(sec), "train_seconds": end,
           "steps_per_s": n / max(end - t0, 1e-9)}  # fmt: skip
    if batch and spr and len(batch) == len(sec):
        rays = sum(batch[first:])
        samples = sum(b * s for b, s in zip(batch[first:], spr[first:]))
        out.update(rays_per_s=rays / max(end - t0, 1e-9),
                   samples_per_s=samples / max(end - t0, 1e-9),
                   mean_rays_per_step=rays / max(n, 1),
                   mean_samples_per_step=samples / max(n, 1))  # fmt: skip
    return out


def run_all(a, flags: list) -> None:
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    configs = parse_configs(a.configs)
    done = []
    for gpus, samples in configs:
        t = tag(a.name, gpus, samples)
        run = out / t
        cmd = train_command(gpus, samples, a.budgets, run, flags)
        print(f"== {t}: {' '.join(cmd)}", flush=True)
        t0 = time.perf_counter()
        with open(out / f"{t}.log", "w") as log:
            rc = subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT, env=env_for(gpus))
        wall = time.perf_counter() - t0
        tail = (out / f"{t}.log").read_text(errors="replace")[-1500:]
        print(f"   exit {rc} after {wall:.0f} s wall\n{tail[-400:]}", flush=True)
        done.append({"tag": t, "gpus": gpus, "target_samples": samples, "exit": rc,
                     "process_wall_s": wall})  # fmt: skip
    # scoring, once every timed training is over
    pending = [d for d in done if d["exit"] == 0]
    procs = []
    for i, d in enumerate(pending):
        if len(procs) >= a.eval_parallel:
            procs.pop(0).wait()
        env = env_for(1)
        env["CUDA_VISIBLE_DEVICES"] = str(i % a.eval_parallel)
        gpus = f"{d['gpus']} GPU{'s' if d['gpus'] > 1 else ''}"
        label = f"{a.name}, {gpus}, {d['target_samples']} samples/step"
        cmd = [sys.executable, str(HERE / "time_to_quality.py"), "eval", str(out / d["tag"]),
               str(out / f"{d['tag']}_ttq.json"), "--label", label]  # fmt: skip
        if a.chunk:
            cmd += ["--chunk", str(a.chunk)]
        log = open(out / f"{d['tag']}_eval.log", "w")
        procs.append(subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env))
    for p in procs:
        p.wait()
    rows = []
    for d in done:
        row = dict(d)
        hist = out / d["tag"] / "history.json"
        if hist.exists():
            row.update(throughput(json.loads(hist.read_text()), a.skip))
        ttq = out / f"{d['tag']}_ttq.json"
        if ttq.exists():
            row["ttq"] = [{k: r[k] for k in ("budget_s", "step", "psnr", "ssim")}
                          for r in json.loads(ttq.read_text())["rows"]]  # fmt: skip
        rows.append(row)
    summary = {"name": a.name, "budgets": a.budgets, "flags": flags, "skip_s": a.skip,
               "rows": rows, "efficiency": efficiencies(rows), "device": device_name(),
               "commit": commit()}  # fmt: skip
    js = out / f"scaling_{a.name}.json"
    js.write_text(json.dumps(summary, indent=1))
    print(markdown(summary))
    try:
        plot(summary, out / f"scaling_{a.name}.png")
    except Exception as e:  # (a plot is a convenience; the JSON is the record)
        print(f"no plot: {e}")


def efficiencies(rows: list) -> list:
    """Per multi-GPU row: the speed-up against 1 GPU at the same total batch, and the scaling
    efficiency against 1 GPU at the same per-GPU batch, in samples/s (where both exist)."""
    one = {r["target_samples"]: r for r in rows if r["gpus"] == 1 and "samples_per_s" in r}
    out = []
    for r in rows:
        if r["gpus"] == 1 or "samples_per_s" not in r:
            continue
        e = {"tag": r["tag"], "gpus": r["gpus"], "target_samples": r["target_samples"]}
        same_total = one.get(r["target_samples"])
        if same_total:
            e["speedup_same_total_batch"] = r["samples_per_s"] / same_total["samples_per_s"]
            e["steps_ratio_same_total_batch"] = r["steps_per_s"] / same_total["steps_per_s"]
        per_gpu = one.get(r["target_samples"] // r["gpus"])
        if per_gpu:
            e["efficiency_same_per_gpu_batch"] = r["samples_per_s"] / (
                r["gpus"] * per_gpu["samples_per_s"]
            )
        out.append(e)
    return out


def markdown(summary: dict) -> str:
    budgets = [float(b) for b in summary["budgets"].split(",")]
    head = (
        "| GPUs | samples/step (target) | steps/s | rays/s | samples/s | "
        + " | ".join(f"PSNR @{b:g} s" for b in budgets)
        + " |"
    )
    lines = [head, "|---" * (5 + len(budgets)) + "|"]
    for r in summary["rows"]:
        ps = {round(x["budget_s"], 3): x["psnr"] for x in r.get("ttq", [])}
        cells = [f"{ps[round(b, 3)]:.2f}" if round(b, 3) in ps else "—" for b in budgets]
        if r["exit"] != 0:
            cells = [f"failed (exit {r['exit']})"] + [""] * (len(budgets) - 1)
        lines.append(
            f"| {r['gpus']} | {r['target_samples']} | {r.get('steps_per_s', 0):.1f} | "
            f"{r.get('rays_per_s', 0) / 1e6:.2f} M | {r.get('samples_per_s', 0) / 1e6:.2f} M | "
            + " | ".join(cells) + " |")  # fmt: skip
    for e in summary["efficiency"]:
        parts = [f"{k} {v:.2f}" for k, v in e.items() if isinstance(v, float)]
        lines.append(f"\n{e['tag']}: " + ", ".join(parts))
    return "\n".join(lines)


def plot(summaries, png: Path) -> None:
    """Val PSNR against training seconds, one panel per summary (a dict or a list of them)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summaries = [summaries] if isinstance(summaries, dict) else list(summaries)
    fig, axes = plt.subplots(1, len(summaries), figsize=(6.0 * len(summaries), 4.2), squeeze=False)
    for ax, summary in zip(axes[0], summaries):
        for r in summary["rows"]:
            t = r.get("ttq")
            if t:
                ax.plot([x["budget_s"] for x in t], [x["psnr"] for x in t], "o-",
                        label=f"{r['gpus']} GPU, {r['target_samples']} samples/step")  # fmt: skip
        ax.set_xlabel("training seconds (wall clock)")
        ax.set_ylabel("val PSNR (dB)")
        ax.set_title(f"{summary['name']}: data-parallel training, {summary['device']}", fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(png, dpi=110)


def device_name() -> str:
    try:
        import torch

        if torch.cuda.is_available():
            return f"{torch.cuda.device_count()} x {torch.cuda.get_device_name(0)}"
    except Exception:
        pass
    return "cpu"


def commit() -> str:
    """The tree's commit: WARPNERF_COMMIT where set (a copy whose git metadata is not the
    tree's own, as on the device machines), else git's HEAD."""
    if os.environ.get("WARPNERF_COMMIT"):
        return os.environ["WARPNERF_COMMIT"]
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                              cwd=HERE).stdout.strip()  # fmt: skip
    except OSError:
        return ""


def main():
    from warpnerf.cli.parser import tool_parser

    p, sub, argv, flags = tool_parser(__doc__)
    r = sub.add_parser("run")
    r.add_argument("out")
    r.add_argument("--name", required=True)
    r.add_argument("--budgets", default="15,30,60")
    r.add_argument("--configs", default="1x262144,2x262144,2x524288")
    r.add_argument("--skip", type=float, default=5.0, help="seconds left out of the throughput")
    r.add_argument("--chunk", type=int, default=None, help="rays per render chunk when scoring")
    r.add_argument("--eval-parallel", type=int, default=1, help="scorers at a time (one GPU each)")
    q = sub.add_parser("report")
    q.add_argument(
        "json",
        nargs="+",
        help="scaling_NAME.json files (several: rows merged "
        "into one table per name, one plot panel per name)",
    )
    q.add_argument("--png", default=None)
    a = p.parse_args(argv)
    if a.cmd == "run":
        run_all(a, flags)
    else:
        merged: dict = {}
        for path in a.json:
            summary = json.loads(Path(path).read_text())
            have = merged.setdefault(summary["name"], summary)
            if have is not summary:  # (another part of the same scene's runs)
                have["rows"] += summary["rows"]
                have["efficiency"] = efficiencies(have["rows"])
        for summary in merged.values():
            print(f"\n{summary['name']} ({summary['device']}, commit {summary['commit'][:7]}):")
            print(markdown(summary))
        if a.png:
            plot(list(merged.values()), Path(a.png))


if __name__ == "__main__":
    main()
