"""How a run was made (train/provenance.py): RUN/run.json holds one session per invocation of
every kind of training (command line, times, steps, software versions, git commit, device,
world size), a resume appends its own, and eval's metrics.json names its checkpoint step and
the same versions."""

from __future__ import annotations

import datetime
import json
import os
import platform
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import warp

import warpnerf
import warpnerf.mesh
from warpnerf.cli import main
from warpnerf.train.provenance import RUN_INFO, git_commit

from .test_datasets import make_blender

ROOT = Path(__file__).resolve().parents[1]
QUIET = ["--quiet", "--no-tensorboard"]
TN = ["--batch", "32", "--samples", "4", "--layers", "2", "--width", "16", "--pos-freqs", "1",
      "--dir-freqs", "1", "--val-images", "0", *QUIET]  # fmt: skip
NEW = {  # tiny first sessions of each kind of run (data under the test's folder)
    "nerf": ["--data", "bl", *TN],
    "volsdf": ["--data", "bl", *TN, "--fine-samples", "4"],
    "sdf": ["--points", "pts.npz", "--batch", "32", "--layers", "2", "--width", "16",
            "--pos-freqs", "1", "--resolution", "8", *QUIET],
    "box": ["--data", "bl", "--batch", "16", "--samples", "4", "--frames", "0", *QUIET],
}  # fmt: skip


def _no_screenshot(*args, **kwargs):
    raise ImportError("screenshots are skipped in these tests")


@pytest.fixture
def world(tmp_path, monkeypatch):
    """The test's folder as the working directory, with a tiny Blender folder and point cloud."""
    make_blender(tmp_path / "bl", n=2)
    make_blender(tmp_path / "bl", n=1, split="val")
    g = np.random.default_rng(0).normal(size=(200, 3))
    np.savez(tmp_path / "pts.npz", points=g / np.linalg.norm(g, axis=1, keepdims=True))
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(warpnerf.mesh, "screenshot", _no_screenshot)  # (train sdf's mesh.png)
    return tmp_path


def _utc(text: str) -> datetime.datetime:
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", text), text
    return datetime.datetime.fromisoformat(text.replace("Z", "+00:00"))


def _now() -> datetime.datetime:
    return datetime.datetime.now(datetime.timezone.utc)


def _check_software(rec: dict) -> None:
    """The versions, commit and device of a session or an evaluation: this process's own."""
    assert rec["versions"] == {
        "warpnerf": warpnerf.__version__,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "warp": warp.config.version,
        "cuda": torch.version.cuda,
    }, rec["versions"]
    git = rec["git"]
    if (ROOT / ".git").exists():  # a checkout: HEAD's commit, as git itself says
        assert re.fullmatch(r"[0-9a-f]{40}", git["commit"]), git
        if shutil.which("git"):
            head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"],
                                  capture_output=True, text=True, timeout=30)  # fmt: skip
            if head.returncode == 0:
                assert git["commit"] == head.stdout.strip()
                assert isinstance(git["dirty"], bool), git
    else:
        assert git == {"commit": None, "dirty": None}
    assert rec["device"] == "cpu"
    assert isinstance(rec["device_name"], str) and rec["device_name"].strip()


def _check_session(s: dict, argv: list, start: int, iters: int, t0, t1) -> None:
    assert s["command"] == ["warpnerf", *argv]
    assert t0.replace(microsecond=0) <= _utc(s["start_time"]) <= _utc(s["end_time"]) <= t1
    assert (s["start_step"], s["end_step"], s["iters"]) == (start, iters, iters)
    assert s["outcome"] == "finished"
    assert (s["world_size"], s["nproc_per_node"]) == (1, 1)
    _check_software(s)


def _sessions(run: Path) -> list:
    return json.loads((run / RUN_INFO).read_text())["sessions"]


@pytest.mark.parametrize("kind", ["nerf", "volsdf", "sdf", "box"])
def test_each_kind_records_its_sessions_and_resume_appends(world, kind):
    first = ["train", kind, "--out", "r", "--iters", "1", *NEW[kind]]
    t0 = _now()
    assert main(first) == 0
    t1 = _now()
    (s,) = _sessions(world / "r")
    _check_session(s, first, 0, 1, t0, t1)
    config = json.loads((world / "r" / "config.json").read_text())
    assert "sessions" not in config and "command" not in config  # the settings alone

    again = ["train", kind, "--out", "r", "--resume", "--iters", "2", *QUIET]
    again += ["--frames", "0"] if kind == "box" else []
    assert main(again) == 0
    t2 = _now()
    a, b = _sessions(world / "r")
    assert a == s  # the first session kept as it was
    _check_session(b, again, 1, 2, t1, t2)
    config = json.loads((world / "r" / "config.json").read_text())
    assert "sessions" not in config and "command" not in config


