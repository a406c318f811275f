"""``--pixel-jitter`` (training rays through uniform random points of their pixels, drawn after
the lattice jitter and backgrounds; the static-shape step draws them alike) and ``eval --spp N``
(the mean of N renders through fixed points of every pixel: :func:`pixel_points`), on a tiny
run of the built-in scene."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

import warpnerf.train.nerf as nerf_module
from warpnerf.cli.parser import main
from warpnerf.errors import UserError
from warpnerf.ops import random_pixels
from warpnerf.train.graph_step import GraphStep
from warpnerf.train.nerf import NeRFConfig
from warpnerf.train.nerf_eval import evaluate_run
from warpnerf.train.nerf_run import (
    MAX_SPP,
    dataset_rays,
    load_data,
    load_run,
    pixel_points,
    render_dataset_image,
    render_rays_of,
)  # fmt: skip
from warpnerf.train.recipe import LEGACY

from .test_ema import FLAGS
from .test_graph_step import _task, _train
from .test_hostile_runs import _one_line
from .test_step_loss import (
    FORCE,
    _pair,
    assert_same_gradients,
    assert_static_trains_as_eager,
    step_both,
)


def trained(tmp_path_factory, name: str, *flags) -> Path:
    """A tiny hash-grid run of the built-in scene (4 steps) trained with ``flags``."""
    out = tmp_path_factory.mktemp(name) / "run"
    assert main(["train", "nerf", *FLAGS, *flags, "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A tiny hash-grid run of the built-in scene trained with --pixel-jitter (4 steps)."""
    return trained(tmp_path_factory, "jitter", "--pixel-jitter")


# ------------------------------------------------------------------------------ pixel_points


def test_pixel_points_centre_and_stratified_grids():
    assert pixel_points(1) == [(0.5, 0.5)]
    assert sorted(pixel_points(4)) == [(0.25, 0.25), (0.25, 0.75), (0.75, 0.25), (0.75, 0.75)]
    for k in (3, 8):  # (MAX_SPP = 64: an 8 x 8 grid)
        cells = {(i, j) for i in range(k) for j in range(k)}
        points = pixel_points(k * k)
        assert {(round(x * k - 0.5), round(y * k - 0.5)) for x, y in points} == cells
        assert all(math.isclose(x * k % 1, 0.5) and math.isclose(y * k % 1, 0.5)
                   for x, y in points)  # fmt: skip


@pytest.mark.parametrize("spp", [2, 3, 5, 7, 12, MAX_SPP - 1])
def test_pixel_points_of_a_non_square_count_are_distinct_r2_points(spp):
    points = pixel_points(spp)
    assert len(points) == spp and len(set(points)) == spp
    assert points[0] == (0.5, 0.5)
    assert all(0 <= x < 1 and 0 <= y < 1 for x, y in points)
    assert pixel_points(spp) == points  # deterministic: a repeatable evaluation


@pytest.mark.parametrize("spp", [0, -1, MAX_SPP + 1])
def test_pixel_points_out_of_range_raise(spp):
    with pytest.raises(ValueError, match="spp"):
        pixel_points(spp)


# ------------------------------------------------------------------- render_dataset_image


@torch.no_grad()  # (as render_dataset_image: the no-grad renderer)
def _by_hand(model, cfg, ds, i, points):
    """The mean of renders through ``points`` of every pixel of image ``i``."""
    h, w = ds.height, ds.width
    py, px = torch.meshgrid(torch.arange(h, dtype=torch.float32),
                            torch.arange(w, dtype=torch.float32), indexing="ij")  # fmt: skip
    px, py = px.reshape(-1), py.reshape(-1)
    cam = torch.full((h * w,), i, dtype=torch.int64)
    outs = []
    for x, y in points:
        o, d = dataset_rays(cfg, ds, cam, px + x, py + y)
        out = render_rays_of(model, cfg, o, d, chunk=cfg.chunk)
        outs.append(torch.cat([out["rgb"], out["depth"][:, None], out["opacity"][:, None]], 1))
    mean = torch.stack(outs).mean(0)
    return mean[:, :3].reshape(h, w, 3), mean[:, 3].reshape(h, w), mean[:, 4].reshape(h, w)


def test_render_dataset_image_spp_is_the_mean_of_renders_through_the_points(run):
    cfg, model, _ = load_run(run)
    ds = load_data(cfg, "val")
    for spp in (4, 3):
        got = render_dataset_image(model, cfg, ds, 1, spp)
        want = _by_hand(model, cfg, ds, 1, pixel_points(spp))
        assert got[0].shape == (ds.height, ds.width, 3) and got[1].shape == (ds.height, ds.width)
        for g, wnt in zip(got, want):
            assert torch.allclose(g, wnt, atol=1e-6, rtol=1e-5), (spp, (g - wnt).abs().max())
    centre = render_dataset_image(model, cfg, ds, 1)
    assert max(float((a - b).abs().max()) for a, b in zip(got, centre)) > 1e-3  # (moved rays)


