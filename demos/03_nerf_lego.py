"""Demo 03: NeRF on lego (or the built-in scene): train, score on val, render a 360-degree video.

    python demos/03_nerf_lego.py --out out/03                        # built-in scene, CPU
    python demos/03_nerf_lego.py --data ../shared/data/lego --device cuda --downscale 1 \\
        --layers 8 --width 256 --samples 64 --coarse-fine --iters 20000 --out out/03_lego

Positions are encoded with 10 frequencies, directions with 4 (the original NeRF); with
--coarse-fine a second network is evaluated on the union of the coarse samples and samples drawn
from the coarse weights. Prints one JSON line last: val PSNR/SSIM, training time, parameters.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _nerf_args  # noqa: E402

from warpnerf.errors import exit_status  # noqa: E402
from warpnerf.train.nerf_eval import render_run, train_and_evaluate  # noqa: E402


def main(argv=None) -> int:
    """Runs the demo; a user error or a refusal of the machine: one line on stderr, status 2."""
    return exit_status("03_nerf_lego", _main, argv)


def _main(argv) -> int:
    p = _nerf_args.parser(__doc__.splitlines()[0], "out/03_nerf_lego")
    p.add_argument("--coarse-fine", action="store_true")
    p.add_argument("--fine-samples", type=_nerf_args.positive, default=64)
    p.add_argument("--frames", type=int, default=40, help="video frames (0: no video)")
    args = p.parse_args(argv)
    cfg = _nerf_args.config(
        args, pos_freqs=10, dir_freqs=4, n_fine=args.fine_samples if args.coarse_fine else 0
    )
    out = Path(args.out)
    res = train_and_evaluate(cfg, out / "run", max_images=args.eval_images, progress=True)
    if args.frames > 0:
        res["video"] = render_run(out / "run", "spiral", args.frames)["out"]
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
