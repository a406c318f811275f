"""Crash safety and determinism of the trainers other than NeRF (test_nerf covers train nerf):
SIGINT/SIGTERM finish the step, checkpoint it and raise Interrupted; the checkpoint is the last
good one (loadable, equal to history.json); --resume then equals an uninterrupted run bit for
bit (fixed seed, CPU), and so do two fresh runs. A writer failing mid-way leaves neither a partial
target nor a temporary file (checkpoints, meshes, videos, images)."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

import warpnerf.train.box_fit as box_mod
import warpnerf.train.sdf as sdf_mod
from warpnerf.errors import Interrupted
from warpnerf.train.box_fit import BoxFitConfig, load_box_run, run_box_fit_on_folder
from warpnerf.train.sdf import SDFConfig, load_sdf_run, train_sdf

from ._scene import write_box_folder

SDF_TINY = dict(batch=128, n_random=128, resolution=16, width=16, n_layers=2, skip=1, pos_freqs=2)
BOX_TINY = dict(batch=256, n_samples=16)


def _signal_on_call(monkeypatch, module, name, sig, call):
    """Wraps module.name so that its ``call``-th call (1-based) sends ``sig`` to this process in
    the middle of a training step."""
    real, calls = getattr(module, name), [0]

    def wrapper(*a, **kw):
        calls[0] += 1
        if calls[0] == call:
            os.kill(os.getpid(), sig)
        return real(*a, **kw)

    monkeypatch.setattr(module, name, wrapper)


def _hidden(folder):
    """Temporary files atomic_path would leave (names starting with a dot; the folder's manifest
    and lock file are not temporary)."""
    from warpnerf.outputs import LOCK, MANIFEST

    keep = (MANIFEST, LOCK)
    return sorted(f.name for f in folder.iterdir() if f.name.startswith(".") and f.name not in keep)


def _assert_last_good_checkpoint(run, step, loader):
    """The checkpoint loads, is at ``step`` and holds the history that history.json holds."""
    ckpt = loader(run)[-1]
    hist = json.loads((run / "history.json").read_text())
    assert ckpt["step"] == step == hist["step"][-1] == len(hist["loss"])
    assert ckpt["history"] == hist
    assert _hidden(run) == []


def _box_result(run):
    return json.loads((run / "result.json").read_text())


@pytest.fixture(scope="module")
def points(tmp_path_factory) -> str:
    """400 points on a sphere (a small cloud keeps the final Chamfer distance cheap)."""
    g = np.random.default_rng(0).normal(size=(400, 3))
    path = tmp_path_factory.mktemp("pts") / "sphere.npz"
    np.savez(path, verts=g / np.linalg.norm(g, axis=1, keepdims=True))
    return str(path)


def sdf_cfg(points, **kw) -> SDFConfig:
    return SDFConfig(points=points, **SDF_TINY, **kw)


@pytest.fixture(scope="module")
def box_scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("box") / "scene"
    write_box_folder(root, n_views=4, size=16, name="transforms_train.json")
    return root


def test_sdf_two_runs_and_interrupt_resume_are_bit_identical(tmp_path, monkeypatch, points):
    """Two fresh runs give the same losses; a SIGTERM in step 3 (inside the loss) lets the step
    finish, checkpoints it (no mesh yet) and restores the handlers; --resume reaches the same
    losses and weights as the uninterrupted run."""
    a = train_sdf(sdf_cfg(points, iters=6), tmp_path / "a", progress=False)
    b = train_sdf(sdf_cfg(points, iters=6), tmp_path / "b", progress=False)
    ha = json.loads((tmp_path / "a" / "history.json").read_text())
    hb = json.loads((tmp_path / "b" / "history.json").read_text())
    assert ha["loss"] == hb["loss"] and a["chamfer"] == b["chamfer"]

    _signal_on_call(monkeypatch, sdf_mod, "sdf_loss", signal.SIGTERM, call=3)
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Interrupted, match="SIGTERM at step 3") as info:
        train_sdf(sdf_cfg(points, iters=6), tmp_path / "c", progress=False)
    assert info.value.step == 3 and signal.getsignal(signal.SIGTERM) is before
    _assert_last_good_checkpoint(tmp_path / "c", 3, load_sdf_run)
    assert not (tmp_path / "c" / "mesh.ply").exists()
    assert not (tmp_path / "c" / "metrics.json").exists()
    monkeypatch.undo()
    train_sdf(SDFConfig(iters=6), tmp_path / "c", resume=True, progress=False)
    ca = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=True)
    cc = torch.load(tmp_path / "c" / "checkpoint.pt", weights_only=True)
    assert cc["history"]["loss"] == ha["loss"]
    assert all(torch.equal(v, cc["model"][k]) for k, v in ca["model"].items())
    assert _hidden(tmp_path / "c") == []


def test_box_two_runs_and_interrupt_resume_are_bit_identical(tmp_path, monkeypatch, box_scene):
    """The box fit in a run folder: two fresh fits agree; SIGINT in step 3 checkpoints it
    (box, Adam, the exponential schedule, the batch generator) and raises Interrupted; resuming
    gives the uninterrupted fit's losses and box exactly."""
    cfg = dict(iters=6, ckpt_every=100, **BOX_TINY)
    ra = run_box_fit_on_folder(box_scene, tmp_path / "a", BoxFitConfig(**cfg), frames=0)
    rb = run_box_fit_on_folder(box_scene, tmp_path / "b", BoxFitConfig(**cfg), frames=0)
    assert _box_result(tmp_path / "a")["losses"] == _box_result(tmp_path / "b")["losses"]
    assert ra == rb

    _signal_on_call(monkeypatch, box_mod, "render_rays", signal.SIGINT, call=3)
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(Interrupted, match="SIGINT at step 3") as info:
        run_box_fit_on_folder(box_scene, tmp_path / "c", BoxFitConfig(**cfg), frames=0)
    assert info.value.step == 3 and signal.getsignal(signal.SIGINT) is before
    _assert_last_good_checkpoint(tmp_path / "c", 3, load_box_run)
    assert not (tmp_path / "c" / "result.json").exists()
    monkeypatch.undo()
    with pytest.raises(Exception, match="must be larger"):
        run_box_fit_on_folder(None, tmp_path / "c", BoxFitConfig(iters=3), resume=True)
    rc = run_box_fit_on_folder(None, tmp_path / "c", BoxFitConfig(iters=6), resume=True, frames=0)
    assert rc == ra
    assert _box_result(tmp_path / "c")["losses"] == _box_result(tmp_path / "a")["losses"]
    va = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=True)["volume"]
    vc = torch.load(tmp_path / "c" / "checkpoint.pt", weights_only=True)["volume"]
    assert all(torch.equal(v, vc[k]) for k, v in va.items())
    saved = json.loads((tmp_path / "c" / "config.json").read_text())
    assert saved["iters"] == 6 and saved["lr_decay_steps"] == 6 and saved["model"] == "box"


