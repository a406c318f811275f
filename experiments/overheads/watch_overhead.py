"""What watching a training costs: the same training run plainly, with TensorBoard logs, and with
TensorBoard logs plus the live viewer (`--viewer`, nobody connected), alternating the order over
repeats.

Reports per mode the median wall time per step inside the loop (from the first step to the end:
the loop's own clock excludes the hooks' time from training seconds, so this clock is the one
that shows their cost, direct and indirect, e.g. the viewer server's threads), the hooks' own
time per step, and the slowdown against the plain runs of the same repeat.

    python experiments/overheads/watch_overhead.py --repeats 3 -- --data builtin --iters 300 \
        --batch 1024 --layers 4 --width 64 --val-images 0
    python experiments/overheads/watch_overhead.py --device cuda -- --data lego --field hash ...

The arguments after ``--`` are `warpnerf train nerf` flags (without --out).
"""

from __future__ import annotations

import argparse
import json
import socket
import statistics
import sys
import tempfile
import time
from pathlib import Path

from warpnerf.cli.parser import build_parser
from warpnerf.cli.train import nerf_config_from_args
from warpnerf.train.loop import LoopHook
from warpnerf.train.nerf import train_nerf

MODES = ("plain", "tensorboard", "viewer")


class _Clock(LoopHook):
    """First hook: wall time per step inside the loop (step ends, hooks included)."""

    def __init__(self):
        self.marks = []

    def on_start(self, task, step):
        self.marks.append(time.perf_counter())

    def on_step(self, step, history, lr):
        self.marks.append(time.perf_counter())


class _Timed(LoopHook):
    """Times another hook's calls."""

    def __init__(self, inner):
        self.inner, self.seconds, self.calls = inner, 0.0, 0

    def on_start(self, task, step):
        self.inner.on_start(task, step)

    def on_step(self, step, history, lr):
        t = time.perf_counter()
        self.inner.on_step(step, history, lr)
        self.seconds += time.perf_counter() - t
        self.calls += 1

    def on_validation(self, step, figures, task):
        self.inner.on_validation(step, figures, task)

    def close(self):
        self.inner.close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def one(mode: str, argv: list, root: Path, k: int) -> dict:
    from warpnerf.train.logs import TensorBoardLog
    from warpnerf.viewer import LiveViewer

    run = root / f"{mode}_{k}"
    args = build_parser().parse_args(["train", "nerf", *argv, "--out", str(run)])
    cfg = nerf_config_from_args(args)
    clock = _Clock()
    timed = []
    if mode != "plain":
        timed.append(_Timed(TensorBoardLog(run)))
    if mode == "viewer":
        timed.append(_Timed(LiveViewer(run, port=_free_port(), log=lambda *a: None)))
    hist = train_nerf(cfg, run, progress=False, log=lambda *a: None, hooks=[clock, *timed])
    steps = [b - a for a, b in zip(clock.marks[1:], clock.marks[2:])]  # (after the first step)
    n = len(hist["step"])
    return {
        "mode": mode,
        "steps": n,
        "median_step_ms": 1e3 * statistics.median(steps),
        "mean_step_ms": 1e3 * sum(steps) / len(steps),
        "hook_ms_per_step": 1e3 * sum(t.seconds for t in timed) / max(n, 1),
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", default=None)
    p.add_argument("train_args", nargs=argparse.REMAINDER)
    a = p.parse_args()
    argv = [x for x in a.train_args if x != "--"]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(a.repeats):
            order = MODES[k % 3 :] + MODES[: k % 3]  # rotate which mode goes first
            for mode in order:
                rows.append(dict(one(mode, argv, Path(tmp), k), repeat=k))
                print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    plain = {r["repeat"]: r["mean_step_ms"] for r in rows if r["mode"] == "plain"}
    print(
        "| mode | runs | median step ms | mean step ms | hooks ms/step | mean slowdown vs plain |"
    )
    print("|---|---|---|---|---|---|")
    summary = {}
    for mode in MODES:
        rs = [r for r in rows if r["mode"] == mode]
        slow = [r["mean_step_ms"] / plain[r["repeat"]] - 1 for r in rs]
        summary[mode] = {
            "median_step_ms": statistics.median(r["median_step_ms"] for r in rs),
            "mean_step_ms": statistics.mean(r["mean_step_ms"] for r in rs),
            "hook_ms_per_step": statistics.mean(r["hook_ms_per_step"] for r in rs),
            "slowdown": statistics.mean(slow),
            "slowdown_each": slow,
        }
        s = summary[mode]
        print(f"| {mode} | {len(rs)} | {s['median_step_ms']:.3f} | {s['mean_step_ms']:.3f} | "
              f"{s['hook_ms_per_step']:.4f} | {100 * s['slowdown']:+.2f} % "
              f"({', '.join(f'{100 * x:+.1f}' for x in slow)}) |")  # fmt: skip
    if a.json:
        Path(a.json).write_text(
            json.dumps({"argv": argv, "rows": rows, "summary": summary}, indent=1)
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
