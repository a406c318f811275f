"""The loss terms' one home (warpnerf/train/losses.py) and the recipe's colour options (issue
44): the eager and the static-shape step compute the same loss from the same terms (Huber,
random backgrounds over RGBA pixels), the random-background composite is exact against its
twin, and Huber's gradient matches instant-ngp's closed form."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from tests.test_datasets import _png, make_blender
from tests.test_graph_step import _params, _task, _train
from warpnerf.data import load_dataset
from warpnerf.errors import UserError
from warpnerf.train.losses import (
    OPACITY_EPS,
    composite_target,
    eikonal_term,
    huber,
    opacity_term,
    photometric,
    ray_mean,
)  # fmt: skip
from warpnerf.train.nerf import NeRFConfig, NeRFTask, resolve_data
from warpnerf.train.nerf_config import VolSDFConfig
from warpnerf.train.recipe import HUBER_DELTA, mask_weight, random_background, wants_alpha


def test_huber_is_instant_ngps_and_its_gradient_matches_the_closed_form():
    x = torch.linspace(-0.5, 0.5, 101, dtype=torch.float64, requires_grad=True)
    t = torch.zeros_like(x)
    h = huber(x, t)
    # the twin: torch's smooth L1 with beta = delta (instant-ngp's Huber, tiny-cuda-nn's loss)
    twin = torch.nn.functional.smooth_l1_loss(x, t, beta=HUBER_DELTA, reduction="none")
    assert torch.allclose(h, twin, atol=1e-15)
    (g,) = torch.autograd.grad(h.sum(), x)
    closed = (x / HUBER_DELTA).clamp(-1, 1).detach()
    assert torch.allclose(g, closed, atol=1e-12)
    xs = torch.randn(6, 3, dtype=torch.float64, requires_grad=True) * 0.2
    ts = torch.randn(6, 3, dtype=torch.float64) * 0.2
    assert torch.autograd.gradcheck(lambda a: huber(a, ts), (xs.detach().requires_grad_(),))


def test_photometric_masked_mean_equals_the_mean_over_used_rays():
    torch.manual_seed(0)
    rgb, target = torch.rand(10, 3, dtype=torch.float64), torch.rand(10, 3, dtype=torch.float64)
    mask = torch.zeros(10, dtype=torch.float64)
    mask[:6] = 1
    n = torch.tensor(6.0, dtype=torch.float64)
    for kind in ("mse", "huber"):
        full, mse_full = photometric(rgb[:6], target[:6], kind)
        masked, mse_masked = photometric(rgb, target, kind, mask, n)
        assert torch.allclose(full, masked) and torch.allclose(mse_full, mse_masked)
    assert torch.allclose(photometric(rgb, target)[0], ((rgb - target) ** 2).mean())
    assert torch.allclose(ray_mean(rgb[:, 0], mask, n), rgb[:6, 0].mean())
    with pytest.raises(ValueError, match="mse or huber"):
        photometric(rgb, target, "l1")


def test_eikonal_term_with_a_device_count_equals_the_host_test():
    class F:
        def eikonal(self, x):
            return (x**2).sum(-1).mean()

    box = torch.rand(5, 3)
    aux = torch.tensor(0.3)
    assert torch.allclose(eikonal_term(F(), box, aux), eikonal_term(F(), box, aux, torch.tensor(4)))
    assert torch.allclose(eikonal_term(F(), box, aux, torch.tensor(0)), F().eikonal(box))
    assert torch.allclose(eikonal_term(F(), box), F().eikonal(box))


def test_random_background_composite_is_exact_for_rgba_pixels(tmp_path):
    """An RGBA Blender split loaded with its alpha: images composited onto white, and the
    target over any background equals the twin's straight composite of the PNG's pixels,
    rgb a + c (1 - a), in float32 (and within half a level when the split is 8-bit)."""
    root = make_blender(tmp_path, n=2, w=12, h=8)
    rng = np.random.default_rng(3)
    raw = rng.integers(0, 256, (8, 12, 4)).astype(np.uint8)
    raw[0, :4, 3] = 0  # transparent, opaque and partial pixels
    raw[1, :4, 3] = 255
    _png(root / "train" / "r_0.png", raw)
    ds = load_dataset(root, "train", alpha=True)
    assert ds.alpha is not None and ds.alpha.shape == ds.images.shape[:3]
    ds8 = load_dataset(root, "train", alpha=True, uint8=True)
    assert ds8.alpha.dtype == torch.uint8 and np.array_equal(ds8.alpha[0].numpy(), raw[..., 3])
    assert load_dataset(root, "train").alpha is None  # (only when asked for)
    f = raw.astype(np.float64) / 255.0
    bg = torch.rand(8 * 12, 3, generator=torch.Generator().manual_seed(1))
    twin = f[..., :3] * f[..., 3:] + bg.double().numpy().reshape(8, 12, 3) * (1 - f[..., 3:])
    got = composite_target(ds.images[0].reshape(-1, 3), ds.alpha[0].reshape(-1), bg, 1.0)
    assert np.abs(got.double().numpy().reshape(8, 12, 3) - twin).max() < 1e-6
    px8 = ds8.images[0].reshape(-1, 3).float() / 255
    got8 = composite_target(px8, ds8.alpha[0].reshape(-1).float() / 255, bg, 1.0)
    assert np.abs(got8.double().numpy().reshape(8, 12, 3) - twin).max() <= 0.5 / 255 + 1e-6
    # downscaled: the area average of the composite is the composite of the area averages
    d2 = load_dataset(root, "train", alpha=True, downscale=2)
    bg2 = bg.reshape(8, 12, 3)[::2, ::2].reshape(-1, 3)
    got2 = composite_target(d2.images[0].reshape(-1, 3), d2.alpha[0].reshape(-1), bg2, 1.0)
    twin2 = (f[..., :3] * f[..., 3:]).reshape(4, 2, 6, 2, 3).mean((1, 3))
    twin2 = twin2 + bg2.double().numpy().reshape(4, 6, 3) * (
        1 - f[..., 3].reshape(4, 2, 6, 2).mean((1, 3))[..., None]
    )
    assert np.abs(got2.double().numpy().reshape(4, 6, 3) - twin2).max() < 1e-6


def test_random_background_mode_and_its_refusal_without_a_grid():
    class DS:
        alpha = torch.ones(1)

    class Opaque:
        alpha = None

    cfg = resolve_data(NeRFConfig(data="builtin", field="hash", random_background="auto"))
    assert random_background(cfg, DS()) and not random_background(cfg, Opaque())
    assert random_background(dataclasses.replace(cfg, random_background="on"), Opaque())
    assert not random_background(dataclasses.replace(cfg, random_background="off"), DS())
    with pytest.raises(UserError, match="--random-background needs"):
        NeRFConfig(data="builtin", field="mlp", random_background="on").validate()


HUBER_BG = dict(random_background="on", photometric_loss="huber")
MASK_BG = dict(random_background="on", mask_loss=0.5)  # the built-in scene's own alpha


def test_opacity_term_is_the_clamped_cross_entropy_and_its_gradient_checks():
    g = torch.Generator().manual_seed(3)
    o = torch.rand(64, generator=g, dtype=torch.float64)
    o[:4] = torch.tensor([0.0, 1.0, 1e-9, 1 - 1e-12], dtype=torch.float64)  # saturated rays
    a = torch.rand(64, generator=g, dtype=torch.float64)
    a[:4] = torch.tensor([1.0, 0.0, 0.5, 1.0], dtype=torch.float64)
    want = torch.nn.functional.binary_cross_entropy(o.clamp(OPACITY_EPS, 1 - OPACITY_EPS), a)
    got = opacity_term(o, a)
    assert torch.isfinite(got) and got.item() == pytest.approx(want.item(), rel=1e-12)
    x = o[4:].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: opacity_term(t, a[4:]), (x,))
    y = o.clone().requires_grad_(True)
    opacity_term(y, a).backward()
    assert torch.isfinite(y.grad).all() and (y.grad[:2] == 0).all()  # clamped: no push further
    # the masked mean over used slots equals the mean over those rays alone
    m = (torch.arange(64) < 40).to(torch.float64)
    n = torch.tensor(40.0, dtype=torch.float64)
    assert opacity_term(o, a, m, n).item() == pytest.approx(opacity_term(o[:40], a[:40]).item())
    # --mask-pixels background: the cross-entropy of the pixels with alpha below 0.5 alone, the
    # mean over all rays; the object's rays get no push
    bg = a < 0.5
    want = torch.nn.functional.binary_cross_entropy(
        o.clamp(OPACITY_EPS, 1 - OPACITY_EPS)[bg], a[bg], reduction="sum"
    ) / len(a)
    assert opacity_term(o, a, pixels="background").item() == pytest.approx(want.item(), rel=1e-12)
    z = o.clone().requires_grad_(True)
    opacity_term(z, a, pixels="background").backward()
    live = bg & (o > 0.01) & (o < 0.99)  # (unclamped: pushed towards its alpha)
    assert (z.grad[~bg] == 0).all() and torch.equal(z.grad[live].sign(), (o - a)[live].sign())
    assert torch.autograd.gradcheck(lambda t: opacity_term(t, a[4:], pixels="background"), (x,))
    with pytest.raises(ValueError, match="pixels"):
        opacity_term(o, a, pixels="object")


def test_the_built_in_scene_renders_its_alpha():
    """The built-in scene's alpha is its rendered opacity: where it is 0 the white background
    shows through, and the images are the straight colours composited onto white."""
    from warpnerf.data.dataset import LoadRequest
    from warpnerf.data.synthetic import _load_builtin

    ds = _load_builtin(LoadRequest(root="builtin", split="train", alpha=True, builtin_size=24))
    assert ds.alpha is not None and ds.alpha.shape == ds.images.shape[:3]
    a = ds.alpha
    assert float(a.min()) >= 0 and float(a.max()) <= 1
    assert 0.05 < float((a > 0.5).float().mean()) < 0.95  # objects and background both seen
    assert float((ds.images[a < 1e-4] - 1).abs().max()) < 1e-3  # empty rays: white
    no = _load_builtin(LoadRequest(root="builtin", split="train", builtin_size=24))
    assert no.alpha is None and torch.equal(no.images, ds.images)
    u8 = _load_builtin(LoadRequest(root="builtin", split="val", alpha=True, uint8=True,
                                   builtin_size=24))  # fmt: skip
    assert u8.alpha.dtype == torch.uint8


def test_mask_loss_defaults_and_its_absence_without_alpha():
    """`train volsdf` weighs the opacity loss 0.1 (random backgrounds stay off: measured worse
    on materials); `train nerf` has no mask loss; a split without alpha has no mask loss, and the
    log says so."""
    v, n = VolSDFConfig(), NeRFConfig()
    assert (v.mask_loss, v.random_background) == (0.1, "off")
    assert (n.mask_loss, n.random_background) == (0.0, "off")

    class DS:
        alpha = torch.ones(1)

    class Opaque:
        alpha = None

    assert mask_weight(v, DS()) == 0.1 and mask_weight(v, Opaque()) == 0.0
    with pytest.raises(UserError, match="mask-loss"):
        NeRFConfig(data="builtin", mask_loss=-1.0).validate()
    with pytest.raises(UserError, match="mask-loss"):
        NeRFConfig(data="builtin", mask_loss=float("nan")).validate()
    assert v.mask_pixels == "all"
    with pytest.raises(UserError, match="mask-pixels"):
        NeRFConfig(data="builtin", mask_pixels="object").validate()
    from tests.test_graph_step import SMALL
    from warpnerf.train.nerf import build_model, load_data

    cfg = resolve_data(NeRFConfig(**{**SMALL, "mask_loss": 0.2}, device="cpu"))
    lines = []
    assert wants_alpha(cfg) and not wants_alpha(resolve_data(NeRFConfig(**SMALL, device="cpu")))
    train = load_data(cfg, "train", alpha=True)
    assert train.alpha is not None
    opaque = dataclasses.replace(train, alpha=None)
    task = NeRFTask(cfg, build_model(cfg), opaque, None, log=lines.append)
    assert task.mask_w == 0 and task.flat_alpha is None
    assert any("no alpha" in s for s in lines)


@pytest.mark.parametrize("kw", [dict(photometric_loss="huber"), HUBER_BG, MASK_BG,
                                {**MASK_BG, "mask_pixels": "background"}])  # fmt: skip
def test_static_step_trains_as_the_eager_step_with_the_recipes_terms(kw):
    """One definition of the loss: with Huber and random backgrounds over RGBA pixels (an alpha
    given to the built-in scene's pixels), the static-shape step (the body a CUDA graph holds)
    gives the eager step's losses and parameters."""
    tasks = [_task("cpu", **kw), _task("cpu", **kw)]
    for task in tasks:
        if task.random_bg and not task.mask_w:  # a random alpha for the built-in pixels
            g = torch.Generator().manual_seed(5)
            task.flat_alpha = torch.rand(task.flat.shape[0], generator=g)
    eager, static = tasks
    la, _, _ = _train(eager, 10)
    lb, _, _ = _train(static, 10, static=True, force=(4096, 1 << 16, 1 << 15))
    assert lb == pytest.approx(la, rel=1e-5)
    # (Huber's gradient is the residual / 0.1: float32 round-off between the two bodies' sums
    # reaches the parameters 10x larger than with the squared error; Adam's steps are 1e-2)
    assert (_params(eager) - _params(static)).abs().max() < 1e-5
    # the terms do reach the loss: the plain recipe trains to other parameters
    plain = _task("cpu")
    _train(plain, 4)
    again = _task("cpu", **kw)
    again.flat_alpha = eager.flat_alpha
    _train(again, 4)
    assert (_params(plain) - _params(again)).abs().max() > 1e-4


def _config_of(argv, monkeypatch, cuda: bool):
    from warpnerf.cli.parser import build_parser
    from warpnerf.cli.train import nerf_config_from_args

    monkeypatch.setattr(torch.cuda, "is_available", lambda: cuda)
    args = build_parser().parse_args(["train", *argv, "--out", "unused"])
    return nerf_config_from_args(args)


def test_the_plain_command_on_cuda_trains_the_measured_gpu_recipe(monkeypatch):
    """`warpnerf train nerf --data lego --device cuda` is the headline recipe: the hash field,
    2^19 samples a step from 4,096 rays, TF32, the weight average (the ablation's winner);
    on a CPU the plain command keeps the paper's MLP and the plain defaults; explicit flags
    and --field mlp win; `train volsdf` keeps its own field."""
    cfg = _config_of(["nerf", "--data", "builtin", "--device", "cuda"], monkeypatch, True)
    want = ("hash", "gpu", 4096, 1 << 19)
    assert (cfg.field, cfg.preset, cfg.batch, cfg.target_samples) == want
    assert cfg.tf32 and cfg.ema == 0.95 and not cfg.sparse_adam and cfg.random_background == "off"
    assert cfg.iters == 40000  # (the measured schedule: the lr decays over 40,000 steps)
    assert cfg.chunk == 1 << 19  # (rendering: a 400x400 frame in one chunk)
    cpu = _config_of(["nerf", "--data", "builtin"], monkeypatch, False)
    assert (cpu.field, cpu.preset, cpu.batch, cpu.target_samples, cpu.ema) == (
        "mlp",
        "default",
        1024,
        0,
        0.0,
    )
    mine = _config_of(["nerf", "--data", "builtin", "--device", "cuda", "--ema", "0", "--batch",
                       "512", "--no-tf32"], monkeypatch, True)  # fmt: skip
    assert (mine.field, mine.batch, mine.ema, mine.tf32) == ("hash", 512, 0.0, False)
    mlp = _config_of(["nerf", "--data", "builtin", "--device", "cuda", "--field", "mlp"],
                     monkeypatch, True)  # fmt: skip
    assert (mlp.field, mlp.batch, mlp.ema) == ("mlp", 1024, 0.0)
    vol = _config_of(["volsdf", "--data", "builtin", "--device", "cuda"], monkeypatch, True)
    assert vol.field == "volsdf" and vol.chunk == 8192
    sdf = _config_of(["volsdf", "--data", "builtin", "--device", "cuda", "--field", "hash_sdf"],
                     monkeypatch, True)  # fmt: skip
    assert sdf.field == "hash_sdf" and sdf.chunk == 400_000  # (frames in few chunks, measured)
    # the measured surface recipe: 2^18 samples a step, the weight average (issue 49, sixth round)
    assert (sdf.batch, sdf.target_samples, sdf.ema) == (4096, 1 << 18, 0.95)
    sdf_cpu = _config_of(["volsdf", "--data", "builtin", "--field", "hash_sdf"], monkeypatch, False)
    assert (sdf_cpu.chunk, sdf_cpu.batch, sdf_cpu.ema) == (8192, 1024, 0.0)
    # more samples a ray than the preset's chunk allows under int32 offsets: fewer rays at once
    deep = _config_of(["volsdf", "--data", "builtin", "--device", "cuda", "--field", "hash_sdf",
                       "--max-samples", "5400"], monkeypatch, True)  # fmt: skip
    resolved = deep.resolve()
    assert resolved.chunk == (2**31 - 1) // 5400 and resolved.chunk * 5400 <= 2**31 - 1
    resolved.check_values()  # (no error naming a flag the command does not have)
    cpu_preset = _config_of(["nerf", "--data", "builtin", "--preset", "cpu", "--field", "hash"],
                            monkeypatch, False)  # fmt: skip
    assert (cpu_preset.batch, cpu_preset.ema, cpu_preset.grid_res) == (512, 0.0, 32)