def test_render_dataset_image_spp_1_is_the_pixel_centre_render(run):
    cfg, model, _ = load_run(run)
    ds = load_data(cfg, "val")
    one = render_dataset_image(model, cfg, ds, 1, 1)
    assert all(torch.equal(a, b) for a, b in zip(one, render_dataset_image(model, cfg, ds, 1)))
    with torch.no_grad():
        o, d = dataset_rays(cfg, ds, image=1)
        out = render_rays_of(model, cfg, o, d, chunk=cfg.chunk)
    h, w = ds.height, ds.width
    exact = (out["rgb"].reshape(h, w, 3), out["depth"].reshape(h, w),
             out["opacity"].reshape(h, w))  # fmt: skip
    assert all(torch.equal(a, b) for a, b in zip(one, exact))
    # the centres as a batch of pixels: the same rays, up to the camera's round-off
    for a, b in zip(one, _by_hand(model, cfg, ds, 1, [(0.5, 0.5)])):
        assert torch.allclose(a, b, atol=1e-5)


# ----------------------------------------------------------------------------- evaluate_run


@pytest.mark.parametrize("spp", [0, -2, MAX_SPP + 1, True, 2.5, "4"])
def test_evaluate_run_refuses_a_bad_spp_before_any_work(run, spp):
    with pytest.raises(UserError, match=r"--spp must be an integer in \[1, 64\]"):
        evaluate_run(run, "val", max_images=1, spp=spp)
    assert not (run / "eval_val").exists()


def test_evaluate_run_spp_none_scores_with_the_runs_train_spp(run, tmp_path_factory, tmp_path):
    """spp None (eval without --spp): the rays a pixel the run trained with (--train-spp; 1 for
    a run without it), recorded in metrics.json; the score is that of the explicit count."""
    spp_run = trained(tmp_path_factory, "train_spp", "--train-spp", "4")
    assert json.loads((spp_run / "config.json").read_text())["train_spp"] == 4
    assert json.loads((run / "config.json").read_text())["train_spp"] == 1
    scores = {}
    for r, want in ((spp_run, 4), (run, 1)):
        for spp in (None, want):
            out = tmp_path / f"{r.parent.name}_{spp}"
            m = evaluate_run(r, "val", max_images=1, out_dir=out, spp=spp)
            assert m["spp"] == want and m["n_images"] == 1
            assert json.loads((out / "metrics.json").read_text())["spp"] == want
            scores[r, spp] = m["psnr"]
        assert scores[r, None] == scores[r, want]
    # a given --spp wins over the run's (another image, another score)
    m = evaluate_run(spp_run, "val", max_images=1, out_dir=tmp_path / "one", spp=1)
    assert m["spp"] == 1 and m["psnr"] != scores[spp_run, None]


def test_evaluate_run_refuses_supersampled_sphere_tracing(run):
    with pytest.raises(UserError, match="--spp needs --renderer volume"):
        evaluate_run(run, "val", max_images=1, spp=4, renderer="sphere")
    assert not (run / "eval_val_sphere").exists()


def test_evaluate_run_records_spp_in_metrics(run, tmp_path):
    for spp in (1, 4, 2):
        out = tmp_path / f"spp{spp}"
        m = evaluate_run(run, "val", max_images=1, out_dir=out, spp=spp)
        assert m["spp"] == spp and m["n_images"] == 1 and math.isfinite(m["psnr"])
        assert json.loads((out / "metrics.json").read_text())["spp"] == spp


