"""What a periodic checkpoint costs the training loop (train/loop.py): the time the loop is
blocked by a synchronous write (torch.save + fsync + rename, as before) against the background
writer's part (a host copy of the state, then a thread writes it), for a state the size of the
lego hash field's (12.2 M parameters and Adam's two moments: 147 MB), median of REPEATS.

    python3 experiments/overheads/checkpoint_cost.py [--device cpu|cuda] [--params 12207507]
        [--repeats 5] [--dir FOLDER]   (where the files go: the run folder's disk)
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--params", type=int, default=12_207_507)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--dir", default=None)
    a = p.parse_args()

    import torch

    from warpnerf.outputs import save_checkpoint
    from warpnerf.train.loop import BackgroundWriter, to_host

    sync = torch.cuda.synchronize if a.device.startswith("cuda") else (lambda: None)
    state = {
        k: torch.randn(a.params, device=a.device) for k in ("weights", "exp_avg", "exp_avg_sq")
    }
    state["history"] = {"loss": [0.1] * 5000, "seconds": [1.0] * 5000}
    with tempfile.TemporaryDirectory(dir=a.dir) as tmp:
        path = Path(tmp) / "checkpoint.pt"
        blocking_sync, blocking_bg, write_bg = [], [], []
        with BackgroundWriter() as writer:
            for _ in range(a.repeats):
                sync()
                t = time.perf_counter()
                save_checkpoint(path, state)
                blocking_sync.append(time.perf_counter() - t)
                sync()
                t = time.perf_counter()
                host = to_host(state)
                writer.submit(save_checkpoint, path, host)
                blocking_bg.append(time.perf_counter() - t)
                writer.wait()  # (what the thread took, overlapping training in a real run)
                write_bg.append(time.perf_counter() - t)
    mb = 3 * a.params * 4 / 1e6
    res = {"device": a.device, "state_mb": mb, "repeats": a.repeats,
           "sync_write_ms_median": 1e3 * statistics.median(blocking_sync),
           "background_blocking_ms_median": 1e3 * statistics.median(blocking_bg),
           "background_total_ms_median": 1e3 * statistics.median(write_bg)}  # fmt: skip
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
