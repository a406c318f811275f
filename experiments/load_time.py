"""Time to load a dataset split (issue 20): ``load_dataset(ROOT, SPLIT)`` with the image reading
pool limited to each of THREADS threads (1 = the sequential baseline), median of REPEATS.

    python experiments/load_time.py ../shared/data/lego ../shared/data/beer [--split train]
        [--threads 1,2,8] [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import time


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("roots", nargs="+")
    p.add_argument("--split", default="train")
    p.add_argument("--threads", default="1,2,8")
    p.add_argument("--repeats", type=int, default=3)
    a = p.parse_args()
    import warpnerf.data.images as images
    from warpnerf.data import load_dataset

    print("| split | " + " | ".join(f"{t} threads" for t in a.threads.split(",")) + " |")
    for root in a.roots:
        row = []
        for threads in (int(t) for t in a.threads.split(",")):
            images.os.cpu_count = lambda n=threads: n  # the pool's size (at most 8)
            times = []
            for _ in range(a.repeats):
                t0 = time.perf_counter()
                ds = load_dataset(root, a.split)
                times.append(time.perf_counter() - t0)
            row.append(f"{statistics.median(times):.2f} s")
        print(f"| {root} {a.split} {tuple(ds.images.shape)} | " + " | ".join(row) + " |")


if __name__ == "__main__":
    main()
