"""Security and reliability, round 4 (issue 45): sizes and limits read from runs, flags and
datasets.

  2  a run's config.json cannot ask for a model larger than its checkpoint holds (eval, render,
     mesh refuse it before building the model, instead of growing until the OOM killer)
  4  values past the kernels' limits (float32 distances, int32 samples and rays) are refused by
     the config checks, from config.json and from flags, before a run folder exists
  6  a nerfstudio ``warpnerf_scene`` with a vanishing box is refused; `warpnerf data` reports
     the scene the data resolves to
  7  LLFF and COLMAP images that are links out of the dataset need --allow-outside-paths
  8  render/eval numbers (--size, --frames, --chunk) are checked before any work
"""

from __future__ import annotations

import contextlib
import json
import resource
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

import warpnerf.mesh
from warpnerf.cli import main
from warpnerf.data import load_dataset
from warpnerf.errors import UserError

from .test_capture import _colmap_capture, _forward_cameras, _llff_capture, _object_cameras
from .test_datasets import make_nerfstudio
from .test_hostile_runs import _copy, _no_screenshot, _one_line, _tamper, runs  # noqa: F401

TINY = ["--iters", "2", "--batch", "32", "--val-images", "0", "--quiet", "--no-tensorboard"]
MLP = [*TINY, "--samples", "4", "--layers", "2", "--width", "16", "--pos-freqs", "1",
       "--dir-freqs", "1"]  # fmt: skip
HASH = [*TINY, "--field", "hash", "--hash-levels", "2", "--hash-log2-size", "8",
        "--hash-max-res", "16", "--hidden", "8", "--grid-res", "8",
        "--appearance-dim", "2"]  # fmt: skip


@pytest.fixture(scope="module")
def hash_runs(runs):  # noqa: F811 (test_hostile_runs' fixture)
    """test_hostile_runs' tiny runs (NeRF MLP, VolSDF, neural SDF, box) and a hash run with
    appearance codes beside them."""
    assert main(["train", "nerf", "--data", str(runs / "bl"), "--out", str(runs / "hash"),
                 *HASH]) == 0  # fmt: skip
    return runs


