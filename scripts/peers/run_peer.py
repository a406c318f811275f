"""Side-by-side peers: trains a peer installed by the user (nerfacc, taichi-nerfs, instant-ngp) on
the same lego train split for the same time budgets as ``scripts/time_to_quality.py``, renders the
same val views through the peer's own code and scores them with warpnerf's PSNR / SSIM.

    python scripts/peers/run_peer.py PEER --data LEGO --peer-dir CHECKOUT --out DIR
        [--budgets 5,15,30,60,120,300] [--python PY] [--label L] [--max-steps N]
        [--timeout S] [-- ARGS FOR THE PEER]
    python scripts/peers/run_peer.py score --pred-dir PNGS --data LEGO --out X.json --label L
        --budget S [--step N] [--train-seconds T] [--render-ms M] [--append]
    python scripts/time_to_quality.py plot DIR/peer_*.json WARPNERF.json --png cmp.png

PEER is ``nerfacc`` (``examples/train_ngp_nerf_occ.py`` of a nerfacc checkout, nerfacc 0.5.3),
``taichi-nerfs`` (``train.py``) or ``instant-ngp`` (its ``pyngp`` Python bindings, driven as
``scripts/run.py`` drives them). The peer's code is never copied into this repository: it runs in
a subprocess, ``PY scripts/peers/peer_runner.py`` (PY: ``--python``, default this interpreter),
from the user's checkout (see that file for the few attribute patches it makes). Versions and
exact commands: ``scripts/peers/README.md``.

Writes DIR/peer_<PEER>.json in the layout of ``time_to_quality.py eval`` (``run``, ``label``,
``rows`` with ``budget_s``, ``step``, ``train_seconds``, ``psnr``, ``ssim``, ``images``,
``render_ms_median``; plus ``schedule_done`` per row and a ``peer`` record: checkout commit,
package versions, command), the val renders under DIR/<PEER>/renders/t<S>s/, and the table.

What is the same as warpnerf's time-to-quality runs: the data (the lego folder's train split for
training, all its val views for scoring; the peers read a staged folder DIR/<PEER>/data/lego of
symbolic links to it, with ``transforms_test.json`` pointing at the val split because nerfacc and
taichi-nerfs load a "test" split at start), the image size (400 x 400: nerfacc's loader is told
the size, taichi-nerfs gets ``--downsample 0.5`` of its hard-coded 800, instant-ngp reads it),
the white background of the scored images, the metrics (:func:`warpnerf.metrics.psnr` /
:func:`~warpnerf.metrics.ssim` per view against the val images composited on white as
``warpnerf eval`` loads them, averaged over the views), and the clock: one run per peer, the
training time read (GPU synchronised) at the start of each step, kernel compilation inside the
steps counted, data loading and the snapshot renders excluded; the state at the first step whose
start is at or past S seconds is the "S seconds" state (``warpnerf train --snapshots``).

What is not the same: each peer keeps its own recipe (network, batch, learning-rate schedule over
its own step count: nerfacc 20000 steps hard-coded in the example, taichi-nerfs ``--max_steps``
default 20000, instant-ngp 35000 with a step-based decay); a peer that finishes its schedule
before a budget gives its final state for the larger budgets (``schedule_done``, ``train_seconds``
below ``budget_s``). Backgrounds in training: nerfacc and taichi-nerfs composite the RGBA training
images on white (as warpnerf does); instant-ngp trains on random background colours in linear
space (its default for synthetic scenes) and its renders, premultiplied linear RGBA on a
transparent background, are converted to sRGB and composited on white in sRGB, as the ground
truth is. nerfacc's JIT-built CUDA extension is loaded before the clock starts (a cold build
takes minutes); taichi's and instant-ngp's run-time kernel compilation is inside the steps (run a
short budget once first to fill their caches). Peers' renders are 8-bit PNGs (rounded): that
adds at most (1/255)^2 / 12 = 1.3e-6 to a view's MSE, under 0.01 dB at ~30 dB (warpnerf scores
its float renders).

Exit status: 0; 1 when the peer run fails; 2 for bad arguments or a peer, module or GPU that is
missing (one line saying what to install).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import shutil
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from peer_runner import EXIT_MISSING, PEERS, hint  # noqa: E402

try:
    from warpnerf.errors import UserError  # a malformed val split, as warpnerf reports it
except ImportError:  # scoring needs warpnerf; the peer checks do not
    UserError = None

RUNNER = HERE / "peer_runner.py"
SPLIT_FILES = ("transforms_train.json", "transforms_val.json")


class Refused(Exception):
    """A bad argument or a missing peer: printed as one line, exit status 2."""


def parse_budgets(text: str) -> list:
    """'5,15,30' -> [5.0, 15.0, 30.0] (sorted, duplicates dropped); Refused unless every item is
    a finite number > 0."""
    out = []
    for item in str(text).split(","):
        item = item.strip()
        try:
            v = float(item)
        except ValueError:
            raise Refused(
                f"--budgets: {item!r} is not a number (give seconds, e.g. 5,15,30,60,120,300)"
            ) from None
        if not math.isfinite(v) or v <= 0:
            raise Refused(f"--budgets: {item!r} must be a finite number of seconds > 0")
        out.append(v)
    return sorted(set(out))


def check_data(path) -> Path:
    """The lego folder: Refused unless it holds transforms_train.json and transforms_val.json with
    frames, camera_angle_x and the first frame's image of each split."""
    root = Path(path)
    if not root.is_dir():
        raise Refused(
            f"--data: {root} is not a folder (give the lego folder with "
            "transforms_train.json, transforms_val.json, train/, val/)"
        )
    for name in SPLIT_FILES:
        p = root / name
        if not p.is_file():
            raise Refused(
                f"--data: {p} not found (the peers need a NeRF-synthetic folder with "
                f"{' and '.join(SPLIT_FILES)})"
            )
        try:
            js = json.loads(p.read_text())
        except (OSError, ValueError) as e:
            raise Refused(f"--data: {p} is not readable JSON: {e}") from None
        frames = js.get("frames") if isinstance(js, dict) else None
        if not isinstance(frames, list) or not frames:
            raise Refused(f"--data: {p} has no 'frames' list")
        if "camera_angle_x" not in js:
            raise Refused(f"--data: {p} has no 'camera_angle_x' (the peers' loaders need it)")
        fp = frames[0].get("file_path") if isinstance(frames[0], dict) else None
        if not isinstance(fp, str) or not (root / (fp + ".png")).is_file():
            raise Refused(
                f"--data: {p}: frames[0].file_path {fp!r} does not name a PNG under "
                f"{root} (the peers add '.png')"
            )
    return root


