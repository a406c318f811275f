"""NeRF model, training loop, exact resume, evaluation and rendering on the tiny built-in scene."""

from __future__ import annotations

import json

import pytest
import torch

from warpnerf.errors import UserError
from warpnerf.fields.encoding import PositionalEncoding
from warpnerf.fields.nerf import NeRFField
from warpnerf.train import NeRFConfig, evaluate_run, render_run, train_nerf
from warpnerf.train.nerf import load_run
from warpnerf.train.nerf_eval import camera_path


def tiny(**kw) -> NeRFConfig:
    base = dict(
        iters=6,
        batch=128,
        n_coarse=16,
        n_layers=2,
        width=16,
        skip=1,
        pos_freqs=3,
        dir_freqs=1,
        near=1.0,
        far=4.0,
        builtin_size=12,
        val_every=3,
        val_images=1,
        ckpt_every=3,
        lr=5e-3,
        lr_final=5e-4,
    )
    base.update(kw)
    return NeRFConfig(**base)


def test_positional_encoding_values():
    enc = PositionalEncoding(2)
    x = torch.tensor([[0.5, -1.0, 2.0]])
    y = enc(x)
    assert y.shape == (1, 3 * 5) and enc.out_dim == 15
    xf = x.unsqueeze(-1) * torch.tensor([1.0, 2.0])
    assert torch.allclose(y, torch.cat([x, torch.sin(xf).flatten(1), torch.cos(xf).flatten(1)], -1))
    assert torch.equal(PositionalEncoding(0)(x), x)
    with pytest.raises(ValueError):
        PositionalEncoding(-1)


@pytest.mark.parametrize("view_dependence", [True, False])
def test_field_view_dependence(view_dependence):
    torch.manual_seed(0)
    f = NeRFField(
        n_layers=3, width=32, skip=2, pos_freqs=4, dir_freqs=2, view_dependence=view_dependence
    )
    p = torch.randn(64, 3)
    d1 = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
    d2 = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
    s1, c1 = f(p, d1)
    s2, c2 = f(p, d2)
    assert torch.equal(s1, s2)  # density never sees the direction
    assert (s1 >= 0).all() and ((c1 > 0) & (c1 < 1)).all()
    assert torch.equal(c1, c2) != view_dependence
    assert f.n_parameters() == sum(p.numel() for p in f.parameters())


HASH = dict(
    field="hash",
    hash_levels=3,
    hash_log2_size=8,
    hash_base_res=4,
    hash_max_res=16,
    hidden=8,
    grid_res=0,
)
# The hash field with an occupancy grid (coarse lattice so the CPU run stays small); the warm-up
# ends inside the 6 steps so both kinds of update (all cells, random subsets) run.
GRID = dict(HASH, grid_res=8, grid_every=2, grid_warmup=2, march_step=0.05, target_samples=2000)


VOLSDF = dict(field="volsdf", n_layers=2, width=24, skip=1, pos_freqs=2, dir_freqs=1)
HASH_SDF = dict(GRID, field="hash_sdf", c2f_every=2, target_samples=0)


