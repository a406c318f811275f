"""Demo 11: surfaces on the fast path — a hash-grid SDF rendered with VolSDF's Laplace density
through the occupancy grid (``--field hash_sdf``), end to end: train, evaluate, render colour,
depth and geometry (sphere-traced normals of the learned SDF) along a spiral, the val views
sphere-traced too (PSNR and time beside the volume renderer's), and a marching-cubes mesh cleaned
of floating pieces with vertex colours baked from the radiance field (PLY + pyvista screenshot).

    python demos/11_hash_sdf.py --out out/11                 # built-in scene, CPU, ~1 min
    (measured on the project's idle 2-core CPU: 57 s, 24.3 dB val; 6 min when the CPU is
    shared; the first run also compiles Warp's kernels)
    python demos/11_hash_sdf.py --data ../shared/data/lego --device cuda --max-seconds 300 \\
        --iters 100000 --batch 4096 --target-samples 262144 --hash-levels 16 \\
        --hash-log2-size 19 --hash-max-res 2048 --grid-res 128 --march-step 0 --eval-images 100
    (the settings of scripts/gpu.py's hash_sdf phase: lego on an H100 reached 31.1 dB on all
    100 val images after 300 s, docs/design/surfaces.md)

The last line is JSON: val PSNR/SSIM (both renderers), final beta, mesh size, time.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from warpnerf.errors import exit_status
from warpnerf.mesh import clean_mesh, extract_mesh, screenshot, vertex_colors, write_ply
from warpnerf.options import from_flags
from warpnerf.train import evaluate_run, load_run, render_run, train_nerf
from warpnerf.train.nerf_config import VolSDFConfig
from warpnerf.train.presets import NERF_PRESETS

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common  # noqa: E402

# VolSDFConfig's fields shown here, and the demo's CPU-sized defaults
FLAGS = ("data", "iters", "max_seconds", "batch", "target_samples", "hash_levels",
         "hash_log2_size", "hash_max_res", "grid_res", "march_step", "eikonal_weight", "aabb",
         "builtin_size", "device")  # fmt: skip
# (march_step: 256 steps across the built-in scene's box diagonal, the cpu preset's, instead of
# 1024: the samples per ray, hence the time a step, drop about 4x; 0 = the box diagonal / 1024)
DEFAULTS = dict(iters=200, batch=256, hash_levels=8, hash_log2_size=14, hash_max_res=256,
                grid_res=32, march_step=NERF_PRESETS["cpu"]["hash_sdf"]["march_step"],
                builtin_size=32)  # fmt: skip


def main(argv=None) -> int:
    """Runs the demo; a user error or a refusal of the machine: one line on stderr, status 2."""
    return exit_status("11_hash_sdf", _main, argv)


def _main(argv) -> int:
    p = _common.config_parser(__doc__, "out/11_hash_sdf", VolSDFConfig, FLAGS, DEFAULTS, frames=12,
                              eval_images=4, mesh_resolution=128)  # fmt: skip
    args = p.parse_args(argv)
    out = _common.check_args(p, args, frames=1, eval_images=0, mesh_resolution=8)
    run = _common.fresh_run(out / "run")
    cfg = VolSDFConfig(
        **from_flags(VolSDFConfig, args, include=FLAGS), field="hash_sdf", n_fine=0,
        tf32=True, val_every=max(1, args.iters // 4), val_images=2, ckpt_every=args.iters,
    )  # fmt: skip
    hist = train_nerf(cfg, run, progress=False, log=lambda *a: None)
    m = evaluate_run(run, "val", max_images=args.eval_images)
    # the same views with the learned surface sphere-traced instead (colour from the field's head
    # at the hit): faster on CPU, less faithful (docs/design/surfaces.md)
    ms = evaluate_run(run, "val", max_images=args.eval_images, renderer="sphere")
    r = render_run(run, "spiral", args.frames)
    cfg, model, _ = load_run(run)
    a, field = cfg.aabb, model.field
    v, f = extract_mesh(field.sdf, [-a] * 3, [a] * 3, args.mesh_resolution, 0.0, device=cfg.device)
    shot, cleaned = None, None
    if len(f):
        try:  # floating pieces below 1 % of the area go (pyvista's connectivity filter)
            v, f, info = clean_mesh(v, f, 0.01)
            cleaned = info["components_removed"]
        except ImportError:  # pyvista missing: the mesh stays as extracted
            pass
        rgb = vertex_colors(field, field.sdf, v, cfg.device)
        write_ply(out / "mesh.ply", v, f, colors=rgb)
        try:
            screenshot(out / "mesh.png", v, f, colors=rgb)
            shot = str(out / "mesh.png")
        except ImportError:  # pyvista missing: the PLY is still written
            pass
    res = _common.surface_summary(args, hist, m, r, len(f), mesh_screenshot=shot,
                                  render_ms_median=m["render_ms_median"],
                                  sphere_traced_psnr=ms["psnr"],
                                  sphere_traced_ms_median=ms["render_ms_median"],
                                  mesh_components_removed=cleaned)  # fmt: skip
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
