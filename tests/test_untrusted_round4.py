"""Security round 4 (issue 45), items 1, 3, 5 and 9:

1  an export never replaces a file a dataset or run reads: a --downscale run exported over the
   dataset an earlier export wrote leaves its full-size images (and its transforms.json) as
   they were, with a one-line refusal
3  a FIFO (or a link, where links are not followed) in place of any file a command reads is
   refused at once with one line naming it: run files (config.json, checkpoint.pt, run.json),
   camera paths, SDF scenes, dataset indexes, images, COLMAP models, LLFF arrays, point clouds
5  a checkpoint's history must hold what the loop reads (step, loss, seconds: numbers, equal
   lengths): checked when the checkpoint is loaded, one line naming it
9  JSON inputs are bounded per kind (bytes) and in nesting depth; a file past either is named
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

import warpnerf.mesh
from warpnerf import outputs
from warpnerf.cli import main
from warpnerf.errors import UserError

from .test_datasets import make_blender, make_nerfstudio

TN = ["--batch", "32", "--samples", "4", "--layers", "2", "--width", "16", "--pos-freqs", "1",
      "--dir-freqs", "1", "--val-images", "0", "--quiet", "--no-tensorboard"]  # fmt: skip
NEW = ["--data", "builtin", "--builtin-size", "8", "--near", "1", "--far", "4", *TN]
SDF = ["--batch", "32", "--layers", "2", "--width", "16", "--pos-freqs", "1", "--resolution", "8",
       "--quiet"]  # fmt: skip
BOX = ["--batch", "16", "--samples", "4", "--frames", "0", "--quiet"]


def _no_screenshot(*args, **kwargs):
    raise ImportError("screenshots are skipped in these tests")


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """Tiny finished runs: NeRF on the built-in scene, a neural SDF on points, a box fit."""
    w = tmp_path_factory.mktemp("round4")
    make_blender(w / "bl", n=2)
    g = np.random.default_rng(0).normal(size=(200, 3))
    np.savez(w / "ok.npz", points=g / np.linalg.norm(g, axis=1, keepdims=True))
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(w)
        mp.setattr(warpnerf.mesh, "screenshot", _no_screenshot)
        assert main(["train", "nerf", "--out", "nerf", "--iters", "2", *NEW]) == 0
        assert main(["train", "sdf", "--points", str(w / "ok.npz"), "--out", "sdf", "--iters",
                     "2", *SDF]) == 0  # fmt: skip
        assert main(["train", "box", "--data", str(w / "bl"), "--out", "box", "--iters", "1",
                     *BOX]) == 0  # fmt: skip
    return w


def _copy(runs: Path, kind: str, dst: Path) -> Path:
    return Path(shutil.copytree(runs / kind, dst / kind))


def _one_line(capsys, rc, *needles, status: int = 2) -> str:
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.strip() and not x.startswith("Warp ")]
    assert rc == status, (rc, err)
    assert "Traceback" not in err and len(lines) == 1, err
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


# ------------------------------------------------------------ 1: exports keep what datasets read


def _pixels(folder: Path) -> dict:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def test_export_never_replaces_the_images_a_dataset_reads(runs, tmp_path, capsys):
    """A dataset written by `export cameras` (the built-in scene's images in DATA/images), a run
    trained on it with --downscale 2, exported again into that folder: was, every full-size
    image replaced by its downscaled copy (and the dataset no longer loading)."""
    from warpnerf.data import load_nerfstudio

    data = tmp_path / "data"
    data.mkdir()
    index_file = data / "transforms.json"
    assert main(["export", str(runs / "nerf"), "cameras", "--out", str(index_file)]) == 0
    images, index = _pixels(data / "images"), (data / "transforms.json").read_bytes()
    assert images
    half = tmp_path / "half"
    assert main(["train", "nerf", "--data", str(data), "--downscale", "2", "--out", str(half),
                 "--iters", "1", "--near", "1", "--far", "4", *TN]) == 0  # fmt: skip
    capsys.readouterr()
    for out in (data / "b.json", data / "transforms.json"):
        rc = main(["export", str(half), "cameras", "--out", str(out)])
        line = _one_line(capsys, rc, "never replaces")
        assert str(data) in line, line
        assert _pixels(data / "images") == images
        assert (data / "transforms.json").read_bytes() == index
        assert not (data / "b.json").exists()
    assert load_nerfstudio(data, holdout=0).images.shape[1:3] == (8, 8)  # still loads
    # the same export again (the same pixels) keeps the images and succeeds
    assert main(["export", str(runs / "nerf"), "cameras", "--out", str(index_file)]) == 0
    assert _pixels(data / "images") == images


def test_export_never_replaces_the_index_its_run_reads(runs, tmp_path, capsys):
    """A run trained (full size) on an exported dataset: exporting it over that dataset's
    transforms.json (which the run reads on --resume, eval, render) is refused."""
    data = tmp_path / "data"
    data.mkdir()
    index_file = data / "transforms.json"
    assert main(["export", str(runs / "nerf"), "cameras", "--out", str(index_file)]) == 0
    index = (data / "transforms.json").read_bytes()
    full = tmp_path / "full"
    assert main(["train", "nerf", "--data", str(data), "--out", str(full), "--iters", "1",
                 "--near", "1", "--far", "4", *TN]) == 0  # fmt: skip
    capsys.readouterr()
    rc = main(["export", str(full), "cameras", "--out", str(data / "transforms.json")])
    _one_line(capsys, rc, str(data / "transforms.json"), "reads")
    assert (data / "transforms.json").read_bytes() == index
    assert main(["export", str(full), "cameras", "--out", str(tmp_path / "other.json")]) == 0


# ------------------------------------------------------------ 3: no read blocks on a FIFO


def _argv(case: str, runs: Path, tmp: Path, fifo) -> list:
    """The argv of an entry point with a FIFO where it reads ``case``'s file."""
    run = lambda kind: _copy(runs, kind, tmp)  # noqa: E731
    if case in ("nerf-config", "nerf-checkpoint", "nerf-run-json"):
        r = run("nerf")
        fifo(r / {"nerf-config": "config.json", "nerf-checkpoint": "checkpoint.pt",
                  "nerf-run-json": "run.json"}[case])  # fmt: skip
        return ["train", "nerf", "--out", str(r), "--resume", "--iters", "3"]
    if case in ("sdf-config", "sdf-checkpoint"):
        r = run("sdf")
        fifo(r / ("config.json" if case == "sdf-config" else "checkpoint.pt"))
        return ["train", "sdf", "--out", str(r), "--resume", "--iters", "3", "--quiet"]
    if case == "box-config":
        r = run("box")
        fifo(r / "config.json")
        return ["train", "box", "--out", str(r), "--resume", "--iters", "2", "--quiet"]
    if case in ("eval-config", "eval-checkpoint"):
        r = run("nerf")
        fifo(r / ("config.json" if case == "eval-config" else "checkpoint.pt"))
        return ["eval", str(r), "--max-images", "1"]
    if case == "export-config":
        r = run("nerf")
        fifo(r / "config.json")
        return ["export", str(r), "cameras", "--out", str(tmp / "t.json")]
    if case == "render-path":
        r = run("nerf")
        return ["render", str(r), "--path", str(fifo(tmp / "path.json")), "--size", "8x8"]
    if case == "mesh-sdf":
        return ["mesh", "--sdf", str(fifo(tmp / "scene.json")), "--out", str(tmp / "m.ply"),
                "--resolution", "8", "--no-screenshot"]  # fmt: skip
    if case in ("blender-index", "blender-image"):
        d = make_blender(tmp / "bl", n=2)
        fifo(d / ("transforms_train.json" if case == "blender-index" else "train/r_1.png"))
        return ["train", "nerf", "--data", str(d), "--out", str(tmp / "o"), "--iters", "1", *TN]
    if case == "nerfstudio-index":
        d = make_nerfstudio(tmp / "ns", n=3)
        fifo(d / "transforms.json")
        return ["train", "nerf", "--data", str(d), "--out", str(tmp / "o"), "--iters", "1", *TN]
    if case in ("colmap-model", "colmap-image"):
        from .test_capture import _colmap_capture, _object_cameras

        _colmap_capture(tmp / "cap", _object_cameras(6))
        fifo(tmp / "cap" / ("sparse/0/cameras.bin" if case == "colmap-model"
                            else "images/img_000.png"))  # fmt: skip
        return ["train", "nerf", "--data", str(tmp / "cap"), "--out", str(tmp / "o"), "--iters",
                "1", *TN]  # fmt: skip
    if case == "llff-poses":
        from .test_capture import _forward_cameras, _llff_capture

        _llff_capture(tmp / "ll", _forward_cameras(6), 20.0, [10.0, 40.0])
        fifo(tmp / "ll" / "poses_bounds.npy")
        return ["train", "nerf", "--data", str(tmp / "ll"), "--out", str(tmp / "o"), "--iters",
                "1", *TN]  # fmt: skip
    if case in ("points-npz", "points-ply"):
        cloud = fifo(tmp / ("cloud.npz" if case == "points-npz" else "cloud.ply"))
        return ["train", "sdf", "--points", str(cloud), "--out", str(tmp / "o"), "--iters", "1",
                *SDF]  # fmt: skip
    raise AssertionError(case)


# case: what the one line must say. Dataset loaders find their files by kind (is_file), so a
# FIFO there is a file they do not find: the line names the dataset or the file, not the FIFO.
FIFO_CASES = {
    "nerf-config": "FIFO", "nerf-checkpoint": "FIFO", "nerf-run-json": "run.json",
    "sdf-config": "FIFO", "sdf-checkpoint": "FIFO", "box-config": "FIFO", "eval-config": "FIFO",
    "eval-checkpoint": "FIFO", "export-config": "FIFO", "render-path": "FIFO",
    "mesh-sdf": "FIFO", "points-npz": "FIFO", "points-ply": "FIFO", "blender-index": "bl",
    "blender-image": "r_1", "nerfstudio-index": "ns", "colmap-model": "cap",
    "colmap-image": "img_000", "llff-poses": "ll",
}  # fmt: skip


@pytest.mark.parametrize("case", list(FIFO_CASES))
def test_a_fifo_in_place_of_any_input_is_refused_at_once(runs, tmp_path, capsys, fifo, case,
                                                         monkeypatch):  # fmt: skip
    """Every entry point that reads a user or run file, with a FIFO in its place: one line,
    exit 2, at once (was: the open waited for a writer forever); where a reader meets the FIFO
    the line names it."""
    monkeypatch.setattr(warpnerf.mesh, "screenshot", _no_screenshot)
    monkeypatch.chdir(tmp_path)
    argv = _argv(case, runs, tmp_path, fifo)
    capsys.readouterr()
    _one_line(capsys, main(argv), FIFO_CASES[case])


def test_the_input_reader_is_bounded_and_refuses_special_files(tmp_path, fifo):
    """``read_input``: the one reader of files a command is given or a run holds. No FIFO opened
    blocking, no device read, a link followed only where asked, bounded by bytes read."""
    (tmp_path / "ok").write_bytes(b"x" * 100)
    (tmp_path / "z").symlink_to("/dev/zero")
    (tmp_path / "l").symlink_to(tmp_path / "ok")
    fifo(tmp_path / "f")
    assert outputs.read_input(tmp_path / "ok", "file", 100) == b"x" * 100
    assert outputs.read_input(tmp_path / "l", "file", 100, follow=True) == b"x" * 100
    with pytest.raises(UserError, match="larger than 99 bytes"):
        outputs.read_input(tmp_path / "ok", "file", 99)
    for name, why, follow in (("z", "character device", True), ("l", "symbolic link", False),
                              ("f", "FIFO", True), ("absent", "no such file", True)):  # fmt: skip
        with pytest.raises(UserError, match=why) as e:
            outputs.read_input(tmp_path / name, "run config", 1 << 20, follow=follow)
        assert str(tmp_path / name) in str(e.value) and "\n" not in str(e.value)


# ------------------------------------------------------------ 5: a checkpoint's history


def _with_history(run: Path, change) -> None:
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    change(state["history"])
    torch.save(state, run / "checkpoint.pt")


HISTORIES = {
    "no seconds": lambda h: h.pop("seconds"),
    "strings in seconds": lambda h: h.update(seconds=["a"] * len(h["step"])),
    "seconds shorter than step": lambda h: h["seconds"].pop(),
    "a NaN loss": lambda h: h["loss"].__setitem__(0, float("nan")),
    "a float step": lambda h: h["step"].__setitem__(0, 1.5),
    "a list in a task's list": lambda h: h["psnr"].__setitem__(0, [1.0]),
    "a key that is no name": lambda h: h.update({3: []}),
}


@pytest.mark.parametrize("what", list(HISTORIES))
def test_a_history_the_loop_cannot_read_is_refused_on_load(runs, tmp_path, capsys, what):
    """Was: KeyError 'seconds' or TypeError (str - float) after the model had loaded."""
    run = _copy(runs, "nerf", tmp_path)
    _with_history(run, HISTORIES[what])
    rc = main(["train", "nerf", "--out", str(run), "--resume", "--iters", "3"])
    _one_line(capsys, rc, str(run / "checkpoint.pt"), "history")
    rc = main(["eval", str(run), "--max-images", "1"])
    _one_line(capsys, rc, str(run / "checkpoint.pt"), "history")


@pytest.mark.parametrize("kind", ["sdf", "box"])
def test_histories_of_every_kind_are_checked(runs, tmp_path, capsys, kind):
    run = _copy(runs, kind, tmp_path)
    _with_history(run, HISTORIES["no seconds"])
    rc = main(["train", kind, "--out", str(run), "--resume", "--iters", "3", "--quiet"])
    _one_line(capsys, rc, str(run / "checkpoint.pt"), "'seconds'")


def test_old_and_own_histories_still_load(runs):
    for kind in ("nerf", "sdf", "box"):
        ckpt = outputs.load_checkpoint(runs / kind / "checkpoint.pt", "cpu", ("step", "history"))
        assert ckpt["history"]["step"][-1] >= 1
    old = Path(__file__).parent / "data" / "runs_986359d"
    for kind in ("nerf_mlp", "nerf_hash", "sdf_mlp", "box"):
        outputs.load_checkpoint(old / kind / "checkpoint.pt", "cpu", ("step", "history"))


# ------------------------------------------------------------ 9: JSON size per kind and depth


def _deep(n: int) -> str:
    return "[" * n + "]" * n


def test_a_deep_run_json_is_named_and_counts_as_no_record(runs, tmp_path, capsys):
    """run.json nested 700 levels: was "input nested too deeply", naming no file. It is an
    unreadable record: the resume goes on, says which file it could not keep, and starts the
    record over."""
    run = _copy(runs, "nerf", tmp_path)
    (run / "run.json").write_text('{"sessions": [{"command": ' + _deep(700) + "}]}")
    with pytest.warns(UserWarning, match="nested") as seen:
        assert main(["train", "nerf", "--out", str(run), "--resume", "--iters", "3"]) == 0
    assert any(str(run / "run.json") in str(w.message) for w in seen)
    assert len(json.loads((run / "run.json").read_text())["sessions"]) == 1


@pytest.mark.parametrize("kind", ["config", "path", "scene", "transforms"])
def test_deep_json_inputs_are_refused_naming_the_file(runs, tmp_path, capsys, monkeypatch, kind):
    """700 levels parse (Python's limit is about 1000) but broke the code that walks or
    rewrites them later, with no file named."""
    monkeypatch.setattr(warpnerf.mesh, "screenshot", _no_screenshot)
    run = _copy(runs, "nerf", tmp_path)
    if kind == "config":
        cfg = json.loads((run / "config.json").read_text())
        target = run / "config.json"
        target.write_text(json.dumps(cfg)[:-1] + ', "field_options": {"x": ' + _deep(700) + "}}")
        argv = ["train", "nerf", "--out", str(run), "--resume", "--iters", "3"]
    elif kind == "path":
        target = tmp_path / "path.json"
        target.write_text('{"warpnerf_camera_path": 1, "keyframes": ' + _deep(700) + "}")
        argv = ["render", str(run), "--path", str(target), "--size", "8x8"]
    elif kind == "scene":
        target = tmp_path / "scene.json"
        target.write_text('{"primitives": ' + _deep(700) + "}")
        argv = ["mesh", "--sdf", str(target), "--out", str(tmp_path / "m.ply"), "--resolution",
                "8", "--no-screenshot"]  # fmt: skip
    else:
        d = make_nerfstudio(tmp_path / "ns", n=3)
        target = d / "transforms.json"
        js = json.loads(target.read_text())
        target.write_text(json.dumps(js)[:-1] + ', "notes": ' + _deep(700) + "}")
        argv = ["train", "nerf", "--data", str(d), "--out", str(tmp_path / "o"), "--iters", "1",
                *TN]  # fmt: skip
    capsys.readouterr()
    _one_line(capsys, main(argv), str(target), "nested")


@pytest.mark.parametrize("kind", ["path", "scene", "config"])
def test_json_inputs_are_bounded_by_what_their_kind_holds(runs, tmp_path, capsys, kind):
    """A 60 MiB camera path cost 1.8 GB to parse; each kind now has its own byte limit
    (json_input.JSON_LIMITS), far above what a valid file of that kind holds."""
    from warpnerf.json_input import JSON_LIMITS

    run = _copy(runs, "nerf", tmp_path)
    if kind == "path":
        target, what = tmp_path / "path.json", "camera path"
        argv = ["render", str(run), "--path", str(target), "--size", "8x8"]
    elif kind == "scene":
        target, what = tmp_path / "scene.json", "JSON scene"
        argv = ["mesh", "--sdf", str(target), "--out", str(tmp_path / "m.ply"), "--resolution",
                "8", "--no-screenshot"]  # fmt: skip
    else:
        target, what = run / "config.json", "run config"
        argv = ["eval", str(run), "--max-images", "1"]
    assert JSON_LIMITS[what] < 64 << 20
    target.write_bytes(b"[" + b" " * JSON_LIMITS[what] + b"]")
    capsys.readouterr()
    _one_line(capsys, main(argv), str(target), "larger than", f"{JSON_LIMITS[what] >> 20} MiB")


def test_limits_leave_room_for_the_largest_valid_files(tmp_path):
    """The largest camera path the viewer can save (1000 keyframes) reads back."""
    from warpnerf.data.camera_path import MAX_KEYFRAMES, CameraPath, load_camera_path
    from warpnerf.json_input import JSON_LIMITS

    rng = np.random.default_rng(0)
    keys = np.repeat(np.eye(4)[None], MAX_KEYFRAMES, 0)
    keys[:, :3, 3] = rng.normal(size=(MAX_KEYFRAMES, 3))
    p = CameraPath(keys, windows=np.tile([0.123456789, 6.123456789], (MAX_KEYFRAMES, 1)))
    p.save(tmp_path / "p.json")
    assert (tmp_path / "p.json").stat().st_size * 2 < JSON_LIMITS["camera path"]
    assert len(load_camera_path(tmp_path / "p.json").keyframes) == MAX_KEYFRAMES


def test_ply_readers_refuse_a_fifo(tmp_path, fifo):
    """read_ply and read_ply_points (meshes and point clouds a command is given) open through
    the one bounded regular-file reader: a FIFO is a one-line error, not a hang."""
    from warpnerf.errors import UserError
    from warpnerf.ply import read_ply, read_ply_points

    p = fifo(str(tmp_path / "mesh.ply"))
    for read in (read_ply, read_ply_points):
        with pytest.raises(UserError, match="mesh.ply"):
            read(p)