def stage_data(data: Path, stage: Path) -> None:
    """stage/ = symbolic links to the lego folder's splits; transforms_test.json -> the val one."""
    stage.mkdir(parents=True, exist_ok=True)
    links = {
        "train": "train",
        "val": "val",
        "transforms_train.json": "transforms_train.json",
        "transforms_val.json": "transforms_val.json",
        "transforms_test.json": "transforms_val.json",
    }
    for name, target in links.items():
        link, dest = stage / name, (data / target).resolve()
        if link.is_symlink():
            link.unlink()
        elif link.exists():
            raise Refused(f"{link} exists and is not a link this script made; remove it")
        if dest.exists():
            link.symlink_to(dest)


def find_python(python: str) -> str:
    exe = shutil.which(python) or (python if Path(python).is_file() else None)
    if exe is None:
        raise Refused(f"--python: {python!r} not found: give the Python the peer is installed in")
    return exe


def git_info(peer_dir: Path) -> dict:
    out = {}
    for key, cmd in (
        ("commit", ["rev-parse", "HEAD"]),
        ("describe", ["describe", "--tags", "--always", "--dirty"]),
    ):
        try:
            r = subprocess.run(
                ["git", "-C", str(peer_dir), *cmd], capture_output=True, text=True, timeout=30
            )
            out[key] = r.stdout.strip() if r.returncode == 0 else None
        except (OSError, subprocess.SubprocessError):
            out[key] = None
    return out


# ---- scoring ----------------------------------------------------------------------------------


