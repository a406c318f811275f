"""``--train-spp N``: each training pixel rendered as the mean of N rays through the fixed points
:func:`pixel_points` of it (warpnerf/train/supersample.py), in the eager step and the
static-shape step alike; its default (4 for the hash NeRF on CUDA with Blender-format data, else
1), its checks, and eval, render and validation rendering a run's images with its count."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import pytest
import torch

import warpnerf.train.nerf_eval as nerf_eval
import warpnerf.train.nerf_run as nerf_run
from warpnerf.cli.parser import main
from warpnerf.errors import UserError
from warpnerf.train.nerf import NeRFConfig, load_data, load_run, resolve_data
from warpnerf.train.nerf_eval import _check_spp
from warpnerf.train.nerf_run import MAX_SPP, _with_data, pixel_points, run_spp, validate
from warpnerf.train.recipe import LEGACY, TRAIN_SPP_MAX, default_train_spp
from warpnerf.train.supersample import PER_RAY, expand_rows, pixel_means, sub_offsets, sub_rays

from .test_datasets import make_blender, make_nerfstudio
from .test_ema import FLAGS
from .test_graph_step import _task
from .test_hostile_runs import _one_line
from .test_pixel_jitter import _Rays, trained
from .test_step_loss import (
    SPP_FORCE,
    _pair,
    assert_same_gradients,
    assert_static_trains_as_eager,
    step_both,
)


@pytest.fixture(scope="module")
def spp_run(tmp_path_factory):
    """A tiny hash-grid run of the built-in scene trained with --train-spp 4 (4 steps)."""
    return trained(tmp_path_factory, "spp", "--train-spp", "4")


# ------------------------------------------------------------------- supersample.py's parts


def _sub_rays_by_hand(cam, px, py, points):
    """Pixel by pixel, point by point: the sub-rays' cameras and pixel coordinates."""
    cams, xs, ys = [], [], []
    for i in range(cam.shape[0]):
        for x, y in points:
            cams.append(int(cam[i]))
            xs.append(float(px[i]) - 0.5 + x)
            ys.append(float(py[i]) - 0.5 + y)
    return torch.tensor(cams), torch.tensor(xs), torch.tensor(ys)


@pytest.mark.parametrize("spp", [1, 2, 3, 4, 9, 16])
def test_sub_offsets_are_the_pixel_points_from_the_centre(spp):
    off = sub_offsets(spp, "cpu")
    assert off.shape == (spp, 2) and off.dtype == torch.float32 and off.device.type == "cpu"
    want = torch.tensor([(x - 0.5, y - 0.5) for x, y in pixel_points(spp)])
    assert torch.allclose(off, want, atol=1e-7)
    assert bool((off.abs() < 0.5).all())  # (each point inside its pixel)
    if spp == 4:  # the centres of the pixel's 2 x 2 cells, exactly
        assert sorted(map(tuple, off.tolist())) == [(-0.25, -0.25), (-0.25, 0.25),
                                                    (0.25, -0.25), (0.25, 0.25)]  # fmt: skip


@pytest.mark.parametrize("spp", [4, 3])
def test_sub_rays_are_each_pixels_points_in_order(spp):
    g = torch.Generator().manual_seed(1)
    n = 7
    cam = torch.randint(0, 5, (n,), generator=g)
    px = torch.randint(0, 100, (n,), generator=g).float() + 0.5
    py = torch.randint(0, 60, (n,), generator=g).float() + 0.5
    c, x, y = sub_rays(cam, px, py, sub_offsets(spp, "cpu"))
    assert c.shape == x.shape == y.shape == (n * spp,)
    assert c.dtype == cam.dtype and x.dtype == torch.float32
    wc, wx, wy = _sub_rays_by_hand(cam, px, py, pixel_points(spp))
    assert torch.equal(c, wc)  # pixel i's sub-rays: rows i*spp .. i*spp + spp - 1
    assert torch.allclose(x, wx, atol=1e-5) and torch.allclose(y, wy, atol=1e-5)
    # every sub-ray lies in its own pixel
    assert torch.equal(x.floor(), expand_rows(px.floor(), spp))
    assert torch.equal(y.floor(), expand_rows(py.floor(), spp))


