"""Issue 47: the training step with and without the march's occupied-box cut, for an A/B in one
lease (the cut is always on in the library; ``uncut`` drops it here by wrapping the grid's march).

    python3 experiments/overheads/march_cut_ab.py {cut,uncut} [profile_train_step.py args] -- \
        train nerf --data lego --device cuda

Everything after the mode goes to ``scripts/profile_train_step.py`` unchanged; both modes march
the same samples (tests/test_march_work.py: the cut is bit-identical), so only the time differs.
"""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "profile_train_step.py"


def main() -> None:
    if len(sys.argv) < 2 or sys.argv[1] not in ("cut", "uncut"):
        sys.exit(f"usage: {Path(__file__).name} {{cut,uncut}} [profile_train_step.py args]")
    mode = sys.argv.pop(1)
    if mode == "uncut":
        from warpnerf.ops import occupancy as ops

        march = ops.march_rays

        def uncut(*args, occupied=None, **kwargs):  # the march before the cut
            return march(*args, **kwargs)

        ops.march_rays = uncut  # (warpnerf.occupancy reads it from the module at each call)
    sys.argv[0] = str(SCRIPT)
    runpy.run_path(str(SCRIPT), run_name="__main__")


if __name__ == "__main__":
    main()
