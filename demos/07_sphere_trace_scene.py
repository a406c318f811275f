"""Demo 07: sphere-trace a scene of 32 primitives (spheres, rounded boxes, tori, capsules, a
carved box, a smooth blend, a ground plane), plain and over-relaxed.

Renders an orbit of the scene with the Warp kernel at omega = 1 (plain sphere tracing) and at
omega = 1.6 (over-relaxed, with Keinert's fallback), reports rays per second, mean iterations
per ray and the fraction of rays on which the two disagree (hit/miss or depth > 1e-3), and writes
``orbit.gif``, ``frame_000.png`` and ``metrics.json``. The last line is JSON.

    python demos/07_sphere_trace_scene.py --out out/07 [--frames 24] [--size 200] [--device cuda]
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

from warpnerf.data.cameras import intrinsics_from_fov, spiral_path
from warpnerf.errors import exit_status
from warpnerf.fields.sdf_scene import many_primitives_scene
from warpnerf.ops import generate_rays
from warpnerf.ops.sphere_trace import sphere_trace
from warpnerf.outputs import write_image, write_json, write_video

_spec = importlib.util.spec_from_file_location(
    "demo06", Path(__file__).with_name("06_sphere_trace_torus.py")
)
demo06 = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(demo06)

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common  # noqa: E402


def disagreement(scene, cams, size, device, omegas=(1.0, 1.6), max_iters=256) -> float:
    """Fraction of rays whose status or depth (> 1e-3) differs between the two omegas."""
    K = intrinsics_from_fov(size, size, 0.7).to(device)
    bad = total = 0
    for c2w in cams.to(device):
        o, d = generate_rays(c2w, K, size, size)
        a, b = (sphere_trace(o, d, scene, 0.0, 12.0, omega=w, max_iters=max_iters) for w in omegas)
        differ = (a.status != b.status) | (a.hit & ((a.t - b.t).abs() > 1e-3))
        bad += int(differ.sum())
        total += o.shape[0]
    return bad / total


def main(argv=None) -> int:
    """Runs the demo; a user error or a refusal of the machine: one line on stderr, status 2."""
    return exit_status("07_sphere_trace_scene", _main, argv)


def _main(argv) -> int:
    p = _common.parser(__doc__, "out/07_sphere_trace_scene", frames=24, size=200)
    p.add_argument("--iters", type=int, default=256, help="sphere-tracing iteration cap")
    p.add_argument("--omega", type=float, default=1.6, help="over-relaxation factor to compare")
    args = p.parse_args(argv)
    if not 1.0 < args.omega < 2.0:
        p.error("1 < --omega < 2 is required")
    out = _common.check_args(p, args, frames=1, size=2, iters=1)

    scene = many_primitives_scene()
    cams = spiral_path(args.frames, radius=7.0, elevation=(30.0, 50.0))
    demo06.render_frames(scene, cams[:1], 8, args.device)  # compile outside the timing
    res = {"primitives": len(scene), "frames": args.frames, "size": args.size}
    frames = None
    for omega in (1.0, args.omega):
        f, st = demo06.render_frames(
            scene, cams, args.size, args.device, omega=omega, max_iters=args.iters, normal_map=False
        )
        frames = frames or f
        key = f"omega_{omega:g}"
        res[key] = {
            "rays_per_s": st["rays"] / st["seconds"],
            "mean_iters_per_ray": st["iters"] / st["rays"],
            "hit_fraction": st["hits"] / st["rays"],
        }
    res["disagreement"] = disagreement(scene, cams[:: max(1, args.frames // 4)], args.size,
                                       args.device, (1.0, args.omega), args.iters)  # fmt: skip
    res["device"] = args.device
    out.mkdir(parents=True, exist_ok=True)
    write_video(out / "orbit.gif", frames)
    write_image(out / "frame_000.png", frames[0])
    write_json(out / "metrics.json", res)
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