def test_expand_rows_repeats_each_row_in_place():
    x = torch.arange(12.0).reshape(4, 3)
    got = expand_rows(x, 3)
    assert got.shape == (12, 3)
    assert torch.equal(got, torch.stack([x[i] for i in range(4) for _ in range(3)]))
    ints = torch.tensor([5, 2, 9])
    assert expand_rows(ints, 2).tolist() == [5, 5, 2, 2, 9, 9]
    assert torch.equal(expand_rows(ints, 1), ints)
    assert expand_rows(torch.zeros(0, 3), 4).shape == (0, 3)
    flags = torch.tensor([True, False])
    assert expand_rows(flags, 3).tolist() == [True] * 3 + [False] * 3


def _means_by_hand(v, n, s):
    return torch.stack([v[i * s : (i + 1) * s].mean(0) for i in range(n)])


def test_pixel_means_averages_only_the_per_ray_entries_of_the_sub_rays():
    n, s = 3, 4
    g = torch.Generator().manual_seed(2)
    out = {k: torch.rand(n * s, generator=g) for k in PER_RAY}
    out["rgb"] = torch.rand(n * s, 3, generator=g)
    out.update(n_kept=123, stats=torch.arange(n * s), weights=torch.rand(n * s, generator=g))
    before = {k: v.clone() if torch.is_tensor(v) else v for k, v in out.items()}
    res = pixel_means(out, n, s)
    for k in PER_RAY:
        assert torch.allclose(res[k], _means_by_hand(out[k], n, s), atol=1e-7), k
        assert res[k].shape == (n, *out[k].shape[1:]), k
    # entries other than the per-ray outputs (counts, per-sample values): as they were
    for k in ("n_kept", "stats", "weights"):
        assert res[k] is out[k], k
    # the renderer's dict is left alone
    for k, v in before.items():
        same = torch.equal(out[k], v) if torch.is_tensor(v) else out[k] == v
        assert same, k
    # a per-ray entry of another length (not the sub-rays'), or a number: kept as it is
    odd = {"rgb": torch.rand(n * s, 3, generator=g), "depth": torch.rand(n, generator=g),
           "opacity": torch.tensor(0.5), "distortion": torch.rand(n * s + 1, generator=g),
           "near_weight": 0.25}  # fmt: skip
    res = pixel_means(odd, n, s)
    assert res["rgb"].shape == (n, 3)
    for k in ("depth", "opacity", "distortion", "near_weight"):
        assert res[k] is odd[k], k
    assert "interlevel" not in res


def test_pixel_means_gives_each_sub_ray_its_share_of_the_gradient():
    n, s = 5, 4
    g = torch.Generator().manual_seed(3)
    x = torch.rand(n * s, 3, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: pixel_means({"rgb": v}, n, s)["rgb"], (x,))
    w = torch.randn(n, 3, generator=g, dtype=torch.float64)
    (pixel_means({"rgb": x}, n, s)["rgb"] * w).sum().backward()
    # d(mean)/d(sub-ray) = 1/s: every sub-ray of pixel i gets w[i] / s
    assert torch.allclose(x.grad, expand_rows(w, s) / s, rtol=0, atol=1e-15)
    d = torch.rand(n * s, generator=g, dtype=torch.float64, requires_grad=True)
    pixel_means({"depth": d}, n, s)["depth"].sum().backward()
    assert torch.allclose(d.grad, torch.full_like(d, 1 / s))


# -------------------------------------------------------------------------- default_train_spp


@pytest.mark.parametrize(
    "field, device, fmt, want",
    [
        ("hash", "cuda", "blender", 4),
        ("hash", "cuda:0", "blender", 4),
        ("hash", "cuda:1", "blender", 4),
        ("hash", "cpu", "blender", 1),
        ("mlp", "cuda", "blender", 1),
        ("hash_sdf", "cuda", "blender", 1),
        ("volsdf", "cuda", "blender", 1),
        *[("hash", "cuda", f, 1) for f in ("builtin", "colmap", "llff", "nerfstudio", None)],
    ],
)  # fmt: skip
def test_default_train_spp_is_4_only_for_the_hash_nerf_on_cuda_with_blender_data(
    field, device, fmt, want
):
    assert default_train_spp(SimpleNamespace(field=field, device=device), fmt) == want
    if device.startswith("cuda"):  # (a torch.device as the config could hold one)
        cfg = SimpleNamespace(field=field, device=torch.device(device))
        assert default_train_spp(cfg, fmt) == want


