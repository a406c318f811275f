"""Issue 43, items 5, 6 and 8: lock files, splits the data does not have, and tools reading a run
that is still training.

  5  a refused `train` leaves nothing in the folder; a finished train, eval or render removes its
     lock file (no lock files with dead pids); a lock file removed by its holder while another
     process opened it is never trusted (the locker takes the file that is in the folder)
  6  `eval --split test` on data without a test split (the built-in scene, Blender split files,
     a nerfstudio folder whose frames name their splits) is refused naming the splits it has
     (it scored the val images before); the hold-out formats keep val and test (documented)
  8  eval, render, mesh and export on a run whose lock a live training holds print one note
     naming the holder's pid and the step of the checkpoint they read
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from warpnerf import outputs, safe_writes
from warpnerf.cli import main
from warpnerf.errors import UserError

TN = ["--batch", "32", "--samples", "4", "--layers", "2", "--width", "16", "--pos-freqs", "1",
      "--dir-freqs", "1", "--val-images", "0", "--quiet", "--no-tensorboard"]  # fmt: skip
NEW = ["--data", "builtin", "--builtin-size", "8", "--near", "1", "--far", "4", *TN]


def _err_lines(capsys) -> list:
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return [x for x in err.splitlines() if x.strip() and not x.startswith("Warp ")]


def _locks(folder: Path) -> list:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob(outputs.LOCK))


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """A tiny finished NeRF run on the built-in scene (2 steps)."""
    w = tmp_path_factory.mktemp("locks43")
    assert main(["train", "nerf", "--out", str(w / "run"), "--iters", "2", *NEW]) == 0
    return w / "run"


@pytest.fixture
def run(base, tmp_path) -> Path:
    return Path(shutil.copytree(base, tmp_path / "run"))


# ------------------------------------------------------------ 5: lock files left behind


def test_finished_commands_remove_their_lock_files(base, run, capsys):
    """A finished train leaves no lock file in its run, nor eval and render in theirs."""
    assert _locks(base) == []
    assert main(["eval", str(run), "--max-images", "1"]) == 0
    assert main(["render", str(run), "--frames", "1", "--size", "8x8"]) == 0
    assert main(["train", "nerf", "--out", str(run), "--resume", "--iters", "3", "--quiet"]) == 0
    assert (run / "eval_val" / "metrics.json").is_file()
    assert _locks(run) == []


def test_refused_train_leaves_nothing(tmp_path, capsys):
    """A folder holding the user's own config.json: `train` refuses it and leaves it as it was
    (no lock file)."""
    out = tmp_path / "mine"
    out.mkdir()
    (out / "config.json").write_text('{"mine": true}\n')
    rc = main(["train", "nerf", "--out", str(out), "--iters", "1", *NEW])
    lines = _err_lines(capsys)
    assert rc == 2 and len(lines) == 1 and "config.json" in lines[0], lines
    assert sorted(p.name for p in out.iterdir()) == ["config.json"]


def test_refusal_in_a_new_folder_leaves_no_folder(tmp_path):
    """A lock that made its folder and is released with nothing written leaves no folder."""
    with pytest.raises(UserError), safe_writes.output_lock(tmp_path / "new" / "deeper"):
        assert (tmp_path / "new" / "deeper" / outputs.LOCK).is_file()
        raise UserError("refused")
    assert list((tmp_path / "new").iterdir()) == []


def test_a_lock_file_removed_under_the_locker_is_not_trusted(tmp_path, monkeypatch):
    """The previous holder removes the lock file between our open and our lock (and a third
    process makes a new one): the lock taken on the removed file locks nothing, so the locker
    opens the file in the folder again and holds that one."""
    folder = tmp_path / "f"
    folder.mkdir()
    real, calls = safe_writes._try_lock, []

    def racing(fd):
        if not calls:  # the holder finished: unlinked the file we opened; another made a new one
            os.unlink(folder / outputs.LOCK)
            (folder / outputs.LOCK).write_text("12345\n")
        calls.append(os.fstat(fd).st_ino)
        return real(fd)

    monkeypatch.setattr(safe_writes, "_try_lock", racing)
    with safe_writes.output_lock(folder):
        assert len(calls) == 2 and calls[0] != calls[1]
        assert os.lstat(folder / outputs.LOCK).st_ino == calls[1]
        assert (folder / outputs.LOCK).read_text() == f"{os.getpid()}\n"
        assert safe_writes.lock_holder(folder) is None  # (this process's own lock: no note)
    assert not (folder / outputs.LOCK).exists()


def test_release_keeps_a_lock_file_it_does_not_hold(tmp_path):
    """Only the file this process holds is removed: one that replaced it meanwhile stays."""
    folder = tmp_path / "f"
    with safe_writes.output_lock(folder):
        os.unlink(folder / outputs.LOCK)
        (folder / outputs.LOCK).write_text("someone else's\n")
    assert (folder / outputs.LOCK).read_text() == "someone else's\n"


# ------------------------------------------------------------ 6: splits the data does not have


def test_eval_refuses_a_split_the_builtin_scene_lacks(run, capsys):
    """`eval --split test` of a built-in run scored the val images (identical PNGs and PSNR)."""
    rc = main(["eval", str(run), "--split", "test", "--max-images", "1"])
    lines = _err_lines(capsys)
    assert rc == 2 and len(lines) == 1, lines
    assert "test" in lines[0] and "train, val" in lines[0], lines
    assert not (run / "eval_test").exists()


def _cfg(data, fmt="auto", holdout=8):
    from warpnerf.train.nerf_config import NeRFConfig

    return NeRFConfig(data=str(data), data_format=fmt, holdout=holdout, device="cpu")


def test_split_files_and_named_frames_are_the_splits(tmp_path):
    """Blender split files and nerfstudio frames that name their split: a split none of them
    has is refused naming those it has (nerfstudio's test was silently its val)."""
    from warpnerf.train.nerf_run import load_data

    from .test_datasets import make_blender, make_nerfstudio

    bl = tmp_path / "bl"
    make_blender(bl, n=2)
    make_blender(bl, n=2, split="val")
    for fmt in ("auto", "blender"):
        with pytest.raises(UserError, match=r"no 'test' split.*train, val"):
            load_data(_cfg(bl, fmt), "test")
        assert len(load_data(_cfg(bl, fmt), "val")) == 2
    named = {i: {"split": "val" if i % 2 else "train"} for i in range(4)}
    ns = make_nerfstudio(tmp_path / "ns", n=4, per_frame=named)
    with pytest.raises(UserError, match=r"no 'test' split.*train, val"):
        load_data(_cfg(ns), "test")
    assert len(load_data(_cfg(ns), "val")) == 2


def test_held_out_images_stay_val_and_test(tmp_path):
    """Formats without split files hold out every k-th image as val and test (documented):
    both names load the same images."""
    from warpnerf.train.nerf_run import load_data

    from .test_datasets import make_blender

    one = tmp_path / "one"
    make_blender(one, n=4)
    (one / "transforms_train.json").rename(one / "transforms.json")
    val, test = load_data(_cfg(one, holdout=2), "val"), load_data(_cfg(one, holdout=2), "test")
    assert len(val) == len(test) == 2


# ------------------------------------------------------------ 8: tools on a run still training

_HOLD = """
import sys, time
from warpnerf.outputs import output_lock
with output_lock(sys.argv[1], "run folder"):
    print("locked", flush=True)
    time.sleep(120)
"""


def test_tools_say_the_run_is_still_training(run, tmp_path, capsys, monkeypatch):
    """A process holds RUN's lock, as a training does: eval, render, mesh and export read the
    run (the lock guards writers only) and say once that it is still training, at which step."""
    import warpnerf.mesh

    def no_screenshot(*a, **k):
        raise ImportError("no screenshots in this test")

    monkeypatch.setattr(warpnerf.mesh, "screenshot", no_screenshot)
    MESH = ["--resolution", "8", "--no-screenshot", "--keep-all", "--level", "0.33"]
    commands = {
        "eval": ["eval", str(run), "--max-images", "1"],
        "render": ["render", str(run), "--frames", "1", "--size", "8x8"],
        "mesh": ["mesh", str(run), "--out", str(run / "mesh.ply"), *MESH],
        "export": ["export", str(run), "cameras", "--out", str(tmp_path / "ex" / "t.json")],
    }
    p = subprocess.Popen([sys.executable, "-c", _HOLD, str(run)], stdout=subprocess.PIPE,
                         text=True)  # fmt: skip
    try:
        assert p.stdout.readline().strip() == "locked"
        assert safe_writes.lock_holder(run) == str(p.pid)
        for name, argv in commands.items():
            rc = main(argv)
            lines = _err_lines(capsys)
            assert rc == 0 or name == "mesh" and "no surface" in lines[-1], (name, lines)
            notes = [x for x in lines if "still training" in x]
            assert len(notes) == 1, (name, notes)
            assert f"{run} is still training (lock held by pid {p.pid})" in notes[0], notes
            assert "reading its checkpoint at step 2" in notes[0], notes
        assert safe_writes.lock_holder(run) == str(p.pid)  # (the probe takes nothing away)
    finally:
        p.kill()
        p.wait()
    assert safe_writes.lock_holder(run) is None
    main(commands["eval"])
    assert not [x for x in _err_lines(capsys) if "still training" in x]