@pytest.mark.parametrize(
    "n_fine, field",
    [(0, "mlp"), (8, "mlp"), (8, "hash"), (0, "grid"), (8, "volsdf"), (0, "hash_sdf"),
     (0, "appearance"), (0, "contract"), (0, "poses"), (8, "poses_mlp"), (0, "distortion")],
)  # fmt: skip
def test_resume_continues_exactly(tmp_path, n_fine, field):
    kw = {"hash": HASH, "grid": GRID, "volsdf": VOLSDF, "hash_sdf": HASH_SDF,
          "appearance": dict(GRID, appearance_dim=4),
          "contract": dict(GRID, contract="on", max_samples=256),
          "poses": dict(GRID, pose_refine=True, pose_lr=1e-2),
          "poses_mlp": dict(pose_refine=True, pose_lr=1e-2),
          "distortion": dict(GRID, contract="on", max_samples=256, distortion_loss=0.05),
          }.get(field, {})  # fmt: skip
    straight = train_nerf(
        tiny(n_fine=n_fine, **kw), tmp_path / "a", progress=False, log=lambda *a: 0
    )
    cfg = tiny(n_fine=n_fine, iters=3, lr_decay_steps=6, **kw)  # the straight run's schedule
    train_nerf(cfg, tmp_path / "b", progress=False, log=lambda *a: 0)
    resumed = train_nerf(
        tiny(iters=6), tmp_path / "b", resume=True, progress=False, log=lambda *a: 0
    )
    assert resumed["loss"] == straight["loss"]  # same batches, same jitter, same optimiser state
    a = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=True)
    b = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=True)
    assert a.get("batch") == b.get("batch")
    assert ("poses" in a["fields"]) == field.startswith("poses")
    for level in ("coarse", "fine", "grid", "poses"):
        if a["fields"].get(level) is None:
            continue
        for k, v in a["fields"][level].items():
            assert torch.equal(v, b["fields"][level][k]), (level, k)
    saved = json.loads((tmp_path / "b" / "config.json").read_text())
    assert saved["iters"] == 6 and saved["n_fine"] == n_fine


def test_runs_from_before_the_grid_load_without_one(tmp_path):
    train_nerf(tiny(iters=3, n_fine=8, **HASH), tmp_path / "r", progress=False, log=lambda *a: 0)
    cfg_path = tmp_path / "r" / "config.json"
    saved = json.loads(cfg_path.read_text())
    del saved["grid_res"], saved["max_samples"]  # as written before the grid existed
    cfg_path.write_text(json.dumps(saved))
    cfg, model, _ = load_run(tmp_path / "r")
    assert cfg.grid_res == 0 and model.grid is None and model.fine is not None
    with pytest.raises(UserError, match="max-samples"):
        train_nerf(tiny(**dict(GRID, max_samples=3)), tmp_path / "x", progress=False)
    with pytest.raises(UserError, match="occupancy grid"):  # a grid-only rendering setting
        evaluate_run(tmp_path / "r", max_images=1, march_step=0.1)
    m = evaluate_run(tmp_path / "r", max_images=1, chunk=50)
    assert m["chunk"] == 50 and m["march_step"] is None


def test_run_folder_guards(tmp_path):
    train_nerf(tiny(iters=3), tmp_path / "r", progress=False, log=lambda *a: 0)
    with pytest.raises(UserError, match="already holds a run"):
        train_nerf(tiny(iters=3), tmp_path / "r", progress=False)
    with pytest.raises(UserError, match="not a training run"):
        train_nerf(tiny(), tmp_path / "nothing", resume=True, progress=False)
    with pytest.raises(UserError, match="near"):
        train_nerf(tiny(near=3.0, far=2.0), tmp_path / "x", progress=False)


def test_eval_and_render_write_outputs(tmp_path):
    run = tmp_path / "r"
    train_nerf(tiny(n_fine=8), run, progress=False, log=lambda *a: 0)
    m = evaluate_run(run, "val", max_images=2)
    assert m["n_images"] == 2 and 0 < m["psnr"] < 60 and -1 <= m["ssim"] <= 1
    assert (run / "eval_val" / "metrics.json").exists() and (
        run / "eval_val" / "val_001.png"
    ).exists()
    import imageio.v3 as iio

    side = iio.imread(run / "eval_val" / "val_000.png")
    assert side.shape == (12, 36, 3)  # ground truth | prediction | depth
    r = render_run(run, "orbit", frames=3, size=(10, 8))
    assert r["frames"] == 3
    for f in ("rgb.mp4", "rgb.gif", "depth.mp4", "depth.gif", "rgb_002.png"):
        assert (run / "render_orbit" / f).stat().st_size > 0