def test_a_new_runs_data_resolves_its_train_spp(tmp_path):
    blender = make_blender(tmp_path / "blender")
    ns = make_nerfstudio(tmp_path / "ns")

    def spp(data, **kw):  # (what the data decides: no device needed)
        return _with_data(NeRFConfig(**{"data": str(data), "field": "hash", **kw})).train_spp

    assert spp(blender, device="cuda") == 4
    assert spp(blender, device="cuda", data_format="blender") == 4
    assert spp(blender, device="cuda", field="mlp") == 1
    assert spp(ns, device="cuda") == 1
    assert spp(blender, device="cuda", train_spp=2) == 2  # (given: kept)
    assert spp(blender, device="cpu", train_spp=9) == 9
    # a CPU run on a Blender folder, resolved and checked as a new run is
    for field in ("hash", "mlp"):
        cfg = resolve_data(NeRFConfig(data=str(blender), field=field, device="cpu"))
        assert cfg.train_spp == 1, field
    # the built-in scene (rendered through the pixels' centres): 1
    assert resolve_data(NeRFConfig(data="builtin", field="hash", device="cpu")).train_spp == 1


# ----------------------------------------------------------------------------- the config


@pytest.mark.parametrize(
    "value, message",
    [
        ("0", "argument --train-spp: must be positive"),
        ("17", f"--train-spp must be an integer in [1, {TRAIN_SPP_MAX}], got 17"),
        ("2.5", "argument --train-spp: expected an integer, got '2.5'"),
        ("True", "argument --train-spp: expected an integer, got 'True'"),
    ],
)
def test_cli_refuses_a_bad_train_spp_in_one_line(tmp_path, capsys, value, message):
    out = tmp_path / "run"
    try:
        rc = main(["train", "nerf", *FLAGS, "--train-spp", value, "--out", str(out)])
    except SystemExit as e:  # (argparse's own checks)
        rc = e.code
    _one_line(capsys, rc, 2, message)
    assert not out.exists()


def test_cli_refuses_train_spp_with_pixel_jitter(tmp_path, capsys):
    out = tmp_path / "run"
    rc = main(["train", "nerf", *FLAGS, "--train-spp", "4", "--pixel-jitter", "--out", str(out)])
    _one_line(capsys, rc, 2, "--train-spp cannot be combined with pixel_jitter (--pixel-jitter)")
    assert not out.exists()
    with pytest.raises(UserError, match="cannot be combined"):  # (the config on its own)
        NeRFConfig(train_spp=4, pixel_jitter=True).check_values()
    NeRFConfig(train_spp=1, pixel_jitter=True).check_values()  # (one ray: no conflict)


def test_saved_config_records_train_spp_and_old_configs_read_1(spp_run):
    saved = json.loads((spp_run / "config.json").read_text())
    assert saved["train_spp"] == 4
    assert NeRFConfig.from_dict(saved, "config.json").train_spp == 4
    assert load_run(spp_run)[0].train_spp == 4
    assert LEGACY["train_spp"] == 1 and NeRFConfig().train_spp is None
    # a run from before the recipe's section: LEGACY's value
    older = {k: v for k, v in saved.items() if k not in LEGACY}
    assert NeRFConfig.from_dict(older, "config.json").train_spp == 1
    # a run written before the option (the recipe's other keys there): one ray a pixel
    before = NeRFConfig.from_dict({k: v for k, v in saved.items() if k != "train_spp"}, "c")
    assert before.train_spp in (None, 1) and run_spp(before) == 1
    for bad in (0, 17, -1, True, 2.5, "4"):
        with pytest.raises(UserError, match=r"run/config.json: field 'train_spp' must be an "):
            NeRFConfig.from_dict({**saved, "train_spp": bad}, "run/config.json")
    with pytest.raises(UserError, match=r"train_spp' cannot be combined with pixel_jitter"):
        NeRFConfig.from_dict({**saved, "pixel_jitter": True}, "run/config.json")
    for bad in (0, 17, True, 2.5):  # (a config built in code: the section's own check)
        with pytest.raises(UserError, match=rf"--train-spp must be an integer in \[1, 16\], got "
                                            rf"{bad!r}"):  # fmt: skip
            NeRFConfig(train_spp=bad).check_values()


