"""Demo 06: sphere-trace the seed's torus along a spiral (Warp kernel, one thread per ray).

Each frame: pinhole rays (Warp), sphere tracing of the analytic torus until |sdf| < eps, normals
from a tetrahedral central difference, Lambert + ambient shading and a normal map side by side.
Writes ``spiral.gif`` / ``spiral.mp4`` and ``frame_000.png``; prints rays per second and mean
iterations per ray as the last JSON line.

    python demos/06_sphere_trace_torus.py --out out/06 [--frames 40] [--size 160] [--device cuda]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch

from warpnerf.data.cameras import intrinsics_from_fov, spiral_path
from warpnerf.errors import exit_status
from warpnerf.fields.sdf_scene import torus_scene
from warpnerf.ops import generate_rays
from warpnerf.ops.sphere_trace import sphere_trace
from warpnerf.outputs import write_image, write_json, write_video
from warpnerf.sphere_tracing import shade

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common  # noqa: E402


def render_frames(scene, cams, size, device, omega=1.0, eps=1e-4, max_iters=256, normal_map=True):
    """(frames, stats): shaded frames [H, W(*2), 3] and totals of rays, time, iterations, hits."""
    K = intrinsics_from_fov(size, size, 0.7).to(device)
    colors = scene.arrays(device)["colors"]
    frames, secs, n_rays, n_iter, n_hit = [], 0.0, 0, 0, 0
    for c2w in cams.to(device):
        o, d = generate_rays(c2w, K, size, size)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        tr = sphere_trace(o, d, scene, 0.0, 12.0, eps=eps, omega=omega, max_iters=max_iters)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        secs += time.perf_counter() - t0
        n_rays += o.shape[0]
        n_iter += int(tr.iters.sum())
        n_hit += int(tr.hit.sum())
        img = shade(tr, d, colors).reshape(size, size, 3)
        if normal_map:
            img = torch.cat([img, shade(tr, d, None).reshape(size, size, 3)], 1)
        frames.append(img.cpu())
    return frames, {"rays": n_rays, "seconds": secs, "iters": n_iter, "hits": n_hit}


def main(argv=None) -> int:
    """Runs the demo; a user error or a refusal of the machine: one line on stderr, status 2."""
    return exit_status("06_sphere_trace_torus", _main, argv)


def _main(argv) -> int:
    p = _common.parser(__doc__, "out/06_sphere_trace_torus", frames=40, size=160)
    p.add_argument("--iters", type=int, default=256, help="sphere-tracing iteration cap")
    args = p.parse_args(argv)
    out = _common.check_args(p, args, frames=1, size=2, iters=1)

    scene = torus_scene()
    cams = spiral_path(args.frames, radius=3.6, elevation=(20.0, 60.0))
    render_frames(scene, cams[:1], 8, args.device)  # compile / warm up outside the timing
    frames, st = render_frames(scene, cams, args.size, args.device, max_iters=args.iters)
    out.mkdir(parents=True, exist_ok=True)
    write_video(out / "spiral.gif", frames)
    write_video(out / "spiral.mp4", frames)
    write_image(out / "frame_000.png", frames[0])
    res = {
        "frames": args.frames,
        "size": args.size,
        "device": args.device,
        "rays_per_s": st["rays"] / st["seconds"],
        "mean_iters_per_ray": st["iters"] / st["rays"],
        "hit_fraction": st["hits"] / st["rays"],
    }
    write_json(out / "metrics.json", res)
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
