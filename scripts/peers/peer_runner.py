"""Runs one peer's own training in the peer's Python and renders the lego val views at the time
budgets. Started by ``run_peer.py`` (``PYTHON scripts/peers/peer_runner.py ...``); it never imports
warpnerf, so the peer may live in an environment of its own. Needs Python >= 3.8.

What it does, per peer (the peer's code is run from the user's checkout, never copied here):

- nerfacc: ``runpy`` runs ``PEER/examples/train_ngp_nerf_occ.py`` as ``__main__`` with its own
  flags (``--data_root STAGE --scene lego --train_split train``). Three attribute patches, all
  done before the script starts: ``SubjectLoader.WIDTH/HEIGHT`` (class constants, 800 in the
  example's loader) set to the images' size; ``SubjectLoader.__getitem__`` wrapped so that each
  training fetch (the first statement of a training step) checks the clock; and
  ``examples.utils.render_image_with_occgrid`` wrapped to keep a reference to the radiance field,
  the estimator and the rendering options the script passes. ``lpips.LPIPS`` is replaced by a
  stub: the example builds a VGG LPIPS net at start (a download) for its own final evaluation,
  which this runner never reaches.
- taichi-nerfs: ``runpy`` runs ``PEER/train.py`` with ``--root_dir STAGE --dataset_name nerf
  --downsample W/800 --exp_name warpnerf_peer`` (and ``--max_steps N`` when given), its cwd
  the work folder (it saves ``results/model.pth`` there); ``BaseDataset.__getitem__`` and
  ``modules.rendering.render`` are wrapped the same way.
- instant-ngp: drives the ``pyngp`` testbed the way ``scripts/run.py`` does without a GUI
  (``load_training_data``, ``frame()`` until ``training_step`` reaches ``n_steps``), and renders
  with ``set_nerf_camera_matrix`` + ``render``.

At the start of each training step the clock (synchronised, ``time.perf_counter``) is read; when
the training time first reaches a budget the current state renders every val view (the clock is
paused meanwhile, and model / estimator are put back in training mode afterwards), so one run
gives every budget, as ``warpnerf train --snapshots`` does. The run stops after the largest
budget, or when the peer's own schedule ends first (then the remaining budgets get the final
state, marked ``schedule_done``). Images are written as 8-bit RGB PNGs, already on white.
"""

from __future__ import annotations

import argparse
import glob
import importlib.util
import json
import math
import os
import re
import runpy
import sys
import time
import types
from pathlib import Path

EXIT_MISSING = 2  # a peer, a module or a GPU is missing: one line on stderr, no traceback

NERFACC_CLONE = (
    "git clone --recursive --branch v0.5.3 https://github.com/nerfstudio-project/nerfacc PEER_DIR"
)
TAICHI_CLONE = "git clone https://github.com/taichi-dev/taichi-nerfs PEER_DIR"
NGP_CLONE = "git clone --recursive https://github.com/NVlabs/instant-ngp PEER_DIR"
NGP_BUILD = (
    "build instant-ngp with its Python bindings: cd PEER_DIR && cmake . -B build "
    "-DCMAKE_BUILD_TYPE=RelWithDebInfo && cmake --build build --config RelWithDebInfo -j"
)

