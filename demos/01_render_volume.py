"""Demo 01: volume-render the seed's analytic SDF volume (box, sphere or torus) along a spiral.

Each sample's opacity is alpha * Psi_beta(-sdf) (Laplace CDF), composited front to back by the Warp
kernel. Writes a colour video (mp4 + gif), a depth video and a depth PNG normalised by its maximum.

    python demos/01_render_volume.py --out out/01 [--shape box|sphere|torus] [--frames 40]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch

from warpnerf.box_demo import GT_BOX, write_spiral
from warpnerf.errors import exit_status
from warpnerf.fields import SDFVolume
from warpnerf.train import BoxFitConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common  # noqa: E402


def main(argv=None) -> int:
    """Runs the demo; a user error or a refusal of the machine: one line on stderr, status 2."""
    return exit_status("01_render_volume", _main, argv)


def _main(argv) -> int:
    p = _common.parser(__doc__, "out/01_render_volume")
    p.add_argument("--shape", default="box", choices=SDFVolume.SHAPES)
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--samples", type=int, default=128, help="samples per ray")
    p.add_argument("--beta", type=float, default=0.05)
    p.add_argument("--iters", type=int, default=0, help="unused (no optimisation here)")
    args = p.parse_args(argv)
    if args.frames < 1 or args.size < 2 or args.samples < 1 or not args.beta > 0:
        p.error("--frames >= 1, --size >= 2, --samples >= 1 and --beta > 0 are required")
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        p.error("--device cuda: no CUDA device available")
    if Path(args.out).exists() and not Path(args.out).is_dir():
        p.error(f"--out {args.out} is a file")

    volume = SDFVolume(args.shape, **GT_BOX, beta=args.beta).to(args.device)
    cfg = BoxFitConfig(n_samples=args.samples, near=0.0, far=5.0)
    t0 = time.perf_counter()
    rgb, depth = write_spiral(volume, Path(args.out), args.frames, args.size, cfg)
    sec = time.perf_counter() - t0
    rays = args.frames * args.size * args.size
    print(
        f"wrote {args.out}/spiral_rgb.mp4, spiral_rgb.gif, spiral_depth.gif, spiral_depth_000.png"
    )
    print(
        json.dumps(
            {
                "shape": args.shape,
                "frames": args.frames,
                "size": args.size,
                "samples_per_ray": args.samples,
                "seconds": round(sec, 3),
                "rays_per_second": round(rays / sec, 1),
                "covered_pixel_fraction": round(float(depth.gt(0).float().mean()), 4),
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
