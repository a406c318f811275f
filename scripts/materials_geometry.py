"""Geometry of an SDF run (volsdf, hash_sdf) on the materials scene against its analytic geometry
(README of the data: 8 spheres of radius 0.32 at z = 0.32, x in {-1.05, -0.35, 0.35, 1.05},
y in {-0.4, 0.4}; a ground disk of radius 1.6 at z = 0): a thin wrapper over
``warpnerf eval RUN --geometry materials`` (warpnerf.train.nerf_eval.evaluate_geometry) with this
script's historical defaults (100,000 points, 20 val images).

    python scripts/materials_geometry.py RUN [--resolution 256] [--val-images 20] [--clean]
        [--json out.json]

Reports, in world units: accuracy (mesh -> truth, the mesh's points under the disk, z < -0.1,
left out: a closed SDF must give the infinitely thin disk some thickness), completeness
(truth -> mesh) and Chamfer (their mean) of the marching-cubes mesh of the learned SDF, and the
mean / median absolute error of the rendered expected depth / opacity on the val views, on pixels
whose analytic ray hits the geometry and whose rendered opacity exceeds 0.5.
"""

from __future__ import annotations

import argparse
import json

from warpnerf.train.nerf_eval import evaluate_geometry


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--points", type=int, default=100_000)
    ap.add_argument("--val-images", type=int, default=20, help="0 = all")
    ap.add_argument("--clean", type=float, nargs="?", const=0.01, default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    res = evaluate_geometry(args.run, "materials", args.resolution, args.points,
                            clean=args.clean, views=args.val_images)  # fmt: skip
    print(json.dumps(res))
    if args.json:
        from warpnerf.outputs import write_json

        write_json(args.json, res)


if __name__ == "__main__":
    main()