def test_camera_path_circles_the_target():
    from warpnerf.data import orbit_views

    cams = orbit_views(20, radius=3.0)
    for kind in ("orbit", "spiral"):
        path = camera_path(cams, kind, 12)
        centres = path[:, :3, 3]
        assert torch.allclose(centres.norm(dim=-1), torch.full((12,), 3.0), atol=1e-3)
        fwd = -path[:, :3, 2]
        assert torch.allclose((fwd * -centres).sum(-1) / 3.0, torch.ones(12), atol=1e-4)
    with pytest.raises(UserError):
        camera_path(cams, "zigzag", 4)


@pytest.mark.slow
def test_builtin_scene_trains_to_psnr_floor(tmp_path, cli_launches):
    """CPU convergence on the built-in 24x24 scene: measured 25.74 / 25.73 dB val after 500
    steps with seeds 0 / 1 (27-37 s of training on a 2-core Xeon, 2026-11-22); the floor leaves
    about 1.7 dB of margin. Launched as the command launches on the CPU (one lane per block,
    ``cli_launches``): 25.73 / 25.86 dB with seeds 0 / 1, 30-33 s of CPU time against 45-54 s
    with the tests' real lanes (2026-12-02; seeds 2 and 3 stay under the floor either way:
    23.44 and 20.4 dB)."""
    cfg = tiny(
        iters=500,
        batch=512,
        n_coarse=32,
        n_layers=4,
        width=64,
        skip=2,
        pos_freqs=6,
        dir_freqs=2,
        builtin_size=24,
        val_every=500,
        val_images=4,
        ckpt_every=500,
    )
    hist = train_nerf(cfg, tmp_path / "r", progress=False, log=lambda *a: 0)
    assert hist["val_psnr"][-1] >= 24.0, hist["val_psnr"]


@pytest.mark.slow
def test_hash_field_trains_to_psnr_floor(tmp_path, cli_launches):
    """The hash field on the built-in 24x24 scene, CPU: measured 27.08 / 28.46 / 27.73 dB val
    after 600 steps with seeds 0 / 1 / 2 (22-23 s of training on a 2-core Xeon, 2026-11-22; it
    sits near 22.5 dB for the first ~200 steps); the floor leaves ~2 dB of margin. With one
    lane per block (``cli_launches``, as the command): 27.02 / 27.95 / 27.80 dB (2026-12-02;
    fewer steps fall short: 23.1 dB for seed 0 after 400)."""
    cfg = tiny(
        field="hash",
        hash_levels=4,
        hash_log2_size=12,
        hash_base_res=4,
        hash_max_res=32,
        hidden=32,
        grid_res=0,
        lr=1e-2,
        lr_final=1e-3,
        iters=600,
        batch=512,
        n_coarse=32,
        builtin_size=24,
        val_every=600,
        val_images=4,
        ckpt_every=600,
    )
    hist = train_nerf(cfg, tmp_path / "r", progress=False, log=lambda *a: 0)
    assert hist["val_psnr"][-1] >= 25.0, hist["val_psnr"]


def test_time_box_then_resume_gets_a_fresh_budget(tmp_path):
    hist = train_nerf(tiny(max_seconds=1e-9), tmp_path / "r", progress=False, log=lambda *a: 0)
    assert hist["step"][-1] == 1  # stopped by the time box, checkpoint written
    hist = train_nerf(tiny(iters=6), tmp_path / "r", resume=True, progress=False, log=lambda *a: 0)
    assert hist["step"][-1] == 6
    with pytest.raises(UserError, match="must be larger"):
        train_nerf(tiny(iters=6), tmp_path / "r", resume=True, progress=False)


