"""Demo 09: VolSDF — a neural SDF rendered through the Laplace density sigma = Psi_beta(-d) / beta
with the Warp compositing kernels, trained from images with an eikonal regulariser; then colour
and geometry (sphere-traced, shaded normals of the learned SDF) renders along a spiral and a
marching-cubes mesh of its zero level set.

    python demos/09_volsdf.py --out out/09                        # built-in scene, CPU
    python demos/09_volsdf.py --data ../shared/data/materials --aabb 1.7 --device cuda \\
        --iters 4000 --layers 8 --width 256 --batch 1024 --samples 64

The last line is JSON: val PSNR/SSIM, final beta, mesh size, time.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from warpnerf.errors import exit_status
from warpnerf.options import from_flags
from warpnerf.train import evaluate_run, render_run, train_nerf
from warpnerf.train.nerf_config import VolSDFConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common  # noqa: E402

# VolSDFConfig's fields shown here (--samples: coarse and fine samples per ray), and the demo's
# smaller defaults
FLAGS = ("data", "iters", "batch", "n_coarse", "n_layers", "width", "beta", "learn_beta", "aabb",
         "builtin_size", "device")  # fmt: skip
DEFAULTS = dict(iters=400, batch=512, n_coarse=32, n_layers=4, width=64, builtin_size=24)


def main(argv=None) -> int:
    """Runs the demo; a user error or a refusal of the machine: one line on stderr, status 2."""
    return exit_status("09_volsdf", _main, argv)


def _main(argv) -> int:
    p = _common.config_parser(__doc__, "out/09_volsdf", VolSDFConfig, FLAGS, DEFAULTS, frames=12,
                              eval_images=4)  # fmt: skip
    args = p.parse_args(argv)
    out = _common.check_args(p, args, frames=1, eval_images=0)
    run = _common.fresh_run(out / "run")
    cfg = VolSDFConfig(
        **from_flags(VolSDFConfig, args, include=FLAGS), n_fine=args.n_coarse,
        skip=max(1, args.n_layers // 2), val_every=max(1, args.iters // 4), val_images=2,
        ckpt_every=args.iters, lr=1e-3 if args.data == "builtin" else None,
    )  # fmt: skip
    hist = train_nerf(cfg, run, progress=False, log=lambda *a: None)
    m = evaluate_run(run, "val", max_images=args.eval_images)
    r = render_run(run, "spiral", args.frames)
    from warpnerf.mesh import extract_mesh, write_ply
    from warpnerf.train.nerf import load_run

    cfg, model, _ = load_run(run)
    a = cfg.aabb
    v, f = extract_mesh(model.coarse.sdf, [-a] * 3, [a] * 3, 96, 0.0, device=cfg.device)
    if len(f):
        write_ply(out / "mesh.ply", v, f)
    print(json.dumps(_common.surface_summary(args, hist, m, r, len(f))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
