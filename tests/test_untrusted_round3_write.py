"""Security round 3, the writing side (issue 32): what a downloaded run or output folder can make
the commands that write into it do.

  1  links and special files where warpnerf writes: a planted symbolic link (lock file, manifest,
     output folder, output file) never makes a command write outside the folder, a FIFO manifest
     never hangs it, a link to an endless device is never read without bound: exit 2, one line
  7  refusals come before any write (export cameras with a foreign transforms.json)
  8  manifests scale: 30k outputs recorded and recognised in seconds, none disowned; the old
     (one JSON object) manifest still reads
  9  a data-parallel rank that dies: the survivor stops with one line, no traceback

Every entry point that writes (train, train --resume, eval, render, mesh, export and the viewer's
camera-path save) is tried with each planted file.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from warpnerf import outputs, safe_writes
from warpnerf.cli import main
from warpnerf.errors import UserError

TN = ["--batch", "32", "--samples", "4", "--layers", "2", "--width", "16", "--pos-freqs", "1",
      "--dir-freqs", "1", "--val-images", "0", "--quiet", "--no-tensorboard"]  # fmt: skip
NEW = ["--data", "builtin", "--builtin-size", "8", "--near", "1", "--far", "4", *TN]


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """A tiny finished NeRF run on the built-in scene (whose images export writes)."""
    w = tmp_path_factory.mktemp("round3")
    assert main(["train", "nerf", "--out", str(w / "run"), "--iters", "2", *NEW]) == 0
    return w / "run"


@pytest.fixture
def run(base, tmp_path) -> Path:
    return Path(shutil.copytree(base, tmp_path / "run"))


@pytest.fixture
def victim(tmp_path) -> Path:
    """A file outside the run folder that nothing may touch."""
    p = tmp_path / "outside" / "victim.txt"
    p.parent.mkdir()
    p.write_text("the user's file")
    return p


def _one_line(capsys, rc, *needles) -> str:
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.strip() and not x.startswith("Warp ")]
    assert rc == 2, (rc, err)
    assert "Traceback" not in err and len(lines) == 1, err
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


# each entry point that writes: its argv (RUN: the run folder, OUT: a folder beside it) and the
# folder it writes its lock and manifest into
COMMANDS = {
    "train": (["train", "nerf", "--out", "OUT", "--iters", "1", *NEW], "OUT"),
    "resume": (["train", "nerf", "--out", "RUN", "--resume", "--iters", "3", "--quiet"], "RUN"),
    "eval": (["eval", "RUN", "--max-images", "1"], "RUN/eval_val"),
    "render": (["render", "RUN", "--frames", "1", "--size", "8x8"], "RUN/render_spiral"),
    "mesh": (
        ["mesh", "--sdf", "torus", "--out", "OUT/m.ply", "--resolution", "8", "--no-screenshot"],
        "OUT",
    ),  # fmt: skip
    "export": (["export", "RUN", "cameras", "--out", "OUT/transforms.json"], "OUT"),
}
LOCKED = ("train", "resume", "eval", "render")  # the commands that lock their folder


def _argv(name, run):
    argv, folder = COMMANDS[name]
    out = run.parent / "out"
    sub = {"RUN": str(run), "OUT": str(out)}
    argv = [a.replace("RUN", sub["RUN"]).replace("OUT", sub["OUT"]) for a in argv]
    folder = Path(folder.replace("RUN", sub["RUN"]).replace("OUT", sub["OUT"]))
    folder.mkdir(parents=True, exist_ok=True)
    return argv, folder


# ------------------------------------------------------------ 1: links and special files


@pytest.mark.parametrize("name", LOCKED)
def test_lock_file_link_is_refused(run, victim, capsys, name):
    """A lock file that links elsewhere was opened, truncated and written (the pid)."""
    argv, folder = _argv(name, run)
    with contextlib.suppress(FileNotFoundError):
        (folder / outputs.LOCK).unlink()  # (a finished run keeps its stale lock file)
    (folder / outputs.LOCK).symlink_to(victim)
    _one_line(capsys, main(argv), str(folder / outputs.LOCK), "link")
    assert victim.read_text() == "the user's file"


def _plant_manifest(folder: Path, kind: str, victim: Path, fifo) -> Path:
    """A manifest in ``folder`` that is a link to ``victim``, a FIFO or a link to /dev/zero."""
    m = folder / outputs.MANIFEST
    with contextlib.suppress(FileNotFoundError):
        m.unlink()
    if kind == "link":
        m.symlink_to(victim)
    elif kind == "fifo":
        fifo(m)
    else:
        m.symlink_to("/dev/zero")
    return m


@pytest.mark.parametrize("kind", ["link", "fifo", "devzero"])
@pytest.mark.parametrize("name", list(COMMANDS))
def test_planted_manifest_is_refused(run, victim, capsys, fifo, name, kind):
    """A manifest that is a link (to a file outside, or to /dev/zero: read without bound) or a
    FIFO (the command hung on it) is refused before anything is written."""
    argv, folder = _argv(name, run)
    m = _plant_manifest(folder, kind, victim, fifo)
    before = sorted(p.name for p in folder.iterdir())
    _one_line(capsys, main(argv), str(m))
    assert victim.read_text() == "the user's file"
    after = sorted(p.name for p in folder.iterdir())
    assert set(after) - {outputs.LOCK} == set(before) - {outputs.LOCK}, (before, after)


@pytest.mark.parametrize("name", ["eval", "render", "export", "snapshots"])
def test_output_folder_link_is_refused(run, tmp_path, capsys, name):
    """A folder warpnerf makes in a run (eval_*, render_*, snapshots/, export's images/) that is a
    link to another folder: the whole output went there."""
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    if name == "snapshots":
        argv, folder = _argv("train", run)
        argv += ["--snapshots", "1"]
        link = folder / "snapshots"
    else:
        argv, folder = _argv(name, run)
        if name == "export":
            link = folder / "images"
        else:
            folder.rmdir()
            link = folder
    link.symlink_to(elsewhere, target_is_directory=True)
    _one_line(capsys, main(argv), str(link), "link")
    assert list(elsewhere.iterdir()) == []


@pytest.mark.parametrize("name", ["train", "resume", "eval", "render", "export"])
def test_output_file_link_is_refused(run, victim, capsys, name):
    """An output file that is a link (a checkpoint, a metrics file, a frame) is never written
    through."""
    target = {"train": "config.json", "resume": "history.json", "eval": "metrics.json",
              "render": "rgb_000.png", "export": "transforms.json"}[name]  # fmt: skip
    argv, folder = _argv(name, run)
    if name == "resume":
        (folder / target).unlink()
    (folder / target).symlink_to(victim)
    _one_line(capsys, main(argv), target)
    assert victim.read_text() == "the user's file"


def test_special_file_in_place_of_an_output_is_refused(run, capsys, fifo):
    argv, folder = _argv("eval", run)
    fifo(folder / "metrics.json")
    _one_line(capsys, main(argv), "metrics.json")
    assert sorted(p.name for p in folder.iterdir()) == ["metrics.json"]  # (no lock file left)


@pytest.mark.parametrize("kind", ["link", "fifo", "devzero"])
def test_camera_path_save_refuses_planted_files(tmp_path, victim, fifo, kind):
    """The viewer's "Save path" writes through CameraPath.save (outputs.write_json): a planted
    manifest beside it is refused the same way."""
    import numpy as np

    from warpnerf.data.camera_path import CameraPath

    _plant_manifest(tmp_path, kind, victim, fifo)
    with pytest.raises(UserError, match="warpnerf-files"):
        CameraPath([np.eye(4)]).save(tmp_path / "path.json")
    assert not (tmp_path / "path.json").exists()
    assert victim.read_text() == "the user's file"


def test_read_regular_is_bounded_and_refuses_special_files(tmp_path, victim, fifo):
    """The reader of files warpnerf wrote earlier: bounded by the bytes it reads (not st_size,
    which is 0 for /dev/zero), no link followed, no FIFO opened blocking."""
    (tmp_path / "z").symlink_to("/dev/zero")
    (tmp_path / "l").symlink_to(victim)
    fifo(tmp_path / "f")
    for name in ("z", "l", "f"):
        with pytest.raises(UserError, match=str(tmp_path / name)):
            outputs.read_regular(tmp_path / name, 1 << 20, "file")
    (tmp_path / "big").write_bytes(b"x" * 101)
    with pytest.raises(UserError, match="100 bytes"):
        outputs.read_regular(tmp_path / "big", 100, "file")
    assert outputs.read_regular(tmp_path / "big", 101, "file") == b"x" * 101
    assert outputs.read_regular(tmp_path / "absent", 100, "file") is None


# ------------------------------------------------------------ 7: refusals before any write


def test_export_refuses_before_writing_images(run, capsys):
    out = run.parent / "out"
    out.mkdir()
    (out / "transforms.json").write_text("the user's own cameras")
    rc = main(["export", str(run), "cameras", "--out", str(out / "transforms.json")])
    _one_line(capsys, rc, "transforms.json", "not written by warpnerf")
    assert sorted(p.name for p in out.iterdir()) == ["transforms.json"]
    assert (out / "transforms.json").read_text() == "the user's own cameras"


def test_export_refuses_a_foreign_image_before_writing(run, capsys):
    out = run.parent / "out"
    (out / "images").mkdir(parents=True)
    (out / "images" / "val_000.png").write_bytes(b"the user's picture")
    rc = main(["export", str(run), "cameras", "--out", str(out / "transforms.json")])
    _one_line(capsys, rc, "val_000.png", "not written by warpnerf")
    assert sorted(p.name for p in (out / "images").iterdir()) == ["val_000.png"]
    assert not (out / "transforms.json").exists()


# ------------------------------------------------------------ 8: manifests at scale


def _timed(seconds: float):
    """Fails (instead of running for minutes) past ``seconds``."""

    def alarm(signum, frame):
        raise TimeoutError(f"took more than {seconds} s")

    signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)


def test_thirty_thousand_outputs_stay_owned(tmp_path):
    """30k outputs in one folder (a 10k-frame render): recording each costs the same, and none is
    disowned once the manifest is large (the first and the last are still warpnerf's)."""
    n = 30000
    names = [f"rgb_{i:05d}.png" for i in range(n)]
    for name in names:
        (tmp_path / name).write_bytes(b"frame")
    old = signal.getsignal(signal.SIGALRM)
    try:
        _timed(60.0)
        t0 = time.perf_counter()
        for name in names:
            outputs.record(tmp_path / name)
        t_record = time.perf_counter() - t0
        t0 = time.perf_counter()
        outputs.check_foreign([tmp_path / name for name in names])  # all warpnerf's: no error
        t_check = time.perf_counter() - t0
        owned = outputs.owned_files(tmp_path)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, old)
    assert names[0] in owned and names[-1] in owned and len(owned) == n
    assert outputs.remove_own(tmp_path, names[:2]) == names[:2]
    print(f"30k records: {t_record:.2f} s, check of 30k: {t_check:.2f} s")
    assert t_record < 20 and t_check < 20


def test_rewrites_keep_the_manifest_small(tmp_path, monkeypatch):
    """An append-only manifest is compacted as it grows: a file rewritten 1000 times (a
    checkpoint) leaves a manifest of a few records, not 1000 (40 kB)."""
    monkeypatch.setattr(safe_writes, "_COMPACT_MIN_BYTES", 4096)
    p = tmp_path / "checkpoint.pt"
    for i in range(1000):
        p.write_bytes(b"x" * (i % 7))
        outputs.record(p)
    assert (tmp_path / outputs.MANIFEST).stat().st_size < 3 * 4096
    assert outputs.owned_files(tmp_path) == {"checkpoint.pt"}


def test_old_manifests_still_read(tmp_path):
    """A manifest of an earlier version (one JSON object) keeps its files warpnerf's, also after
    new records are appended to it."""
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    a.write_bytes(b"a")
    b.write_bytes(b"b")
    st = a.stat()
    (tmp_path / outputs.MANIFEST).write_text(json.dumps({"a.png": [st.st_size, st.st_mtime_ns]}))
    assert outputs.owned_files(tmp_path) == {"a.png"}
    outputs.record(b)
    assert outputs.owned_files(tmp_path) == {"a.png", "b.png"}


def test_oversized_manifest_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setattr(safe_writes, "_MANIFEST_MAX_BYTES", 1000)
    (tmp_path / outputs.MANIFEST).write_bytes(b"\n" * 1001)
    with pytest.raises(UserError, match="larger than"):
        outputs.owned_files(tmp_path)


def test_manifest_lines_are_untrusted(tmp_path):
    """Malformed records, names with separators, deep nesting: ignored, never an error."""
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    (tmp_path / "sub").mkdir()
    st = victim.stat()
    lines = [json.dumps(["../victim.txt", st.st_size, st.st_mtime_ns]), "[" * 100000, "not json",
             json.dumps(["x", "1", 2]), json.dumps({"..": [1, 2]})]  # fmt: skip
    (tmp_path / "sub" / outputs.MANIFEST).write_text("\n".join(lines) + "\n")
    assert outputs.owned_files(tmp_path / "sub") == set()
    assert outputs.remove_own(tmp_path / "sub", ["../victim.txt"]) == []
    assert victim.read_text() == "keep"


# ------------------------------------------------------------ 9: data-parallel faults


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("dead", [1, 0])
@pytest.mark.slow
def test_dead_rank_stops_the_other_with_one_line(tmp_path, dead):
    """Two gloo ranks started as torchrun would; one is killed mid-training (SIGKILL): the other
    exits non-zero within seconds with one line saying so, no traceback."""
    out = tmp_path / "dp"
    port = _port()
    argv = [sys.executable, "-m", "warpnerf.cli", "train", "nerf", "--out", str(out), "--iters",
            "100000", "--ckpt-every", "2", *NEW]  # fmt: skip
    procs = []
    for rank in (0, 1):
        env = dict(os.environ, RANK=str(rank), LOCAL_RANK=str(rank), WORLD_SIZE="2",
                   LOCAL_WORLD_SIZE="2", MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port),
                   WARPNERF_DIST_TIMEOUT="120", OMP_NUM_THREADS="1")  # fmt: skip
        procs.append(subprocess.Popen(argv, env=env, stdout=subprocess.PIPE,
                                      stderr=subprocess.PIPE, text=True))  # fmt: skip
    try:
        t0 = time.time()
        while not (out / "history.json").exists():  # both ranks are training
            assert time.time() - t0 < 240 and all(p.poll() is None for p in procs), [
                p.communicate() for p in procs if p.poll() is not None
            ]
            time.sleep(0.2)
        procs[dead].kill()
        procs[dead].wait()
        survivor = procs[1 - dead]
        t_kill = time.time()
        _, err = survivor.communicate(timeout=120)
        waited = time.time() - t_kill
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    lines = [x for x in err.splitlines() if x.strip() and not x.startswith("Warp ")]
    assert survivor.returncode not in (0, None), err
    assert "Traceback" not in err and len(lines) == 1, err
    assert "rank" in lines[0], lines[0]
    assert waited < 60, waited