def natural_key(name: str):
    """'r_10' after 'r_9': digit runs compare as numbers."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def match_predictions(pred_dir: Path, stems: list) -> tuple:
    """[(val index, png path)] and "name" or "index".

    By name when every PNG's stem is a val frame's file name (``r_7.png`` -> the frame whose
    file_path ends in ``r_7``, as instant-ngp's screenshots are named); otherwise by sorted index:
    the PNGs in natural order (digit runs compared as numbers: val_2 before val_10) are val frames
    0, 1, 2, ... of transforms_val.json. Subsets are allowed (all names, or the first frames)."""
    if not pred_dir.is_dir():
        raise Refused(f"--pred-dir: {pred_dir} is not a folder")
    files = sorted(
        (
            p
            for p in pred_dir.iterdir()
            if p.suffix.lower() == ".png" and not p.name.startswith(".")
        ),
        key=lambda p: natural_key(p.name),
    )
    if not files:
        raise Refused(f"--pred-dir: no .png files in {pred_dir}")
    index = {s: i for i, s in enumerate(stems)}
    if all(p.stem in index for p in files):
        return sorted(((index[p.stem], p) for p in files), key=lambda t: t[0]), "name"
    if len(files) > len(stems):
        raise Refused(
            f"--pred-dir: {len(files)} PNGs in {pred_dir} but the val split has "
            f"{len(stems)} views, and the names are not the val frames' "
            f"({stems[0]}.png, ...)"
        )
    return list(enumerate(files)), "index"


def read_prediction(path: Path, shape) -> object:
    """A rendered view as float32 [H, W, 3] in [0, 1]: 8- or 16-bit, grey / RGB / RGBA; straight
    alpha composited on white (rgb * a + 1 - a), as warpnerf composites the val images."""
    import imageio.v3 as iio
    import numpy as np

    try:
        img = np.asarray(iio.imread(path))
    except Exception as e:  # imageio raises many types for unreadable files
        raise Refused(f"{path}: cannot read image: {e}") from None
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim == 3 and img.shape[-1] in (1, 2):
        img = np.concatenate([img[..., :1].repeat(3, -1), img[..., 1:]], -1)
    if img.ndim != 3 or img.shape[-1] not in (3, 4):
        raise Refused(f"{path}: expected an RGB or RGBA image, got shape {img.shape}")
    if img.dtype not in (np.uint8, np.uint16):
        raise Refused(f"{path}: expected 8- or 16-bit pixels, got {img.dtype}")
    img = img.astype(np.float32) / (255.0 if img.dtype == np.uint8 else 65535.0)
    if img.shape[-1] == 4:
        a = img[..., 3:]
        img = img[..., :3] * a + (1.0 - a)
    if img.shape[:2] != tuple(shape):
        raise Refused(
            f"{path}: {img.shape[1]}x{img.shape[0]} pixels, but the val views are "
            f"{shape[1]}x{shape[0]} (render at the data's size; no resizing is done)"
        )
    return img


class GroundTruth:
    """The val split as ``warpnerf eval`` loads it: RGBA composited on a white background."""

    def __init__(self, data):
        from warpnerf.data import load_blender

        self.ds = load_blender(data, "val", background=(1.0, 1.0, 1.0))
        self.stems = [Path(p).stem for p in self.ds.paths]

    def score(self, pred_dir) -> dict:
        import torch

        from warpnerf.metrics import psnr, ssim

        pairs, how = match_predictions(Path(pred_dir), self.stems)
        gt = self.ds.images
        rows = []
        for i, p in pairs:
            pred = torch.from_numpy(read_prediction(p, gt.shape[1:3]))
            rows.append(
                {"view": i, "file": p.name, "psnr": psnr(pred, gt[i]), "ssim": ssim(pred, gt[i])}
            )
        n = len(rows)
        if n < len(self.stems):
            print(
                f"run_peer: note: {pred_dir} holds {n} of the {len(self.stems)} val views",
                file=sys.stderr,
            )
        out = {
            "psnr": sum(r["psnr"] for r in rows) / n,
            "ssim": sum(r["ssim"] for r in rows) / n,
            "images": n,
            "matched_by": how,
            "per_image": rows,
        }
        identical = sum(1 for r in rows if math.isinf(r["psnr"]))
        if identical:  # PSNR inf (written as null in JSON)
            out["identical_images"] = identical
        return out


def write_result(path: Path, obj: dict) -> None:
    from warpnerf.outputs import write_json

    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, obj)


def print_table(rows: list) -> None:
    def f(v, fmt):
        return "-" if v is None else (format(v, fmt) if math.isfinite(v) else "inf")

    md = [
        "| budget s | training s | steps | val PSNR | val SSIM | frame ms |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        md.append(
            f"| {r['budget_s']:g} | {f(r.get('train_seconds'), '.1f')} | "
            f"{r.get('step', '-')} | {f(r['psnr'], '.2f')} | {f(r['ssim'], '.4f')} | "
            f"{f(r.get('render_ms_median'), '.1f')} |"
        )
    print("\n".join(md))


def cmd_score(a) -> int:
    if not math.isfinite(a.budget) or a.budget <= 0:
        raise Refused(f"--budget must be a number of seconds > 0, got {a.budget:g}")
    check_data(a.data)
    m = GroundTruth(a.data).score(a.pred_dir)
    row = {"budget_s": a.budget}
    if a.step is not None:
        row["step"] = a.step
    row["train_seconds"] = a.train_seconds  # null when not known
    row.update(psnr=m["psnr"], ssim=m["ssim"], images=m["images"], render_ms_median=a.render_ms)
    if "identical_images" in m:
        row["identical_images"] = m["identical_images"]
    out = Path(a.out)
    rows = []
    if a.append and out.is_file():
        try:
            old = json.loads(out.read_text())
            rows = [r for r in old["rows"] if r["budget_s"] != a.budget]
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise Refused(f"--append: {out} is not a results file of this script: {e}") from None
    rows = sorted([*rows, row], key=lambda r: r["budget_s"])
    write_result(
        out,
        {
            "run": str(a.pred_dir),
            "label": a.label,
            "rows": rows,
            "geometry": None,
            "matched_by": m["matched_by"],
        },
    )
    print_table(rows)
    return 0


# ---- peer runs --------------------------------------------------------------------------------


def peer_preflight(peer: str, peer_dir: Path, python: str) -> dict:
    """Exit-2 checks that need no GPU: the checkout (here), then the modules (in ``python``)."""
    spec = PEERS[peer]
    if not peer_dir.is_dir():
        raise Refused(
            f"{peer} is not installed: checkout {peer_dir} not found; "
            f"{hint(spec['clone'], peer_dir)} (see scripts/peers/README.md)"
        )
    exe = find_python(python)
    r = subprocess.run(
        [exe, str(RUNNER), peer, "--peer-dir", str(peer_dir), "--check"],
        capture_output=True,
        text=True,
    )
    if r.returncode == EXIT_MISSING:
        lines = r.stderr.strip().splitlines() or ["(no message)"]
        raise Refused(f"{peer} is not installed: {lines[-1].removeprefix(f'run_peer: {peer}: ')}")
    if r.returncode != 0:
        tail = (r.stderr.strip().splitlines() or ["(no message)"])[-1]
        raise Refused(f"{exe} could not check {peer}: {tail}")
    info = json.loads(r.stdout.strip().splitlines()[-1])
    info["executable_given"] = python
    return info


def cmd_peer(a, peer_args: list) -> int:
    budgets = parse_budgets(a.budgets)
    data = check_data(a.data)
    if a.max_steps is not None and a.max_steps <= 0:
        raise Refused(f"--max-steps must be > 0, got {a.max_steps}")
    if a.max_steps and a.peer == "nerfacc":
        raise Refused(
            "--max-steps: nerfacc's train_ngp_nerf_occ.py hard-codes max_steps = 20000 "
            "and has no flag for it"
        )
    if a.timeout is not None and a.timeout <= 0:
        raise Refused(f"--timeout must be > 0 seconds, got {a.timeout}")
    peer_dir = Path(a.peer_dir).absolute()
    env = peer_preflight(a.peer, peer_dir, a.python)
    out = Path(a.out)
    base = out / a.peer
    stage, work, renders = base / "data" / "lego", base / "work", base / "renders"
    stage_data(data.resolve(), stage)
    work.mkdir(parents=True, exist_ok=True)
    renders.mkdir(parents=True, exist_ok=True)
    (renders / "snapshots.json").unlink(missing_ok=True)
    cmd = [
        env["executable"],
        str(RUNNER),
        a.peer,
        "--peer-dir",
        str(peer_dir),
        "--stage",
        str(stage.absolute()),
        "--work",
        str(work.absolute()),
        "--out",
        str(renders.absolute()),
        "--budgets",
        ",".join(f"{b:g}" for b in budgets),
        "--max-steps",
        str(a.max_steps or 0),
        "--",
        *peer_args,
    ]
    print("run_peer:", " ".join(cmd), flush=True)
    try:
        rc = subprocess.run(cmd, timeout=a.timeout).returncode
    except subprocess.TimeoutExpired:
        print(
            f"run_peer: {a.peer} ran past --timeout {a.timeout:g} s; scoring what it rendered",
            file=sys.stderr,
        )
        rc = 0
    if rc == EXIT_MISSING:
        return EXIT_MISSING  # the runner printed what is missing
    snap = renders / "snapshots.json"
    if rc != 0 or not snap.is_file():
        print(f"run_peer: {a.peer} failed (exit status {rc}); its output is above", file=sys.stderr)
        if not snap.is_file():
            return 1
    snaps = json.loads(snap.read_text())["rows"]
    if not snaps:
        print(
            f"run_peer: {a.peer} rendered nothing (it stopped before the first budget)",
            file=sys.stderr,
        )
        return 1
    gt = GroundTruth(data)
    scored, rows = {}, []
    for s in snaps:
        if s["dir"] not in scored:
            m = gt.score(renders / s["dir"])
            scored[s["dir"]] = m
            write_result(renders / s["dir"] / "metrics.json", m)
        m = scored[s["dir"]]
        row = {
            "budget_s": s["budget_s"],
            "step": s["step"],
            "train_seconds": s["train_seconds"],
            "psnr": m["psnr"],
            "ssim": m["ssim"],
            "images": m["images"],
            "render_ms_median": s["render_ms_median"],
            "schedule_done": s["schedule_done"],
        }
        rows.append(row)
        print(json.dumps(row), flush=True)
    git = git_info(peer_dir)
    label = a.label or f"{a.peer} {git.get('describe') or ''}".strip()
    entry = {
        "nerfacc": "examples/train_ngp_nerf_occ.py",
        "taichi-nerfs": "train.py",
        "instant-ngp": "pyngp (as scripts/run.py)",
    }[a.peer]
    result = {
        "run": str(base),
        "label": label,
        "rows": rows,
        "geometry": None,
        "peer": {
            "name": a.peer,
            "checkout": str(peer_dir),
            **git,
            "entry": entry,
            "python": env["python"],
            "executable": env["executable"],
            "versions": env["versions"],
            "command": cmd,
            "peer_args": peer_args,
            "data": str(data.resolve()),
            "max_steps": a.max_steps,
            "complete": rc == 0,
        },
    }
    write_result(out / f"peer_{a.peer}.json", result)
    print_table(rows)
    return 0 if rc == 0 else 1


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    peer_args = argv[argv.index("--") + 1 :] if "--" in argv else []
    argv = argv[: argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(
        prog="run_peer.py",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(
        dest="cmd", required=True, metavar="{nerfacc,taichi-nerfs,instant-ngp,score}"
    )
    for name in PEERS:
        r = sub.add_parser(name, help=f"train and score {name}")
        r.add_argument(
            "--data", required=True, help="the lego folder (transforms_*.json, train/, val/)"
        )
        r.add_argument("--peer-dir", required=True, help=f"the user's {name} checkout")
        r.add_argument("--out", required=True, help="output folder")
        r.add_argument("--budgets", default="5,15,30,60,120,300", help="training seconds")
        r.add_argument(
            "--python", default=sys.executable, help="the Python the peer is installed in"
        )
        r.add_argument("--label", default=None)
        r.add_argument(
            "--max-steps",
            type=int,
            default=None,
            help="taichi-nerfs: its --max_steps (schedule length); instant-ngp: n_steps",
        )
        r.add_argument("--timeout", type=float, default=None, help="kill the peer after S seconds")
    s = sub.add_parser("score", help="score a folder of rendered val PNGs")
    s.add_argument("--pred-dir", required=True, help="rendered val views (PNG)")
    s.add_argument("--data", required=True, help="the lego folder")
    s.add_argument("--out", required=True, help="JSON to write")
    s.add_argument("--label", required=True)
    s.add_argument("--budget", type=float, required=True, help="the row's budget_s")
    s.add_argument("--step", type=int, default=None)
    s.add_argument("--train-seconds", type=float, default=None, help="if known")
    s.add_argument("--render-ms", type=float, default=None, help="median frame time, if known")
    s.add_argument("--append", action="store_true", help="add the row to an existing --out")
    a = p.parse_args(argv)
    a.peer = a.cmd
    try:
        if a.cmd == "score":
            if peer_args:
                raise Refused("score takes no arguments after --")
            return cmd_score(a)
        return cmd_peer(a, peer_args)
    except Refused as e:
        print(f"run_peer: {e}", file=sys.stderr)
        return EXIT_MISSING
    except Exception as e:
        if UserError is None or not isinstance(e, UserError):
            raise
        print(f"run_peer: {e}", file=sys.stderr)
        return EXIT_MISSING
    except KeyboardInterrupt:
        print("run_peer: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