def test_config_defaults_resolve_per_data():
    from warpnerf.data.synthetic import FAR, NEAR

    cfg = NeRFConfig().resolve()
    assert (cfg.near, cfg.far) == (NEAR, FAR)
    cfg = NeRFConfig(data="some/folder").resolve()
    assert (cfg.near, cfg.far) == (2.0, 6.0)
    with pytest.raises(UserError, match="t-threshold"):
        tiny(t_threshold=1.5).validate()
    # the hash field's defaults: a 128^3 grid, step = diagonal / 1024, and they validate
    cfg = NeRFConfig(data="some/folder", field="hash").validate()
    assert cfg.grid_res == 128 and cfg.max_samples == 1024
    assert cfg.march_step == pytest.approx(3.0 * 3**0.5 / 1024)
    assert NeRFConfig(data="some/folder").validate().grid_res == 0  # NeRF's MLP: no grid


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_signal_checkpoints_the_step_and_resume_is_exact(tmp_path, sig):
    """A SIGTERM/SIGINT during training (delivered here from the step-3 validation log) lets the
    step finish, checkpoints it and raises Interrupted; --resume then gives the same losses and
    weights as a run that was never interrupted."""
    import os
    import signal

    from warpnerf.errors import Interrupted

    straight = train_nerf(tiny(iters=6), tmp_path / "a", progress=False, log=lambda *a: 0)

    def log(*a):
        os.kill(os.getpid(), getattr(signal, sig))

    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(Interrupted, match=f"{sig} at step 3") as info:
        train_nerf(tiny(iters=6), tmp_path / "b", progress=False, log=log)
    assert info.value.step == 3 and signal.getsignal(signal.SIGINT) is before
    ckpt = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=True)
    assert ckpt["step"] == 3
    resumed = train_nerf(
        tiny(iters=6), tmp_path / "b", resume=True, progress=False, log=lambda *a: 0
    )
    assert resumed["loss"] == straight["loss"]
    a = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=True)
    b = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=True)
    for k, v in a["fields"]["coarse"].items():
        assert torch.equal(v, b["fields"]["coarse"][k]), k


def test_images_on_host_gives_the_same_training(tmp_path, device):
    """--images-on host (a CUDA run's images in host memory as 8-bit, each batch gathered there
    and turned into float32 on the GPU) trains as images on the device: the same batches, and
    targets within 0.5/255 (the built-in scene's float images rounded to 8 bits)."""
    if device.type != "cuda":
        pytest.skip("host-resident images are a CUDA matter (a CPU run's images are on the host)")
    from warpnerf.train.nerf import load_data

    host = load_data(tiny(device="cuda", images_on="host", **GRID), "train", uint8=True)
    dev = load_data(tiny(device="cuda", **GRID), "train")
    assert host.images.dtype == torch.uint8 and host.images.device.type == "cpu"
    assert (host.images.float() / 255 - dev.images.cpu()).abs().max() <= 0.5 / 255 + 1e-6
    runs = {}
    for where in ("device", "host"):
        cfg = tiny(device="cuda", images_on=where, **GRID)
        runs[where] = train_nerf(cfg, tmp_path / where, progress=False, log=lambda *a: 0)
    # (the same batches; targets rounded to 8 bits, so losses agree to about 1 %)
    torch.testing.assert_close(runs["host"]["loss"], runs["device"]["loss"], rtol=2e-2, atol=0)
    torch.testing.assert_close(
        runs["host"]["val_psnr"], runs["device"]["val_psnr"], rtol=2e-2, atol=0
    )