# per peer: files that must be in the checkout, (module, how to install it) pairs, packages
# whose versions are recorded
PEERS = {
    "nerfacc": {
        "files": [
            "examples/train_ngp_nerf_occ.py",
            "examples/utils.py",
            "examples/datasets/nerf_synthetic.py",
            "examples/radiance_fields/ngp.py",
        ],
        "clone": NERFACC_CLONE,
        "modules": [
            ("torch", "pip install torch (a CUDA build, e.g. torch==2.0.1 for cu118)"),
            ("nerfacc", "pip install nerfacc==0.5.3"),
            (
                "tinycudann",
                "pip install git+https://github.com/NVlabs/tiny-cuda-nn/#subdirectory=bindings/torch",
            ),
            ("imageio", "pip install -r PEER_DIR/examples/requirements.txt"),
            ("tqdm", "pip install -r PEER_DIR/examples/requirements.txt"),
            ("numpy", "pip install numpy"),
        ],
        "versions": ["torch", "nerfacc", "tinycudann", "numpy"],
    },
    "taichi-nerfs": {
        "files": [
            "train.py",
            "opt.py",
            "datasets/base.py",
            "datasets/nerf.py",
            "modules/rendering.py",
        ],
        "clone": TAICHI_CLONE,
        "modules": [
            ("torch", "pip install torch (a CUDA build)"),
            ("taichi", "pip install taichi==1.7.4"),
            ("einops", "pip install -r PEER_DIR/requirements.txt"),
            ("kornia", "pip install kornia==0.6.12 (0.9 lacks kornia.utils.grid)"),
            ("cv2", "pip install -r PEER_DIR/requirements.txt"),
            ("imageio", "pip install -r PEER_DIR/requirements.txt"),
            ("scipy", "pip install -r PEER_DIR/requirements.txt"),
            ("tqdm", "pip install tqdm"),
            ("torchmetrics", "pip install torchmetrics"),
            ("numpy", "pip install numpy"),
        ],
        "versions": ["torch", "taichi", "kornia", "torchmetrics", "numpy"],
    },
    "instant-ngp": {
        "files": ["scripts/run.py", "CMakeLists.txt"],
        "clone": NGP_CLONE,
        "modules": [
            ("numpy", "pip install numpy"),
            ("imageio", "pip install -r PEER_DIR/requirements.txt"),
        ],
        "versions": ["numpy", "imageio"],
    },
}


class Missing(Exception):
    """A peer, module or device is missing; the message is one line saying what to install."""


class Stop(Exception):
    """Raised from inside the peer's training loop once the last budget is rendered."""


def hint(text: str, peer_dir) -> str:
    return text.replace("PEER_DIR", str(peer_dir))


def pyngp_dirs(peer_dir: Path) -> list:
    """Folders under PEER/build*/ holding a pyngp extension (as scripts/common.py searches)."""
    found = []
    for ext in ("so", "pyd"):
        for p in glob.glob(
            os.path.join(str(peer_dir), "build*", "**", f"pyngp*.{ext}"), recursive=True
        ):
            found.append(os.path.dirname(p))
    return sorted(set(found))


def setup_path(peer: str, peer_dir: Path) -> None:
    """sys.path as the peer's own entry point sees it (installed packages keep precedence over
    the checkout's copy of the library; the checkout's example packages come first)."""
    if peer == "nerfacc":
        sys.path.insert(0, str(peer_dir / "examples"))  # radiance_fields, datasets
        sys.path.append(str(peer_dir))  # the `examples` namespace package
    elif peer == "taichi-nerfs":
        sys.path.insert(0, str(peer_dir))  # opt, gui, datasets, modules
    else:
        sys.path.extend(pyngp_dirs(peer_dir))


def check(peer: str, peer_dir: Path) -> dict:
    """Raises :class:`Missing` unless the checkout and the modules are there; returns versions."""
    spec = PEERS[peer]
    if not peer_dir.is_dir():
        raise Missing(f"{peer} checkout not found at {peer_dir}: {hint(spec['clone'], peer_dir)}")
    for f in spec["files"]:
        if not (peer_dir / f).is_file():
            raise Missing(
                f"{peer_dir} is not a {peer} checkout ({f} missing): "
                f"{hint(spec['clone'], peer_dir)}"
            )
    setup_path(peer, peer_dir)
    for mod, how in spec["modules"]:
        if importlib.util.find_spec(mod) is None:
            raise Missing(
                f"Python module {mod!r} not found in {sys.executable}: {hint(how, peer_dir)}"
            )
    if peer == "instant-ngp" and importlib.util.find_spec("pyngp") is None:
        raise Missing(
            f"no pyngp module under {peer_dir}/build*/ (the `instant-ngp` "
            f"binary alone is not enough): {hint(NGP_BUILD, peer_dir)}"
        )
    from importlib import metadata

    versions = {}
    for name in spec["versions"]:
        try:
            versions[name] = metadata.version(name)
        except Exception:  # not installed as a distribution (a source tree, a build folder)
            versions[name] = None
    return {"python": sys.version.split()[0], "executable": sys.executable, "versions": versions}