def test_eval_metrics_name_the_checkpoint_step_and_versions(world):
    assert main(["train", "nerf", "--out", "r", "--iters", "2", *NEW["nerf"]]) == 0
    t0 = _now()
    argv = ["eval", "r", "--max-images", "1"]
    assert main(argv) == 0
    m = json.loads((world / "r" / "eval_val" / "metrics.json").read_text())
    assert (m["step"], m["checkpoint"]) == (2, "checkpoint.pt")
    p = m["provenance"]
    assert p["command"] == ["warpnerf", *argv]
    assert t0.replace(microsecond=0) <= _utc(p["time"]) <= _now()
    _check_software(p)
    (s,) = _sessions(world / "r")
    assert (p["versions"], p["git"]["commit"]) == (s["versions"], s["git"]["commit"])


def test_runs_from_before_run_json_and_copied_runs_resume(world):
    assert main(["train", "nerf", "--out", "r", "--iters", "1", *NEW["nerf"]]) == 0
    (world / "r" / RUN_INFO).unlink()  # a run from before provenance: resumes, records from now
    assert main(["train", "nerf", "--out", "r", "--resume", "--iters", "2", *QUIET]) == 0
    (s,) = _sessions(world / "r")
    assert (s["start_step"], s["end_step"]) == (1, 2)
    # a copied run (run.json no longer matches the folder's manifest) resumes and appends
    shutil.copytree(world / "r", world / "c")
    os.utime(world / "c" / RUN_INFO, (1e9, 1e9))
    assert main(["train", "nerf", "--out", "c", "--resume", "--iters", "3", *QUIET]) == 0
    assert [x["end_step"] for x in _sessions(world / "c")] == [2, 3]
    # an unreadable record does not stop a resume: it starts over with this session
    (world / "c" / RUN_INFO).write_text("{not json")
    assert main(["train", "nerf", "--out", "c", "--resume", "--iters", "4", *QUIET]) == 0
    assert [x["start_step"] for x in _sessions(world / "c")] == [3]


def test_a_foreign_run_json_is_not_replaced(world, capsys):
    (world / "r").mkdir()
    (world / "r" / RUN_INFO).write_text("my notes")
    assert main(["train", "nerf", "--out", "r", "--iters", "1", *NEW["nerf"]]) == 2
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.startswith("warpnerf ")]
    assert len(lines) == 1 and "run.json" in lines[0] and "not written by warpnerf" in lines[0], err
    assert (world / "r" / RUN_INFO).read_text() == "my notes"
    assert not (world / "r" / "checkpoint.pt").exists()


def _fake_checkout(root: Path, head: str, **files) -> Path:
    (root / ".git").mkdir(parents=True)
    (root / ".git" / "HEAD").write_text(head + "\n")
    for name, text in files.items():
        p = root / ".git" / name.replace("__", "/")
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return root


def test_git_commit_reads_heads_refs_and_packed_refs_without_git(tmp_path):
    a, b = "a" * 40, "0123456789abcdef" * 2 + "01234567"
    loose = _fake_checkout(tmp_path / "loose", "ref: refs/heads/main", refs__heads__main=a + "\n")
    assert git_commit(loose)["commit"] == a
    packed = _fake_checkout(tmp_path / "packed", "ref: refs/heads/dev",
                            **{"packed-refs": f"# pack-refs\n{a} refs/heads/main\n"
                                              f"{b} refs/heads/dev\n"})  # fmt: skip
    assert git_commit(packed)["commit"] == b
    assert git_commit(_fake_checkout(tmp_path / "detached", b))["commit"] == b
    # a worktree: .git is a file naming the git folder
    (tmp_path / "wt").mkdir()
    (tmp_path / "wt" / ".git").write_text(f"gitdir: {loose / '.git'}\n")
    assert git_commit(tmp_path / "wt")["commit"] == a
    # not a checkout, an unborn branch, a HEAD that is not a commit: nothing known
    assert git_commit(tmp_path / "nothing") == {"commit": None, "dirty": None}
    unborn = _fake_checkout(tmp_path / "unborn", "ref: refs/heads/main")
    assert git_commit(unborn) == {"commit": None, "dirty": None}
    assert git_commit(_fake_checkout(tmp_path / "junk", "x" * 40))["commit"] is None


@pytest.mark.slow
def test_data_parallel_sessions_record_the_world_size(tmp_path):
    """Two gloo ranks under torchrun: rank 0 writes run.json with world size 2; a resume in one
    process appends a session of world size 1."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = dict(os.environ, WARPNERF_DIST_TIMEOUT="120", OMP_NUM_THREADS="1")
    cmd = ["-m", "warpnerf.cli", "train", "nerf", "--data", "builtin", "--builtin-size", "8",
           "--out", "r", "--iters", "1", *TN]  # fmt: skip
    launch = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node=2",
              "--master-addr=127.0.0.1", f"--master-port={port}"]  # fmt: skip
    res = subprocess.run([*launch, *cmd], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=600)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    (s,) = _sessions(tmp_path / "r")
    assert (s["world_size"], s["nproc_per_node"]) == (2, 2)
    assert s["command"][1:] == cmd[2:]  # (argv[0] is the module's path)
    resume = ["-m", "warpnerf.cli", "train", "nerf", "--out", "r", "--resume", "--iters", "2"]
    res = subprocess.run([sys.executable, *resume, *QUIET], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=600)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    assert [x["world_size"] for x in _sessions(tmp_path / "r")] == [2, 1]