def test_cli_eval_spp_out_of_range_is_one_line(run, capsys):
    with pytest.raises(SystemExit) as e:  # (argparse: not positive)
        main(["eval", str(run), "--spp", "0"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and "argument --spp" in err, err
    rc = main(["eval", str(run), "--spp", str(MAX_SPP + 1)])
    _one_line(capsys, rc, 2, "--spp must be an integer in [1, 64], got 65")
    rc = main(["eval", str(run), "--spp", "4", "--renderer", "sphere"])
    _one_line(capsys, rc, 2, "--spp needs --renderer volume")
    assert not (run / "eval_val").exists() and not (run / "eval_val_sphere").exists()


def test_cli_eval_spp_prints_and_records_it(run, tmp_path, capsys):
    out = tmp_path / "ev"
    argv = ["eval", str(run), "--spp", "4", "--max-images", "1", "--quiet", "--out", str(out)]
    assert main(argv) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["spp"] == 4
    assert json.loads((out / "metrics.json").read_text())["spp"] == 4


# ------------------------------------------------------------------------------ the config


def test_config_records_pixel_jitter_and_an_old_config_reads_false(run):
    saved = json.loads((run / "config.json").read_text())
    assert saved["pixel_jitter"] is True
    assert load_run(run)[0].pixel_jitter is True
    assert LEGACY["pixel_jitter"] is False
    assert NeRFConfig().pixel_jitter is False
    # a run written before the option (the recipe's other keys there): trained without it
    before = {k: v for k, v in saved.items() if k != "pixel_jitter"}
    assert NeRFConfig.from_dict(before, "config.json").pixel_jitter is False
    # a run from before the recipe's section: LEGACY's value
    older = {k: v for k, v in saved.items() if k not in LEGACY}
    assert NeRFConfig.from_dict(older, "config.json").pixel_jitter is False
    with pytest.raises(UserError, match="pixel_jitter"):
        NeRFConfig.from_dict({**saved, "pixel_jitter": 1}, "config.json")


# ---------------------------------------------------------------------- the training step


class _Rays:
    """Records what the training step passes to dataset_rays and render_rays_of."""

    def __init__(self, monkeypatch):
        self.rays, self.renders = [], []
        monkeypatch.setattr(nerf_module, "dataset_rays", self._rays)
        monkeypatch.setattr(nerf_module, "render_rays_of", self._render)

    def _rays(self, cfg, ds, cam_idx=None, px=None, py=None, **kw):
        self.rays.append((cam_idx.clone(), px.clone(), py.clone()))
        return dataset_rays(cfg, ds, cam_idx, px, py, **kw)

    def _render(self, *args, **kw):
        self.renders.append({k: kw.get(k) for k in ("jitter", "background")})
        return render_rays_of(*args, **kw)


def _first_step(monkeypatch, **kw):
    """(cam, px, py) of a fresh task's first eager step, the lattice jitter and backgrounds it
    rendered with, and the task."""
    spy = _Rays(monkeypatch)
    task = _task("cpu", **kw)
    task.loss(0)
    assert len(spy.rays) == 1 and len(spy.renders) == 1
    return spy.rays[0], spy.renders[0], task


@pytest.mark.parametrize(
    "kw",
    [{}, {"random_background": "on"}, {"grid_res": 0}],
    ids=["grid", "grid+random_background", "no_grid"],
)  # fmt: skip
def test_eager_step_rays_pass_through_random_points_of_their_pixels(monkeypatch, kw):
    (cam, px, py), drawn, task = _first_step(monkeypatch, **kw)
    # without the option: the pixel centres random_pixels draws from the run's seed, as before
    cfg = task.cfg
    want = random_pixels(task.n_img, task.w, task.h, cfg.batch,
                         generator=torch.Generator().manual_seed(cfg.seed))  # fmt: skip
    assert torch.equal(cam, want[0]) and torch.equal(px, want[1]) and torch.equal(py, want[2])
    assert torch.equal(px - px.floor(), torch.full_like(px, 0.5))
    assert torch.equal(py - py.floor(), torch.full_like(py, 0.5))
    (cam_j, px_j, py_j), drawn_j, task_j = _first_step(monkeypatch, pixel_jitter=True, **kw)
    assert task_j.cfg.pixel_jitter
    # the same pixels, each ray through a point of its own pixel, not its centre
    assert torch.equal(cam_j, cam)
    ox, oy = px_j - (px - 0.5), py_j - (py - 0.5)
    for off in (ox, oy):
        assert bool(((off >= 0) & (off <= 1)).all())
        assert float((off - 0.5).abs().min()) < 0.1 < float((off - 0.5).abs().max())
        assert 0.3 < float(off.mean()) < 0.7
    assert not torch.equal(ox, oy)
    # drawn after the lattice jitter and the backgrounds: those stay the draws they were
    for k in ("jitter", "background"):
        a, b = drawn[k], drawn_j[k]
        assert (a is None) == (b is None) and (a is None or torch.equal(a, b)), k
    if task.random_bg:
        assert drawn["background"] is not None


@pytest.mark.parametrize("kw", [{}, {"random_background": "on"}], ids=["plain", "random_bg"])
def test_static_step_draws_the_eager_steps_rays_and_gradients(monkeypatch, kw):
    """One step after the same eager first step: the static-shape body (no capture) passes the
    eager step's rays (the same pixel points, bit for bit) and gives its loss and gradients."""
    eager, static = _pair(dict(pixel_jitter=True, **kw))
    spy = _Rays(monkeypatch)
    loss_e, _, loss_s, _ = step_both(eager, static)
    (cam_e, px_e, py_e), (cam_s, px_s, py_s) = spy.rays
    n = cam_e.shape[0]
    assert torch.equal(cam_s[:n], cam_e)
    assert torch.equal(px_s[:n], px_e) and torch.equal(py_s[:n], py_e)
    assert not torch.equal(px_e - px_e.floor(), torch.full_like(px_e, 0.5))
    (shape,) = static.graph.shapes.values()
    assert shape.pix is not None
    assert loss_s.item() == pytest.approx(loss_e.item(), rel=1e-6)
    assert_same_gradients(eager, static)


def test_static_step_trains_as_the_eager_step_with_pixel_jitter():
    """Six steps: the static-shape step with --pixel-jitter gives the eager step's losses and
    parameters, batch for batch."""
    assert_static_trains_as_eager(6, pixel_jitter=True)


def test_static_step_without_pixel_jitter_has_no_pixel_buffer():
    task = _task("cpu")
    _train(task, 2, static=True, force=FORCE)
    assert all(shape.pix is None for shape in task.graph.shapes.values())
    assert isinstance(task.graph, GraphStep)