def own(peer_dir: Path, *mods) -> None:
    """Missing unless each module was imported from the checkout (not a same-named package)."""
    root = str(peer_dir.resolve())
    for m in mods:
        if not str(Path(m.__file__).resolve()).startswith(root):
            raise Missing(
                f"{m.__name__} was imported from {m.__file__}, not from {peer_dir}: "
                "another package of that name shadows the checkout's"
            )


def need_cuda():
    import torch

    if not torch.cuda.is_available():
        raise Missing(
            f"{sys.executable}: torch.cuda.is_available() is False: the peers need an "
            "NVIDIA GPU and a CUDA build of torch"
        )
    return torch


def to_uint8(img):
    import numpy as np

    img = np.nan_to_num(np.asarray(img, dtype=np.float64), nan=0.0)
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_png(path: Path, rgb) -> None:
    import imageio

    imageio.imwrite(str(path), to_uint8(rgb))


class Clock:
    """Training seconds between step starts, with the snapshot rendering paused out.

    ``render(folder) -> list of per-view milliseconds`` is set by the peer's driver once it has
    a model to render; ``sync`` waits for the GPU before the clock is read."""

    def __init__(self, budgets, out: Path, sync=lambda: None):
        self.budgets = sorted(budgets)
        self.k = 0  # next budget
        self.out = out
        self.sync = sync
        self.t0 = None
        self.paused = 0.0
        self.fetches = 0  # training fetches so far (torch peers: one per step)
        self.busy = False  # rendering a snapshot: our own data fetches are not steps
        self.render = None
        self.rows = []

    def seconds(self) -> float:
        self.sync()
        return time.perf_counter() - self.t0 - self.paused

    def start(self):
        self.sync()
        self.t0 = time.perf_counter()

    def step_start(self, step=None):
        """Called at the start of each training step (``step``: steps completed so far; for the
        torch peers the count of training fetches before this one)."""
        if self.busy:
            return
        if self.t0 is None:
            self.start()
        if step is None:
            step = self.fetches
            self.fetches += 1
        if self.k < len(self.budgets):
            s = self.seconds()
            if s >= self.budgets[self.k]:
                self.snapshot(step, s, done=False)
        if self.k >= len(self.budgets):
            raise Stop

    def fetch(self, training: bool):
        """A peer's dataset hands out an item: a training batch starts a step; anything else
        means its loop has ended (raises Stop once every budget is rendered)."""
        if training:
            self.step_start()
        else:
            self.training_ended()
            if not self.busy and self.k >= len(self.budgets):
                raise Stop

    def training_ended(self, step=None):
        """The peer's loop has ended (its own evaluation begins, or its script returned)."""
        if self.busy or self.t0 is None or self.k >= len(self.budgets):
            return
        self.snapshot(self.fetches if step is None else step, self.seconds(), done=True)

    def snapshot(self, step, seconds, done):
        if self.render is None:
            raise RuntimeError("a budget was reached before the peer rendered its first batch")
        crossed = [b for b in self.budgets[self.k :] if done or seconds >= b]
        folder = self.out / f"t{crossed[0]:g}s"
        folder.mkdir(parents=True, exist_ok=True)
        for p in folder.glob("val_*.png"):  # a previous run's images (our own names only)
            if re.fullmatch(r"val_\d{3,}\.png", p.name):
                p.unlink()
        print(
            f"[peer_runner] {seconds:.2f} s, step {step}: rendering the val views for "
            f"budget(s) {', '.join(f'{b:g}' for b in crossed)} s",
            flush=True,
        )
        t = time.perf_counter()
        self.busy = True
        try:
            ms = self.render(folder)
        finally:
            self.busy = False
            self.sync()
            self.paused += time.perf_counter() - t
        ms = sorted(ms)
        med = (ms[len(ms) // 2] + ms[(len(ms) - 1) // 2]) / 2 if ms else None
        for b in crossed:
            self.rows.append(
                {
                    "budget_s": b,
                    "step": int(step),
                    "train_seconds": seconds,
                    "render_ms_median": med,
                    "dir": folder.name,
                    "schedule_done": bool(done),
                }
            )
        self.k += len(crossed)
        self.save()

    def save(self):
        p = self.out / "snapshots.json"
        tmp = p.with_name(".snapshots.json.tmp")
        tmp.write_text(json.dumps({"rows": self.rows}, indent=2) + "\n")
        os.replace(tmp, p)


def image_size(stage: Path):
    import imageio

    with open(stage / "transforms_train.json") as f:
        frame = json.load(f)["frames"][0]
    img = imageio.imread(str(stage / (frame["file_path"] + ".png")))
    return int(img.shape[1]), int(img.shape[0])


def run_script(path: Path, argv: list, cwd: Path):
    sys.argv = [str(path), *argv]
    os.chdir(cwd)
    print(f"[peer_runner] {path} {' '.join(argv)}", flush=True)
    runpy.run_path(str(path), run_name="__main__")


def run_nerfacc(a, clock: Clock):
    torch = need_cuda()
    clock.sync = torch.cuda.synchronize
    # Build / load nerfacc's CUDA extension before the clock starts (a cold JIT build takes
    # minutes; it is cached in torch's extension folder afterwards).
    from nerfacc.cuda import _backend

    if getattr(_backend, "_C", None) is None:
        raise Missing(
            "nerfacc's CUDA extension is unavailable (no nvcc on PATH for its JIT "
            "build): install the CUDA toolkit matching torch, or a prebuilt wheel: pip "
            "install nerfacc==0.5.3 -f https://nerfacc-bucket.s3.us-west-2.amazonaws.com"
            "/whl/torch-2.0.0_cu118.html"
        )
    stub = types.ModuleType("lpips")

    class LPIPS(torch.nn.Module):  # never called: the run stops before the example's evaluation
        def __init__(self, *args, **kwargs):
            super().__init__()

        def forward(self, x, y):
            return torch.zeros((), device=x.device)

    stub.LPIPS = LPIPS
    sys.modules["lpips"] = stub
    try:
        import examples.utils as eu
        from datasets import nerf_synthetic
    except ImportError as e:
        raise Missing(f"cannot import the example's modules from {a.peer_dir}: {e}") from None
    own(a.peer_dir, eu, nerf_synthetic)
    loader_cls = nerf_synthetic.SubjectLoader
    w, h = image_size(a.stage)
    loader_cls.WIDTH, loader_cls.HEIGHT = w, h  # the example's loader assumes 800 x 800
    state = {}
    orig_render = eu.render_image_with_occgrid

    def render_hook(radiance_field, estimator, rays, *args, **kwargs):
        if radiance_field.training:
            state.update(rf=radiance_field, est=estimator, args=args, kwargs=dict(kwargs))
        return orig_render(radiance_field, estimator, rays, *args, **kwargs)

    eu.render_image_with_occgrid = render_hook
    orig_get = loader_cls.__getitem__

    def getitem(self, index):
        clock.fetch(self.training)
        return orig_get(self, index)

    loader_cls.__getitem__ = getitem

    def render(folder: Path):
        if "val" not in state:
            state["val"] = loader_cls(
                subject_id="lego",
                root_fp=str(a.stage.parent),
                split="val",
                num_rays=None,
                device="cuda:0",
            )
        rf, est, loader = state["rf"], state["est"], state["val"]
        kwargs = dict(state["kwargs"])
        rf.eval()
        est.eval()
        ms = []
        try:
            with torch.no_grad():
                for i in range(len(loader)):
                    torch.cuda.synchronize()
                    t = time.perf_counter()
                    data = loader[i]
                    kwargs["render_bkgd"] = data["color_bkgd"]  # white at inference
                    rgb = orig_render(rf, est, data["rays"], *state["args"], **kwargs)[0]
                    torch.cuda.synchronize()
                    ms.append(1e3 * (time.perf_counter() - t))
                    write_png(folder / f"val_{i:03d}.png", rgb.float().cpu().numpy())
        finally:
            rf.train()
            est.train()
        return ms

    clock.render = render
    argv = ["--data_root", str(a.stage.parent), "--scene", "lego", "--train_split", "train"]
    run_script(a.peer_dir / "examples" / "train_ngp_nerf_occ.py", argv + a.peer_args, a.work)


def run_taichi(a, clock: Clock):
    torch = need_cuda()
    clock.sync = torch.cuda.synchronize
    try:
        import modules.rendering as rendering
        from datasets import base, dataset_dict
        from datasets.ray_utils import get_rays
    except ImportError as e:
        raise Missing(f"cannot import its modules from {a.peer_dir}: {e}") from None
    own(a.peer_dir, rendering, base)
    w, h = image_size(a.stage)
    downsample = w / 800.0  # NeRFDataset: w = h = int(800 * downsample), focal scaled alike
    if int(800 * downsample) != w or w != h:
        raise Missing(
            f"taichi-nerfs' nerf loader needs square images of 800 * downsample pixels; got {w}x{h}"
        )
    state = {}
    orig_render = rendering.render

    def render_hook(model, *args, **kwargs):
        if not kwargs.get("test_time", False):
            state.update(model=model, exp_step_factor=kwargs.get("exp_step_factor", 0))
        return orig_render(model, *args, **kwargs)

    rendering.render = render_hook
    orig_get = base.BaseDataset.__getitem__

    def getitem(self, idx):
        clock.fetch(self.split.startswith("train"))
        return orig_get(self, idx)

    base.BaseDataset.__getitem__ = getitem

    def render(folder: Path):
        if "val" not in state:
            ds = dataset_dict["nerf"](root_dir=str(a.stage), split="val", downsample=downsample)
            state["val"] = ds.to("cuda")
        ds, model = state["val"], state["model"]
        vw, vh = ds.img_wh
        model.eval()
        ms = []
        try:
            with torch.no_grad():
                for i in range(len(ds.poses)):
                    torch.cuda.synchronize()
                    t = time.perf_counter()
                    with torch.autocast(device_type="cuda", dtype=torch.float16):  # as train.py
                        rays_o, rays_d = get_rays(ds.directions, ds.poses[i])
                        res = orig_render(
                            model,
                            rays_o,
                            rays_d,
                            test_time=True,
                            exp_step_factor=state["exp_step_factor"],
                        )
                    rgb = res["rgb"].float().reshape(vh, vw, 3)
                    torch.cuda.synchronize()
                    ms.append(1e3 * (time.perf_counter() - t))
                    write_png(folder / f"val_{i:03d}.png", rgb.cpu().numpy())
        finally:
            model.train()
        return ms

    clock.render = render
    argv = [
        "--root_dir",
        str(a.stage),
        "--dataset_name",
        "nerf",
        "--downsample",
        f"{downsample:g}",
        "--exp_name",
        "warpnerf_peer",
    ]
    if a.max_steps:
        argv += ["--max_steps", str(a.max_steps)]
    run_script(a.peer_dir / "train.py", argv + a.peer_args, a.work)


def linear_to_srgb(x):
    import numpy as np

    x = np.clip(x, 0.0, 1.0)
    return np.where(x > 0.0031308, 1.055 * np.power(x, 1.0 / 2.4) - 0.055, 12.92 * x)


def run_ngp(a, clock: Clock):
    import numpy as np
    import pyngp as ngp

    p = argparse.ArgumentParser(prog="instant-ngp peer arguments")
    p.add_argument("--network", default="", help="network config (run.py --network)")
    p.add_argument("--spp", type=int, default=8, help="samples per pixel of the val renders")
    extra = p.parse_args(a.peer_args)
    os.chdir(a.work)
    testbed = ngp.Testbed()
    testbed.root_dir = str(a.peer_dir)
    # a folder would load every *.json in it (val included): name the train file
    testbed.load_training_data(str(a.stage / "transforms_train.json"))
    if extra.network:
        testbed.reload_network_from_file(extra.network)
    testbed.shall_train = True
    with open(a.stage / "transforms_val.json") as f:
        val = json.load(f)
    w, h = image_size(a.stage)
    fov = float(val["camera_angle_x"]) * 180.0 / math.pi

    def render(folder: Path):
        saved = (
            list(testbed.background_color),
            testbed.snap_to_pixel_centers,
            testbed.nerf.render_min_transmittance,
            testbed.shall_train,
        )
        # as run.py's --test_transforms evaluation (snapped pixel centres, transmittance 1e-4),
        # but on a transparent background: the premultiplied linear RGBA is composited on white
        # in sRGB below, as the ground truth is
        testbed.background_color = [0.0, 0.0, 0.0, 0.0]
        testbed.snap_to_pixel_centers = True
        testbed.nerf.render_min_transmittance = 1e-4
        testbed.shall_train = False
        testbed.fov_axis = 0
        testbed.fov = fov
        ms = []
        try:
            for i, fr in enumerate(val["frames"]):
                t = time.perf_counter()
                testbed.set_nerf_camera_matrix(np.matrix(fr["transform_matrix"])[:-1, :])
                img = np.asarray(testbed.render(w, h, extra.spp, True), dtype=np.float64)
                ms.append(1e3 * (time.perf_counter() - t))
                alpha = np.clip(img[..., 3:4], 0.0, 1.0)
                straight = np.divide(
                    img[..., :3], alpha, out=np.zeros_like(img[..., :3]), where=alpha > 0
                )
                write_png(
                    folder / f"val_{i:03d}.png", linear_to_srgb(straight) * alpha + (1.0 - alpha)
                )
        finally:
            bg, snap, tmin, train = saved
            testbed.background_color = bg
            testbed.snap_to_pixel_centers = snap
            testbed.nerf.render_min_transmittance = tmin
            testbed.shall_train = train
        return ms

    clock.render = render
    n_steps = a.max_steps or 35000  # run.py's default when --n_steps is not given
    clock.start()
    while testbed.frame():
        step = testbed.training_step
        if step >= n_steps:
            break
        clock.step_start(step)
    clock.training_ended(testbed.training_step)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("peer", choices=sorted(PEERS))
    p.add_argument("--peer-dir", type=Path, required=True)
    p.add_argument("--check", action="store_true", help="check the installation, print versions")
    p.add_argument("--stage", type=Path, help="the staged lego folder (STAGE_ROOT/lego)")
    p.add_argument("--work", type=Path, help="working folder (the peer's cwd)")
    p.add_argument("--out", type=Path, help="renders and snapshots.json go here")
    p.add_argument("--budgets", help="comma-separated seconds")
    p.add_argument("--max-steps", type=int, default=0)
    argv = sys.argv[1:] if argv is None else argv
    peer_args = argv[argv.index("--") + 1 :] if "--" in argv else []
    argv = argv[: argv.index("--")] if "--" in argv else argv
    a = p.parse_args(argv)
    a.peer_args = peer_args
    a.peer_dir = a.peer_dir.absolute()
    try:
        info = check(a.peer, a.peer_dir)
        if a.check:
            print(json.dumps(info))
            return 0
        a.out.mkdir(parents=True, exist_ok=True)
        a.work.mkdir(parents=True, exist_ok=True)
        clock = Clock([float(b) for b in a.budgets.split(",")], a.out)
        run = {"nerfacc": run_nerfacc, "taichi-nerfs": run_taichi, "instant-ngp": run_ngp}
        try:
            run[a.peer](a, clock)
        except Stop:
            pass
        clock.training_ended()  # the schedule ended before the last budget
        clock.save()
    except Missing as e:
        print(f"run_peer: {a.peer}: {e}", file=sys.stderr)
        return EXIT_MISSING
    return 0


if __name__ == "__main__":
    sys.exit(main())
