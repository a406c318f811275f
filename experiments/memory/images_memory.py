"""Peak GPU memory of NeRF training against the number of training images (issue 20: "GPU memory
of training independent of the number of images"). A generated capture (random pixel values,
cameras on a sphere looking at the origin; the content does not matter for memory) of N images
of W x H is held as the training split with ``--images-on host`` (pixels gathered on the host
each step) or ``device`` (all images on the GPU); a hash field + occupancy grid trains STEPS steps
and the peak of ``torch.cuda.max_memory_allocated`` over the training is reported, per N.

    python3 experiments/memory/images_memory.py --images 100,2000 --width 1920 --height 1080 \
        --steps 40 [--images-on host] [--dtype uint8|float32] [--json out.json]
"""

from __future__ import annotations

import argparse
import time


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--images", default="100,2000", help="numbers of images, comma-separated")
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--images-on", default="host", choices=("host", "device"))
    p.add_argument("--dtype", default="uint8", choices=("uint8", "float32"),
                   help="how the images are held: 8-bit, as `--images-on host` keeps a loaded "
                   "capture (the default), or float32")  # fmt: skip
    p.add_argument("--json", default=None)
    a = p.parse_args()
    counts = [int(x) for x in a.images.split(",")]
    if min(counts) < 1 or a.width < 1 or a.height < 1 or a.steps < 1:
        raise SystemExit("images, width, height and steps must be positive")

    import torch

    from warpnerf.data.cameras import orbit_views
    from warpnerf.data.dataset import Dataset
    from warpnerf.train import NeRFConfig
    from warpnerf.train.loop import bare_step
    from warpnerf.train.nerf import NeRFTask, build_model

    if not torch.cuda.is_available():
        raise SystemExit("images_memory.py measures GPU memory: it needs CUDA")
    rows = []
    for n in counts:
        t0 = time.perf_counter()
        u8 = a.dtype == "uint8"
        images = torch.empty(n, a.height, a.width, 3, dtype=torch.uint8 if u8 else torch.float32)
        gen = torch.Generator().manual_seed(n)
        for i in range(0, n, 16):  # (in slices: a single torch.rand of tens of GB is slow)
            shape = images[i : i + 16].shape
            images[i : i + 16] = (torch.randint(0, 256, shape, generator=gen, dtype=torch.uint8)
                                  if u8 else torch.rand(shape, generator=gen))  # fmt: skip
        f = 0.6 * a.width
        ds = Dataset(
            images=images,
            c2w=orbit_views(n, radius=4.0),
            intrinsics=torch.tensor([[f, f, a.width / 2, a.height / 2]]).repeat(n, 1),
        )
        made_s = time.perf_counter() - t0
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
        cfg = NeRFConfig(data="generated", field="hash", device="cuda", tf32=True, batch=4096,
                         target_samples=262144, aabb=1.5, near=2.0, far=6.0,
                         images_on=a.images_on)  # fmt: skip
        train = ds.to("cuda", images=a.images_on == "device")  # (cameras on the GPU)
        model = build_model(cfg)
        task = NeRFTask(cfg, model, train, None, log=lambda *x: None)
        opt = task.optimizer(task.parameters(), cfg.lr)
        t1 = time.perf_counter()
        for i in range(a.steps):
            float(bare_step(task, opt, i))
        torch.cuda.synchronize()
        step_ms = 1e3 * (time.perf_counter() - t1) / a.steps
        peak = torch.cuda.max_memory_allocated() - base
        rows.append({"images": n, "width": a.width, "height": a.height, "images_on": a.images_on,
                     "dtype": a.dtype, "host_gib": images.numel() * images.element_size() / 2**30,
                     "peak_gpu_mib": peak / 2**20,
                     "step_ms": step_ms, "make_s": made_s})  # fmt: skip
        print(rows[-1], flush=True)
        del task, model, opt, train, ds, images
    from warpnerf.bench import markdown_rows

    print(markdown_rows(rows, [
        ("images", "{images}"), ("W x H", "{width}x{height}"), ("images on", "{images_on}"),
        ("host GiB", "{host_gib:.1f}"), ("peak GPU MiB", "{peak_gpu_mib:.0f}"),
        ("step ms", "{step_ms:.1f}"),
    ]))  # fmt: skip
    if a.json:
        from warpnerf.outputs import write_json

        write_json(a.json, {"rows": rows, "steps": a.steps, "device": torch.cuda.get_device_name()})


if __name__ == "__main__":
    main()