@contextlib.contextmanager
def _memory_cap(extra: int = 3 << 30):
    """This process's address space limited to what it has now + ``extra`` bytes while the
    block runs: code that would grow without bound (the failure these tests guard against) ends
    in a MemoryError instead of the OOM killer."""
    with open("/proc/self/status") as f:
        vm = next(int(ln.split()[1]) * 1024 for ln in f if ln.startswith("VmSize:"))
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    resource.setrlimit(resource.RLIMIT_AS, (vm + extra, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


# ------------------------------------------------ 2: sizes bounded by what the checkpoint holds

EVAL = ["eval", "RUN", "--max-images", "1"]
RENDER = ["render", "RUN", "--frames", "1", "--size", "8x8"]
MESH = ["mesh", "RUN", "--out", "m.ply", "--resolution", "8", "--no-screenshot"]
OVERSIZED = [  # (run, config fields, command)
    ("nerf", {"n_layers": 2**31 - 1}, EVAL),
    ("nerf", {"width": 2**20}, RENDER),
    ("hash", {"hash_log2_size": 24, "hash_max_res": 2048}, EVAL),
    ("hash", {"hash_levels": 64, "hash_log2_size": 19, "hash_max_res": 2048}, RENDER),
    ("hash", {"hidden": 2**20}, EVAL),
    ("hash", {"appearance_images": 10**6, "appearance_dim": 256}, EVAL),
    ("sdf", {"n_layers": 2**31 - 1}, MESH),
    ("sdf", {"width": 2**20}, MESH),
]


@pytest.mark.parametrize("kind,fields,argv", OVERSIZED, ids=lambda x: str(x)[:40])
def test_a_config_cannot_ask_for_more_than_its_checkpoint_holds(
    hash_runs, tmp_path, monkeypatch, capsys, kind, fields, argv
):
    run = _copy(hash_runs, kind, tmp_path)
    _tamper(run, **fields)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(warpnerf.mesh, "screenshot", _no_screenshot)
    capsys.readouterr()
    t0 = time.perf_counter()
    with _memory_cap():
        rc = main([str(run) if a == "RUN" else a for a in argv])
    _one_line(capsys, rc, 2, str(run / "config.json"), str(run / "checkpoint.pt"))
    assert time.perf_counter() - t0 < 30
    assert not list(run.glob("render_*")) and not (tmp_path / "m.ply").exists()


def test_runs_of_their_own_size_still_load(hash_runs, tmp_path, capsys):
    for kind in ("nerf", "hash"):
        run = _copy(hash_runs, kind, tmp_path)
        assert main(["eval", str(run), "--max-images", "1", "--quiet"]) == 0, kind
    run = _copy(hash_runs, "sdf", tmp_path)
    assert main(["mesh", str(run), "--out", str(tmp_path / "m.ply"), "--resolution", "8",
                 "--no-screenshot", "--quiet"]) == 0  # fmt: skip


# ------------------------------------------------ 4: the kernels' limits, checked with the config

PAST_LIMITS = [  # (config fields, words of the error)
    ({"far": 1e39}, ["'far'"]),
    ({"aabb": 1e39}, ["'aabb'"]),
    ({"near": 1e38, "far": 3e38}, ["'near'"]),
    ({"n_coarse": 10**8}, ["n_coarse"]),
    ({"n_fine": 10**8}, ["n_fine"]),
    ({"chunk": 2**31 - 1}, ["chunk"]),
    ({"builtin_size": 2**31 - 1}, ["'builtin_size'"]),
]


@pytest.mark.parametrize("fields,words", PAST_LIMITS, ids=lambda x: str(x)[:30])
def test_config_values_past_the_kernels_limits_are_refused(hash_runs, tmp_path, capsys, fields,
                                                           words):  # fmt: skip
    run = _copy(hash_runs, "nerf", tmp_path)
    _tamper(run, **fields)
    rc = main(["eval", str(run), "--max-images", "1"])
    _one_line(capsys, rc, 2, "config.json", *words)


FLAGS_PAST_LIMITS = [
    (["--far", "1e39"], "--far"),
    (["--near", "0", "--far", "1e39"], "--far"),
    (["--aabb", "1e39"], "--aabb"),
    (["--samples", "100000000"], "--samples"),
    (["--batch", str(10**9)], "--batch"),
    (["--data", "builtin", "--builtin-size", "2147483647"], "--builtin-size"),
]


@pytest.mark.parametrize("flags,word", FLAGS_PAST_LIMITS, ids=lambda x: str(x)[:30])
def test_flags_past_the_kernels_limits_leave_no_run_folder(hash_runs, tmp_path, capsys, flags,
                                                           word):  # fmt: skip
    out = tmp_path / "run"
    argv = ["train", "nerf", "--data", str(hash_runs / "bl"), *MLP, "--out", str(out), *flags]
    with _memory_cap():
        rc = main(argv)
    _one_line(capsys, rc, 2, word)
    assert not out.exists()
    rc = main(["train", "nerf", "--out", str(out), "--resume", "--iters", "3"])
    _one_line(capsys, rc, 2, "not found")


# ------------------------------------------------ 6: the scene block of an exported capture


@pytest.mark.parametrize("block,word", [
    ({"near": 0.5, "far": 6.0, "aabb": 1e-300}, "aabb"),
    ({"near": 0.5, "far": 6.0, "aabb": 1.5, "inner": 1e-300}, "inner"),
])  # fmt: skip
def test_a_vanishing_scene_block_is_refused(tmp_path, capsys, block, word):
    root = make_nerfstudio(tmp_path / "ns", n=4, top={"warpnerf_scene": block})
    out = tmp_path / "run"
    rc = main(["train", "nerf", "--data", str(root), *HASH, "--out", str(out)])
    _one_line(capsys, rc, 2, "transforms.json", f"warpnerf_scene.{word}")
    assert not out.exists()


def test_a_vanishing_saved_scene_is_refused(hash_runs, tmp_path, capsys):
    run = _copy(hash_runs, "hash", tmp_path)
    scene = {"format": "nerfstudio", "transform": np.eye(4).tolist(), "ndc": None,
             "near": 0.5, "far": 6.0, "aabb": 1e-300}  # fmt: skip
    _tamper(run, scene=scene)
    rc = main(["eval", str(run), "--max-images", "1"])
    _one_line(capsys, rc, 2, "config.json", "'scene'", "aabb")


def test_data_reports_the_scene_of_an_exported_capture(tmp_path, capsys):
    block = {"near": 0.25, "far": 9.5, "aabb": 1.25, "inner": 0.75}
    root = make_nerfstudio(tmp_path / "ns", n=4, top={"warpnerf_scene": block})
    capsys.readouterr()
    assert main(["data", str(root)]) == 0
    info = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (info["near"], info["far"]) == (0.25, 9.5)
    assert (info["aabb"], info["inner"]) == (1.25, 0.75)


# ------------------------------------------------ 7: capture images that link out of the dataset


def _link_out(folder: Path, name: str, outside: Path) -> None:
    outside.mkdir(exist_ok=True)
    shutil.move(folder / name, outside / name)
    (folder / name).symlink_to(outside / name)


def _capture(tmp_path: Path, fmt: str) -> tuple[Path, Path]:
    root = tmp_path / "cap"
    if fmt == "llff":
        _llff_capture(root, _forward_cameras(9), 20.0, [10.0, 40.0])
        return root, root / "images"
    _colmap_capture(root, _object_cameras(9))
    return root, root / "images"


@pytest.mark.parametrize("fmt", ["llff", "colmap"])
@pytest.mark.parametrize("which", ["first", "later"])
def test_capture_images_linked_out_of_the_dataset_need_the_opt_in(tmp_path, capsys, fmt, which):
    root, images = _capture(tmp_path, fmt)
    name = sorted(p.name for p in images.iterdir())[0 if which == "first" else 5]
    _link_out(images, name, tmp_path / "secret")
    with pytest.raises(UserError) as e:
        load_dataset(root, "train", holdout=0)
    msg = str(e.value)
    assert name in msg and "--allow-outside-paths" in msg and str(tmp_path / "secret") in msg
    assert len(load_dataset(root, "train", holdout=0, allow_outside=True)) == 9
    capsys.readouterr()
    _one_line(capsys, main(["data", str(root)]), 2, name, "--allow-outside-paths")
    assert main(["data", str(root), "--allow-outside-paths"]) == 0


@pytest.mark.parametrize("fmt", ["llff", "colmap"])
def test_capture_images_folder_linked_out_needs_the_opt_in(tmp_path, capsys, fmt):
    root, images = _capture(tmp_path, fmt)
    shutil.move(images, tmp_path / "elsewhere")
    images.symlink_to(tmp_path / "elsewhere")
    out = tmp_path / "run"
    rc = main(["train", "nerf", "--data", str(root), *MLP, "--out", str(out)])
    _one_line(capsys, rc, 2, "--allow-outside-paths")
    assert not out.exists()
    assert main(["train", "nerf", "--data", str(root), *MLP, "--out", str(out),
                 "--allow-outside-paths"]) == 0  # fmt: skip


# ------------------------------------------------ 8: render / eval numbers checked first

BAD_TOOL_FLAGS = [
    (["render", "RUN", "--size", "8x1"], "--size"),
    (["render", "RUN", "--size", "1x8"], "--size"),
    (["render", "RUN", "--size", "65536x2"], "--size"),
    (["render", "RUN", "--size", "16384x16384"], "--size"),
    (["render", "RUN", "--frames", str(10**12)], "--frames"),
    (["eval", "RUN", "--chunk", str(10**20)], "--chunk"),
    (["eval", "RUN", "--march-step", "1e39"], "--march-step"),
    (["eval", "RUN", "--geometry", "materials", "--mesh-resolution", str(10**6)],
     "--mesh-resolution"),
    (["eval", "RUN", "--geometry", "materials", "--geometry-points", str(10**15)],
     "--geometry-points"),
]  # fmt: skip


@pytest.mark.parametrize("argv,word", BAD_TOOL_FLAGS,
                         ids=[" ".join(a[2:]) for a, _ in BAD_TOOL_FLAGS])  # fmt: skip
def test_render_and_eval_numbers_are_checked_before_any_work(hash_runs, tmp_path, monkeypatch,
                                                             capsys, argv, word):  # fmt: skip
    import warpnerf.train.nerf_eval
    import warpnerf.train.nerf_run

    run = _copy(hash_runs, "nerf", tmp_path)

    def no_work(*args, **kwargs):
        raise AssertionError("the run was loaded before the flags were checked")

    monkeypatch.setattr(warpnerf.train.nerf_run, "load_run", no_work)
    monkeypatch.setattr(warpnerf.train.nerf_eval, "load_run", no_work)
    capsys.readouterr()
    t0 = time.perf_counter()
    rc = main([str(run) if a == "RUN" else a for a in argv])
    _one_line(capsys, rc, 2, word)
    assert time.perf_counter() - t0 < 10
    assert not list(run.glob("render_*")) and not list(run.glob("eval_*"))


def test_eval_chunk_times_the_runs_samples_stays_within_int32(hash_runs, tmp_path, capsys):
    run = _copy(hash_runs, "nerf", tmp_path)  # (4 samples a ray)
    rc = main(["eval", str(run), "--chunk", str(2**30)])
    _one_line(capsys, rc, 2, "--chunk", "--samples", "int32")
    assert not list(run.glob("eval_*"))


def test_the_smallest_video_renders(hash_runs, tmp_path):
    run = _copy(hash_runs, "nerf", tmp_path)
    assert main(["render", str(run), "--size", "2x2", "--frames", "1", "--quiet"]) == 0
    assert (run / "render_spiral" / "rgb.mp4").stat().st_size > 0
