"""Issue 49: does NeuS's unbiased density stop the shrinking of curved shapes? An A/B on the
CPU: `train volsdf --data DATA --field hash_sdf --preset cpu --sdf-density {laplace,neus}`, then
per shape the signed distance of the delivered mesh to it (median over the vertices nearest that
shape: negative = the mesh lies inside, eroded), its mean |distance|, and the Chamfer distance.

- ``--data builtin`` (a box and a sphere, known exactly; `warpnerf mesh`): note that the built-in
  scene's own images are volume-rendered with a Laplace density (beta 0.02), so their outlines
  already carry that density's tail: there a Laplace field is the consistent model.
- ``--data <materials>`` (Mitsuba's hard surfaces): `warpnerf eval RUN --geometry materials`
  (the delivered mesh's Chamfer and per-shape signed medians).

    python3 experiments/surfaces/neus_builtin_ab.py --out DIR [--data builtin] [--densities
        laplace,neus] [--seed 0] [--extra "--iters 300"] [--json DIR/ab.json]
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch


def _cli(*args) -> None:
    subprocess.run([sys.executable, "-m", "warpnerf.cli", *map(str, args)], check=True)


def shape_errors(v: np.ndarray) -> dict:
    from warpnerf.data.synthetic import GlossyScene
    from warpnerf.fields.sdf_volume import sdf_box, sdf_sphere

    s = GlossyScene()
    p = torch.as_tensor(v, dtype=torch.float32)
    d_box = sdf_box(p, s.box_c, s.box_s)
    d_sph = sdf_sphere(p, s.sph_c, s.sph_r)
    out = {}
    for name, d, mine in (("sphere", d_sph, d_sph.abs() < d_box.abs()),
                          ("box", d_box, d_box.abs() <= d_sph.abs())):  # fmt: skip
        dm = d[mine]
        out[name] = {"vertices": int(mine.sum()), "signed_median": float(dm.median()),
                     "mean_abs": float(dm.abs().mean())}  # fmt: skip
    ref = s.surface_points(4000)  # Chamfer against points spread by area
    n = ref.shape[0]
    near = torch.cat([torch.cdist(ref[i : i + 1000], p).min(1).values for i in range(0, n, 1000)])
    acc = float(torch.minimum(d_box, d_sph).abs().mean())
    out["accuracy"], out["completeness"] = acc, float(near.mean())
    out["chamfer"] = 0.5 * (acc + out["completeness"])
    return out


def _materials_figures(run: Path, resolution: int) -> dict:
    """The delivered mesh and the depths of a materials run (`eval --geometry materials`)."""
    p = subprocess.run([sys.executable, "-m", "warpnerf.cli", "eval", str(run), "--geometry",
                        "materials", "--mesh-resolution", str(resolution), "--quiet"],
                       check=True, capture_output=True, text=True)  # fmt: skip
    g = json.loads(p.stdout)
    dl = g["delivered"]
    sm = dl["signed_median"]
    spheres = [v for k, v in sm.items() if k != "disk"]
    val = json.loads((run / "history.json").read_text()).get("val_psnr") or [float("nan")]
    return {"chamfer": dl["chamfer"], "spheres_signed": float(np.mean(spheres)),
            "disk_signed": sm["disk"], "depth_error": g.get("depth_error_mean", float("nan")),
            "psnr": val[-1], "signed_median": sm}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="folder for the runs and meshes")
    ap.add_argument("--data", default="builtin", help="builtin, or a materials folder")
    ap.add_argument("--densities", default="laplace,neus")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--extra", default="", help="more train flags, one string")
    ap.add_argument("--resolution", type=int, default=96, help="the mesh's grid")
    ap.add_argument("--json")
    a = ap.parse_args()
    from warpnerf.mesh import read_ply

    out = Path(a.out)
    rows = []
    for kind in a.densities.split(","):
        run = out / f"run_{kind}"
        t0 = time.perf_counter()
        _cli("train", "volsdf", "--data", a.data, "--field", "hash_sdf", "--preset", "cpu",
             "--sdf-density", kind, "--seed", a.seed, "--out", run, "--quiet", "--no-tensorboard",
             *shlex.split(a.extra))  # fmt: skip
        train_s = time.perf_counter() - t0
        if a.data == "builtin":
            ply = out / f"mesh_{kind}.ply"
            _cli("mesh", run, "--out", ply, "--resolution", a.resolution)
            v, _ = read_ply(ply)
            figures = shape_errors(np.asarray(v))
        else:
            figures = _materials_figures(run, a.resolution)
        beta = json.loads((run / "history.json").read_text()).get("beta") or [None]
        row = {"density": kind, "train_s": round(train_s, 1), "beta_end": beta[-1], **figures}
        print(json.dumps(row))
        rows.append(row)
        print(json.dumps(row))
    if a.data == "builtin":
        print("| density | sphere signed median | sphere mean abs | box signed median | box mean "
              "abs | Chamfer |")  # fmt: skip
        print("|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['density']} | {r['sphere']['signed_median']:+.4f} | "
                  f"{r['sphere']['mean_abs']:.4f} | {r['box']['signed_median']:+.4f} | "
                  f"{r['box']['mean_abs']:.4f} | {r['chamfer']:.4f} |")  # fmt: skip
    else:
        print("| density | val dB | spheres' signed median (mean of 8) | disk | delivered Chamfer "
              "| depth error |")  # fmt: skip
        print("|---|---|---|---|---|---|")
        for r in rows:
            print(
                f"| {r['density']} | {r['psnr']:.2f} | {r['spheres_signed']:+.4f} | "
                f"{r['disk_signed']:+.4f} | {r['chamfer']:.4f} | {r['depth_error']:.4f} |"
            )
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
