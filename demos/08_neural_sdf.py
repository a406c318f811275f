"""Demo 08: fit a neural SDF to a point cloud (|f| on the points + eikonal loss), extract its mesh
(Warp marching cubes), and sphere-trace the network itself (batched torch queries of the rays
still marching) into a normal-shaded turntable.

    python demos/08_neural_sdf.py --out out/08                       # built-in torus points
    python demos/08_neural_sdf.py --points ../shared/data/bunny_pointcloud.npz --iters 2000
    python demos/08_neural_sdf.py --field hash                       # the hash-grid SDF

Writes the run folder (config, checkpoint, mesh.ply, mesh.png, metrics.json) under --out plus
turntable.gif; the last line is JSON with the Chamfer distance (bounding-box diagonals), the
eikonal residual and the sphere-tracing statistics.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from warpnerf.data.cameras import intrinsics_from_fov, spiral_path
from warpnerf.errors import exit_status
from warpnerf.ops import generate_rays
from warpnerf.options import add_flags, from_flags
from warpnerf.outputs import write_video
from warpnerf.sphere_tracing import shade, sphere_trace_fn
from warpnerf.train.sdf import SDFConfig, train_sdf

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common  # noqa: E402

FLAGS = ("points", "field", "iters", "batch", "width", "resolution", "device")  # SDFConfig's


def turntable(model, n_frames, size, device):
    """Normal-shaded frames of the network's zero level set, and (rays/s, mean iterations)."""
    K = intrinsics_from_fov(size, size, 0.7).to(device)
    frames, rays, iters, secs = [], 0, 0, 0.0
    for c2w in spiral_path(n_frames, radius=2.8, elevation=(10.0, 35.0)).to(device):
        o, d = generate_rays(c2w, K, size, size)
        t0 = time.perf_counter()
        tr = sphere_trace_fn(model, o, d, 0.5, 5.0, eps=1e-3, max_iters=128)
        secs += time.perf_counter() - t0
        rays, iters = rays + o.shape[0], iters + int(tr.iters.sum())
        frames.append(shade(tr, d, None).reshape(size, size, 3).cpu())
    return frames, rays / secs, iters / rays


def main(argv=None) -> int:
    """Runs the demo; a user error or a refusal of the machine: one line on stderr, status 2."""
    return exit_status("08_neural_sdf", _main, argv)


def _main(argv) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="out/08_neural_sdf")  # (--device: SDFConfig's flag)
    add_flags(p, SDFConfig, include=FLAGS, defaults=dict(iters=600, batch=2048))
    p.add_argument("--frames", type=int, default=12)
    p.add_argument("--size", type=int, default=96)
    args = p.parse_args(argv)
    out = _common.check_args(p, args, frames=1, size=2)
    run = _common.fresh_run(out / "run")

    cfg = SDFConfig(**from_flags(SDFConfig, args, include=FLAGS), n_random=args.batch)
    m = train_sdf(cfg, run, progress=False)
    from warpnerf.train.sdf import load_sdf_run

    _, model, _ = load_sdf_run(run)
    frames, rays_per_s, mean_iters = turntable(model, args.frames, args.size, args.device)
    write_video(out / "turntable.gif", frames)
    res = {
        "points": args.points,
        "field": args.field,
        "iters": m["step"],
        "train_seconds": m["seconds"],
        "chamfer": m["chamfer"],
        "eikonal_residual_box_mean": m["eikonal_residual_box"]["mean"],
        "eikonal_residual_surface_mean": m["eikonal_residual_surface"]["mean"],
        "mesh_faces": m["faces"],
        "trace_rays_per_s": rays_per_s,
        "trace_mean_iters": mean_iters,
    }
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