# ------------------------------------------------------------------- the eager training step


class _Spy(_Rays):
    """Records the rays, draws and render outputs of the training step."""

    def __init__(self, monkeypatch):
        super().__init__(monkeypatch)
        self.outs = []

    def _render(self, *args, **kw):
        out = super()._render(*args, **kw)
        self.outs.append(out)
        return out


def _random_alpha(task):
    """A random alpha for the built-in scene's pixels (as test_step_loss's pairs have)."""
    task.flat_alpha = torch.rand(task.flat.shape[0], generator=torch.Generator().manual_seed(5))


@pytest.mark.parametrize("kw", [{}, {"random_background": "on"}], ids=["grid", "random_bg"])
def test_eager_step_loss_is_the_pixels_mean_colour_against_their_targets(monkeypatch, kw):
    spy = _Spy(monkeypatch)
    _task("cpu", **kw).loss(0)  # one ray a pixel: the pixels' centres
    cam, px, py = spy.rays[0]
    n = cam.shape[0]
    task = _task("cpu", train_spp=4, **kw)
    assert task.train_spp == 4 and task.cfg.train_spp == 4
    if task.random_bg:
        _random_alpha(task)
    states, pixels = [], []  # the device generator before the step's draws; the targets read
    update, read = task._grid_update, task.pixels

    def grid_update(step):
        update(step)
        states.append(task.grid_gen.get_state())

    def pixels_read(idx):
        pixels.append(read(idx))
        return pixels[-1]

    task._grid_update, task.pixels = grid_update, pixels_read
    loss, terms = task.loss(0)
    # the same pixels, each through its 4 points (the 2 x 2 cells' centres), pixel by pixel
    cam4, px4, py4 = spy.rays[1]
    wc, wx, wy = _sub_rays_by_hand(cam, px, py, pixel_points(4))
    assert torch.equal(cam4, wc) and torch.equal(px4, wx) and torch.equal(py4, wy)
    # the lattice jitter drawn for every sub-ray, then a background a pixel, for its sub-rays
    (state,) = states
    g = torch.Generator().set_state(state)
    drawn = spy.renders[1]
    assert torch.equal(drawn["jitter"], torch.rand(4 * n, generator=g))
    bg = None
    if task.random_bg:
        bg = torch.rand(n, 3, generator=g)
        assert torch.equal(drawn["background"], torch.stack([bg[i] for i in range(n)
                                                             for _ in range(4)]))  # fmt: skip
    else:
        assert drawn["background"] is None
    # the loss: the pixels' mean colours against their targets
    rgb = spy.outs[1]["rgb"]
    assert rgb.shape == (4 * n, 3)
    rgb.retain_grad()
    mean = _means_by_hand(rgb, n, 4)
    ((target, alpha),) = pixels
    assert target.shape == (n, 3)
    if bg is not None:  # (composited onto the pixel's random background)
        assert alpha is not None
        target = target + (1 - alpha)[:, None] * (bg - task.cfg.background)
    want = ((mean - target) ** 2).mean()
    assert loss.item() == pytest.approx(want.item(), rel=1e-6)
    assert float(terms["psnr"]) == pytest.approx(want.item(), rel=1e-6)
    # not the sub-rays' own loss against their pixels' colours
    each = ((rgb - expand_rows(target, 4)) ** 2).mean()
    assert each.item() > want.item() * (1 + 1e-4)
    # each sub-ray gets a quarter of its pixel's gradient
    loss.backward()
    per_pixel = 2 * (mean - target).detach() / (3 * n)
    assert torch.allclose(rgb.grad, expand_rows(per_pixel, 4) / 4, rtol=1e-4, atol=1e-9)