def test_uint8_images_load_as_rounded_floats(tmp_path):
    """uint8=True reads a split as 8-bit values (the float images x 255, rounded; a quarter of
    the memory) from files (Blender RGBA composited, then rounded) and the built-in scene; a
    CPU run's training split stays float32 (its images are on the host already)."""
    import numpy as np

    from warpnerf.data import load_dataset
    from warpnerf.data.images import read_all, to_uint8
    from warpnerf.train.nerf import load_data

    from ._scene import write_box_folder

    write_box_folder(tmp_path / "box", n_views=4, size=16, name="transforms_train.json")
    f = load_dataset(tmp_path / "box", "train")
    q = load_dataset(tmp_path / "box", "train", uint8=True)
    assert q.images.dtype == torch.uint8 and f.images.dtype == torch.float32
    assert torch.equal(q.images, torch.from_numpy(to_uint8(f.images.numpy())))
    assert (q.images.float() / 255 - f.images).abs().max() <= 0.5 / 255 + 1e-7
    b = load_dataset("builtin", "train", builtin_size=8, uint8=True)
    assert b.images.dtype == torch.uint8 and b.images.max() > 200
    out = read_all([0.0, 0.5, 1.0], lambda v: np.full((2, 2, 3), v, np.float32), dtype=np.uint8)
    assert out.dtype == np.uint8 and out[:, 0, 0, 0].tolist() == [0, 128, 255]
    cpu = load_data(tiny(images_on="host", **GRID), "train", uint8=True)
    assert cpu.images.dtype == torch.float32
    with pytest.raises(UserError, match="uint8"):
        load_dataset("builtin", "train", uint8=1)


def test_images_on_choice_and_host_index(tmp_path):
    from warpnerf.ops import random_pixels
    from warpnerf.train.nerf import images_stay_on_host

    img = torch.zeros(2, 4, 4, 3)
    assert not images_stay_on_host("cpu", img, "host")  # a CPU run's images are there already
    assert images_stay_on_host("cuda", img, "host")
    assert not images_stay_on_host("cuda:0", img, "device")
    with pytest.raises(UserError, match="--images-on"):
        tiny(images_on="disk").validate()
    from warpnerf.data.dataset import Dataset

    ds = Dataset(images=img, c2w=torch.eye(4).repeat(2, 1, 1), intrinsics=torch.ones(2, 4))
    kept = ds.to("meta", images=False)  # (any other device: the cameras move, the images stay)
    assert kept.c2w.device.type == "meta" and kept.images is img
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    cam, px, py, flat = random_pixels(3, 5, 4, 64, generator=g1)
    cam2, px2, py2, (flat2, host) = random_pixels(3, 5, 4, 64, generator=g2, host_index=True)
    assert torch.equal(flat, flat2) and torch.equal(flat, host) and host.device.type == "cpu"
    assert torch.equal(cam, cam2) and torch.equal(px, px2) and torch.equal(py, py2)


def test_eight_bit_images_train_as_their_float_values():
    """A training split held as uint8 (as --images-on host loads it) gives the training of its
    float values / 255 wherever it is held (here on the CPU, the path without the host gather)."""
    from warpnerf.data.cameras import orbit_views
    from warpnerf.data.dataset import Dataset
    from warpnerf.train.loop import bare_step
    from warpnerf.train.nerf import NeRFTask, build_model

    n, h, w = 3, 10, 12
    u8 = torch.randint(
        0, 256, (n, h, w, 3), dtype=torch.uint8, generator=torch.Generator().manual_seed(1)
    )
    losses = []
    for images in (u8, u8.float() / 255.0):
        torch.manual_seed(0)
        ds = Dataset(images=images, c2w=orbit_views(n, radius=4.0),
                     intrinsics=torch.tensor([[8.0, 8.0, w / 2, h / 2]]).repeat(n, 1))  # fmt: skip
        cfg = NeRFConfig(data="generated", field="hash", batch=32, aabb=1.5, near=2.0, far=6.0,
                         **{k: v for k, v in GRID.items() if k != "field"}).resolve()  # fmt: skip
        task = NeRFTask(cfg, build_model(cfg), ds, None, log=lambda *a: None)
        opt = task.optimizer(task.parameters(), cfg.lr)
        losses.append([float(bare_step(task, opt, i).detach()) for i in range(3)])
    assert losses[0] == pytest.approx(losses[1], rel=1e-6) and losses[0][0] < 1.0