def test_box_run_folder_guards(tmp_path, box_scene, points):
    """A folder holding another kind of run is refused; a new box fit over an old one starts over
    (its checkpoint replaced); --resume needs a box run."""
    from warpnerf.errors import UserError

    train_sdf(sdf_cfg(points, iters=1), tmp_path / "s", progress=False)
    with pytest.raises(UserError, match="another kind of run"):
        run_box_fit_on_folder(box_scene, tmp_path / "s", BoxFitConfig(iters=1, **BOX_TINY))
    with pytest.raises(UserError, match="not a box run"):
        run_box_fit_on_folder(None, tmp_path / "s", BoxFitConfig(iters=2), resume=True)
    with pytest.raises(UserError, match="not a training run"):
        run_box_fit_on_folder(None, tmp_path / "none", BoxFitConfig(iters=2), resume=True)
    cfg = BoxFitConfig(iters=2, **BOX_TINY)
    run_box_fit_on_folder(box_scene, tmp_path / "r", cfg, frames=0)
    run_box_fit_on_folder(box_scene, tmp_path / "r", BoxFitConfig(iters=1, **BOX_TINY), frames=0)
    assert torch.load(tmp_path / "r" / "checkpoint.pt", weights_only=True)["step"] == 1


@pytest.mark.parametrize("model", ["sdf", "box", "nerf"])
@pytest.mark.slow
def test_cli_sigterm_exits_143_with_the_last_checkpoint(tmp_path, box_scene, points, model):
    """`warpnerf train sdf|box|nerf` under SIGTERM: exit 143, one line naming the step, a
    checkpoint equal to history.json, no temporary files, no final outputs."""
    cmd = [sys.executable, "-m", "warpnerf.cli", "train", model, "--out", "r", "--quiet"]
    cmd += ["--iters", "1000000", "--batch", "32"]
    if model == "sdf":  # first checkpoint at step 500 (the default --ckpt-every)
        cmd += ["--points", points, "--layers", "1", "--width", "8", "--pos-freqs", "0"]
        first = 500
    elif model == "box":  # first checkpoint at step 100
        cmd += ["--data", str(box_scene), "--samples", "4", "--frames", "0"]
        first = 100
    else:
        cmd += ["--data", "builtin", "--samples", "4", "--layers", "1", "--width", "8"]
        cmd += ["--builtin-size", "8", "--ckpt-every", "2", "--val-images", "0"]
        first = 2
    p = subprocess.Popen(cmd, cwd=tmp_path, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while not (tmp_path / "r" / "checkpoint.pt").exists() and time.time() < deadline:
        time.sleep(0.05)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 143, err
    assert "SIGTERM at step" in err and "Traceback" not in err
    ckpt = torch.load(tmp_path / "r" / "checkpoint.pt", weights_only=True)
    hist = json.loads((tmp_path / "r" / "history.json").read_text())
    assert ckpt["step"] == hist["step"][-1] >= first and ckpt["history"] == hist
    assert _hidden(tmp_path / "r") == []
    assert not {"mesh.ply", "metrics.json", "result.json"} & set(os.listdir(tmp_path / "r"))


def test_checkpoint_write_failing_midway_keeps_the_last_good_one(tmp_path, monkeypatch, points):
    """A full disk during the step-4 checkpoint: train_sdf raises, the step-2 checkpoint and
    history stay whole and loadable, no temporary file remains, and --resume continues."""
    real_save, calls = torch.save, [0]

    def save(obj, f, *a, **kw):
        calls[0] += 1
        if calls[0] == 2:
            with open(f, "wb") as fh:
                fh.write(b"PK\x03\x04 half a checkpoint")
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_save(obj, f, *a, **kw)

    monkeypatch.setattr(torch, "save", save)
    with pytest.raises(OSError, match="No space"):
        train_sdf(sdf_cfg(points, iters=6, ckpt_every=2), tmp_path / "r", progress=False)
    _assert_last_good_checkpoint(tmp_path / "r", 2, load_sdf_run)
    monkeypatch.undo()
    m = train_sdf(SDFConfig(iters=6), tmp_path / "r", resume=True, progress=False)
    assert m["step"] == 6 and _hidden(tmp_path / "r") == []


def test_mesh_video_and_image_writers_failing_midway_leave_nothing(tmp_path, monkeypatch):
    """write_ply failing after its header, write_video failing at its third frame (GIF and MP4:
    imageio's writer must stop ffmpeg before the temporary file is removed), write_image and the
    mesh screenshot failing after writing part of the file: the previous target (if any) is
    untouched and no temporary file is left."""
    import warpnerf.mesh as mesh_mod
    import warpnerf.ply as ply_mod
    from warpnerf.mesh import read_ply, write_ply
    from warpnerf.outputs import write_image, write_video

    v = np.random.default_rng(0).random((5, 3)).astype(np.float32)
    f = np.array([[0, 1, 2], [2, 3, 4]], dtype=np.int32)
    write_ply(tmp_path / "m.ply", v, f)

    class HalfFile:
        def __init__(self, path, mode):
            self.fh, self.n = open(path, mode), 0

        def write(self, b):
            self.n += 1
            if self.n == 2:
                raise OSError(errno.EIO, "I/O error")
            return self.fh.write(b)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.fh.close()

    monkeypatch.setattr(ply_mod, "open", HalfFile, raising=False)
    with pytest.raises(OSError, match="I/O error"):
        write_ply(tmp_path / "m.ply", v[:3] + 1, f[:1])
    monkeypatch.undo()
    rv, rf = read_ply(tmp_path / "m.ply")
    assert np.array_equal(rv, v) and np.array_equal(rf, f)

    frames = [np.zeros((8, 8, 3), np.uint8)] * 2 + [np.zeros((8, 8, 5), np.uint8)]
    for name in ("v.gif", "v.mp4"):
        with pytest.raises(ValueError):
            write_video(tmp_path / name, frames)
    import imageio.v3 as iio

    def broken_imwrite(uri, image, **kw):
        with open(uri, "wb") as fh:
            fh.write(b"\x89PNG half")
        raise OSError(errno.EIO, "I/O error")

    monkeypatch.setattr(iio, "imwrite", broken_imwrite)
    with pytest.raises(OSError, match="I/O error"):
        write_image(tmp_path / "i.png", np.zeros((4, 4, 3), np.uint8))
    monkeypatch.undo()
    pytest.importorskip("pyvista")
    import pyvista as pv

    def broken_screenshot(self, filename=None, **kw):
        with open(filename, "wb") as fh:
            fh.write(b"\x89PNG half")
        raise RuntimeError("render window lost")

    monkeypatch.setattr(pv.Plotter, "screenshot", broken_screenshot)
    with pytest.raises(RuntimeError, match="render window"):
        mesh_mod.screenshot(tmp_path / "m.png", v, f)
    assert sorted(os.listdir(tmp_path)) == [".warpnerf-files.json", "m.ply"]  # + the manifest