def test_eager_step_with_a_fine_pass_averages_the_coarse_colours_too():
    """--field mlp --coarse-fine --train-spp 4: the coarse pass's colours are per sub-ray too
    (the loss's coarse photometric term compares them with the pixels' colours)."""
    task = _task("cpu", field="mlp", grid_res=0, n_coarse=8, n_fine=8, train_spp=4)
    assert task.model.fine is not None
    loss, _ = task.loss(0)
    assert math.isfinite(loss.item())


# ------------------------------------------------------------- the static-shape training step


@pytest.mark.parametrize("kw", [{}, {"random_background": "on"}], ids=["plain", "random_bg"])
def test_static_step_renders_the_eager_steps_sub_rays_and_gradients(monkeypatch, kw):
    """One step after the same eager first step: the static-shape body (no capture) renders the
    eager step's sub-rays (bit for bit) and gives its loss and gradients."""
    eager, static = _pair(dict(train_spp=4, **kw), force=SPP_FORCE)
    spy = _Rays(monkeypatch)
    loss_e, terms_e, loss_s, terms_s = step_both(eager, static)
    (cam_e, px_e, py_e), (cam_s, px_s, py_s) = spy.rays
    m = cam_e.shape[0]
    assert m == 4 * terms_e["batch"] and terms_s["batch"] == terms_e["batch"]
    (shape,) = static.graph.shapes.values()
    slots = shape.key[0]
    assert cam_s.shape == (4 * slots,) and shape.jitter.shape == (4 * slots,)
    assert torch.equal(cam_s[:m], cam_e)
    assert torch.equal(px_s[:m], px_e) and torch.equal(py_s[:m], py_e)
    assert loss_s.item() == pytest.approx(loss_e.item(), rel=1e-6)
    assert float(terms_s["samples_per_ray"]) == pytest.approx(float(terms_e["samples_per_ray"]))
    assert_same_gradients(eager, static)


def test_static_step_trains_as_the_eager_step_with_train_spp():
    """Five steps: the static-shape step with --train-spp 4 gives the eager step's losses and
    parameters, batch for batch."""
    assert_static_trains_as_eager(5, SPP_FORCE, train_spp=4)


# ---------------------------------------------------------------------------- validation


@pytest.mark.parametrize("spp", [1, 4])
def test_render_dataset_image_builds_no_autograd_graph(spp):
    """Validation renders without autograd (its images go to numpy for the figures)."""
    task = _task("cpu")
    val = load_data(task.cfg, "val")
    images = nerf_run.render_dataset_image(task.model, task.cfg, val, 0, spp)
    assert [x.shape for x in images] == [(val.height, val.width, 3), (val.height, val.width),
                                         (val.height, val.width)]  # fmt: skip
    assert not any(x.requires_grad for x in images)


def test_validate_renders_with_the_runs_train_spp(monkeypatch, spp_run):
    calls = []

    def render(model, cfg, ds, i, spp=1):
        calls.append((i, spp))
        h, w = ds.images.shape[1:3]
        return torch.full((h, w, 3), 0.5), torch.zeros(h, w), torch.ones(h, w)

    monkeypatch.setattr(nerf_run, "render_dataset_image", render)
    val = SimpleNamespace(images=torch.full((3, 2, 2, 3), 0.25))
    for train_spp, want in ((4, 4), (9, 9), (1, 1), (None, 1)):
        calls.clear()
        psnr = validate(None, SimpleNamespace(val_images=2, train_spp=train_spp), val)
        assert calls == [(0, want), (1, want)], train_spp
        assert psnr == pytest.approx(-10 * math.log10(0.0625))
    calls.clear()
    validate(None, SimpleNamespace(val_images=1), val)  # (a config from before the option)
    assert calls == [(0, 1)]
    # a run's own config (trained with --train-spp 4) and validation split
    cfg, model, _ = load_run(spp_run)
    calls.clear()
    validate(model, cfg, load_data(cfg, "val"))
    assert calls and all(spp == 4 for _, spp in calls)


# ------------------------------------------------------------------------ render and eval


def test_check_spp_takes_none_and_refuses_bad_counts():
    for renderer in ("volume", "sphere"):
        assert _check_spp(None, renderer) is None
        assert _check_spp(1, renderer) == 1
    assert _check_spp(4, "volume") == 4 and _check_spp(MAX_SPP, "volume") == MAX_SPP
    for bad in (0, -1, MAX_SPP + 1, True, 2.5, "4"):
        with pytest.raises(UserError, match=r"--spp must be an integer in \[1, 64\]"):
            _check_spp(bad, "volume")
    with pytest.raises(UserError, match="--spp needs --renderer volume"):
        _check_spp(4, "sphere")


def _printed(capsys) -> dict:
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_render_uses_the_runs_train_spp_unless_given(spp_run, monkeypatch, capsys):
    renders = []

    def render(model, cfg, o, d, **kw):
        renders.append(d.clone())
        return nerf_run.render_rays_of(model, cfg, o, d, **kw)

    monkeypatch.setattr(nerf_eval, "render_rays_of", render)
    counts = {}
    for argv, want in (([], 4), (["--spp", "1"], 1), (["--spp", "2"], 2)):
        renders.clear()
        assert main(["render", str(spp_run), "--frames", "2", "--quiet", *argv]) == 0
        res = _printed(capsys)
        assert res["spp"] == want and res["frames"] == 2 and res["renderer"] == "volume"
        counts[want] = len(renders)
        if want > 1:  # each render through another point of every pixel
            assert all(not torch.equal(renders[0], r) for r in renders[1:])
    assert counts[4] == 4 * counts[1] and counts[2] == 2 * counts[1]


def test_render_refuses_a_bad_spp_in_one_line(spp_run, capsys):
    with pytest.raises(SystemExit) as e:  # (argparse: not positive)
        main(["render", str(spp_run), "--spp", "0"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and "argument --spp" in err, err
    rc = main(["render", str(spp_run), "--frames", "2", "--spp", str(MAX_SPP + 1)])
    _one_line(capsys, rc, 2, "--spp must be an integer in [1, 64], got 65")
    # (checked before the run is read: a NeRF run is refused for --spp, not for sphere tracing)
    rc = main(["render", str(spp_run), "--frames", "2", "--spp", "4", "--renderer", "sphere"])
    _one_line(capsys, rc, 2, "--spp needs --renderer volume")
    assert not (spp_run / "render_spiral_sphere").exists()


def test_cli_eval_without_spp_scores_with_the_runs_train_spp(spp_run, tmp_path, capsys):
    out = tmp_path / "ev"
    argv = ["eval", str(spp_run), "--max-images", "1", "--quiet", "--out", str(out)]
    assert main(argv) == 0
    assert _printed(capsys)["spp"] == 4
    assert json.loads((out / "metrics.json").read_text())["spp"] == 4


def test_four_rays_a_pixel_are_the_2x2_means_of_a_render_at_twice_the_size():
    """The points of `--spp 4` / `--train-spp 4` are the pixel centres of the same camera at
    twice the resolution: a supersampled image equals the 2x2 means of that larger render (how
    lego 400x400 was made from its 800x800 renders), and a one-ray image does not."""
    from warpnerf.data.cameras import camera_rays

    task = _task("cpu")
    model, cfg = task.model, task.cfg
    val = load_data(cfg, "val")
    h, w = val.height, val.width
    small = nerf_run.render_dataset_image(model, cfg, val, 0, 4)[0]
    centres = nerf_run.render_dataset_image(model, cfg, val, 0, 1)[0]
    o, d = camera_rays(val.c2w[:1], val.intrinsics[:1] * 2, 2 * w, 2 * h)  # fx, fy, cx, cy x 2
    with torch.no_grad():
        big = nerf_run.render_rays_of(model, cfg, o, d, chunk=cfg.chunk)["rgb"]
    means = big.reshape(h, 2, w, 2, 3).mean((1, 3))
    assert torch.allclose(small, means, atol=1e-5)
    assert (centres - means).abs().max() > 1e-3  # (the field is not flat at this scale)
