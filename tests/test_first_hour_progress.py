"""Issue 43 items 10 and 11: progress on the commands that take a while (render, eval, mesh,
export), small frames rendered together (the time sink of `render` on a CPU), and `train
--viewer` serving the finished run until Ctrl-C (not when nobody can press it)."""

from __future__ import annotations

import io
import os
import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from warpnerf.cli.parser import main

ROOT = Path(__file__).resolve().parents[1]
# a tiny hash_sdf run (tests/test_first_hour_resume.py's settings)
VOLSDF = ["--data", "builtin", "--field", "hash_sdf", "--hash-levels", "3", "--hash-log2-size",
          "8", "--hash-max-res", "16", "--grid-res", "8", "--builtin-size", "16", "--batch", "64",
          "--val-images", "0", "--quiet", "--no-tensorboard"]  # fmt: skip


@pytest.fixture(scope="module")
def sdf_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("progress") / "r"
    assert main(["train", "volsdf", *VOLSDF, "--iters", "4", "--out", str(run)]) == 0
    return run


# ---- item 10: progress -----------------------------------------------------------------------


def test_progress_is_a_bar_on_a_terminal_and_lines_otherwise():
    from warpnerf.train.progress import Progress

    s = io.StringIO()
    with Progress(3, "render", unit="frame", stream=s, every=0) as bar:
        for _ in range(3):
            bar.update()
    lines = s.getvalue().splitlines()
    assert lines and all(line.startswith("render:") for line in lines)
    assert "1/3" in lines[0] and "3/3" in lines[-1]  # the last line: where it ended
    assert "\r" not in s.getvalue()  # (no redraws in a log)

    s = io.StringIO()  # a long wait between lines: nothing until the first is due
    with Progress(3, "render", stream=s, every=1e9) as bar:
        bar.update(3)
    assert s.getvalue() == ""

    s = io.StringIO()  # a terminal: tqdm's one updating line
    with Progress(3, "render", unit="frame", stream=s, terminal=True) as bar:
        bar.update(3)
    assert "\r" in s.getvalue() and "3/3" in s.getvalue()

    s = io.StringIO()  # --quiet
    with Progress(3, "render", stream=s, every=0, terminal=False, enabled=False) as bar:
        bar.update(3)
    assert s.getvalue() == ""
    counted = Progress(10, "mesh", stream=s, every=1e9).counting(lambda x: len(x) * 2)
    assert counted([1, 2, 3]) == 6


def _frames(folder: Path, kinds=("rgb", "depth", "geometry")) -> dict:
    from PIL import Image

    return {p.name: np.asarray(Image.open(p)) for k in kinds
            for p in sorted(folder.glob(f"{k}_*.png"))}  # fmt: skip


def test_render_renders_small_frames_together(sdf_run, monkeypatch):
    """The time sink of `render` on a CPU (issue 43 item 10): 32x32 frames rendered one by one,
    each step of the pipeline (the SDF view's ~60 sphere-tracing steps a frame above all) a
    batch of 1024 rays. Frames that fit one rendering chunk now render together: far fewer
    field calls, and the same PNGs as frame by frame."""
    from warpnerf.fields.hash_sdf import HashSDFField
    from warpnerf.train import nerf_eval

    assert nerf_eval.frames_per_batch(32, 32, 40, 8192) == 8
    assert nerf_eval.frames_per_batch(32, 32, 3, 8192) == 3
    assert nerf_eval.frames_per_batch(800, 800, 40, 8192) == 1
    assert nerf_eval.frames_per_batch(32, 32, 40, None) == 1

    calls = []
    geometry = HashSDFField._geometry

    def counted(self, x):
        calls.append(len(x))
        return geometry(self, x)

    monkeypatch.setattr(HashSDFField, "_geometry", counted)
    res = nerf_eval.render_run(sdf_run, frames=6, size=(16, 16))
    together, n_together = _frames(Path(res["out"])), len(calls)
    assert len(together) == 18 and res["frames"] == 6

    calls.clear()
    monkeypatch.setattr(nerf_eval, "frames_per_batch", lambda *a: 1)  # the old way
    nerf_eval.render_run(sdf_run, frames=6, size=(16, 16))
    one_by_one, n_one_by_one = _frames(Path(res["out"])), len(calls)
    assert together.keys() == one_by_one.keys()
    for name, img in together.items():
        assert np.abs(img.astype(int) - one_by_one[name].astype(int)).max() <= 1, name
    assert n_together * 3 <= n_one_by_one, (n_together, n_one_by_one)


_LINE = re.compile(r"^(render|eval val|eval geometry: SDF grid|mesh: field on the grid|"
                   r"export pointcloud):\s+\d+%.*\d+(\.\d+)?[kM]?/\d+(\.\d+)?[kM]? \[")  # fmt: skip


def _progress_lines(err: str, what: str) -> list:
    return [ln for ln in err.splitlines() if _LINE.match(ln) and ln.startswith(what + ":")]


def test_run_tools_show_progress_unless_quiet(sdf_run, tmp_path, monkeypatch, capsys):
    """render, eval, mesh and export pointcloud: progress lines on stderr when it is no
    terminal (here: every update, PERIODIC_SECONDS 0), none with --quiet; stdout's last line
    stays the command's JSON."""
    import json

    import warpnerf.train.progress as progress

    monkeypatch.setattr(progress, "PERIODIC_SECONDS", 0.0)
    commands = {
        "render": ["render", str(sdf_run), "--frames", "3", "--size", "8x8"],
        "eval val": ["eval", str(sdf_run), "--max-images", "2", "--out", str(tmp_path / "e")],
        "mesh: field on the grid": ["mesh", str(sdf_run), "--out", str(tmp_path / "m.ply"),
                                    "--resolution", "80", "--no-screenshot"],
        "export pointcloud": ["export", str(sdf_run), "pointcloud", "--out",
                              str(tmp_path / "p.ply"), "--views", "2", "--stride", "4",
                              "--min-opacity", "0.05"],
    }  # fmt: skip
    for what, argv in commands.items():
        capsys.readouterr()
        assert main(argv) == 0, what
        out, err = capsys.readouterr()
        assert _progress_lines(err, what), (what, err[-2000:])
        json.loads(out.strip().splitlines()[-1])
        assert main([*argv, "--quiet"]) == 0, what
        out, err = capsys.readouterr()
        assert not _progress_lines(err, what), (what, err[-2000:])


# ---- item 11: the viewer after training ------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _box_scene(tmp_path) -> Path:
    from ._scene import write_box_folder

    write_box_folder(tmp_path / "scene", n_views=3, size=8, name="transforms_train.json")
    return tmp_path / "scene"


def _train_box(tmp_path, port: int, *flags, stdin=None) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    argv = [sys.executable, "-m", "warpnerf.cli", "train", "box", "--data",
            str(_box_scene(tmp_path)), "--out", str(tmp_path / "b"), "--iters", "2", "--frames",
            "0", "--quiet", "--samples", "8", "--no-tensorboard", "--viewer", "--viewer-port",
            str(port), *flags]  # fmt: skip
    return subprocess.Popen(argv, cwd=tmp_path, env=env, stdin=stdin, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip


def _lines(stream) -> queue.Queue:
    q = queue.Queue()

    def read():
        for line in stream:
            q.put(line)
        q.put(None)

    threading.Thread(target=read, daemon=True).start()
    return q


def _wait_for(q: queue.Queue, pattern: str, seconds: float, seen: list) -> str | None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            line = q.get(timeout=max(0.1, end - time.monotonic()))
        except queue.Empty:
            break
        if line is None:
            return None
        seen.append(line)
        if re.search(pattern, line):
            return line
    return None


def _port_open(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def test_viewer_keeps_serving_the_finished_run_until_ctrl_c(tmp_path):
    """`train ... --viewer` at a terminal (stdin a pty): once training ends the viewer keeps
    serving the finished run, says so, and Ctrl-C exits 0 with the port freed."""
    import pty

    port = _free_port()
    master, slave = pty.openpty()
    p = _train_box(tmp_path, port, stdin=slave)
    os.close(slave)
    err, seen = _lines(p.stderr), []
    _lines(p.stdout)
    try:
        line = _wait_for(err, r"training finished; the viewer keeps serving", 600, seen)
        assert line is not None, "".join(seen)[-3000:]
        url = re.search(r"(http://\S+)", line).group(1)
        assert str(tmp_path / "b") in line and "Ctrl-C to exit" in line
        time.sleep(1.0)
        assert p.poll() is None  # still serving
        with urllib.request.urlopen(url, timeout=30) as r:  # the page, with the token
            assert r.status == 200
        p.send_signal(signal.SIGINT)
        assert p.wait(timeout=60) == 0
        assert _wait_for(err, r"viewer: stopped after \d+ frames", 10, seen), "".join(seen)
        assert not _port_open(port)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        os.close(master)


def test_viewer_does_not_wait_when_stdin_is_no_terminal(tmp_path):
    """Scripts, pipes, CI: nobody can press Ctrl-C, so the command ends with the training and
    says how to keep the viewer (--viewer-wait)."""
    port = _free_port()
    p = _train_box(tmp_path, port, stdin=subprocess.DEVNULL)
    out, err = p.communicate(timeout=600)
    assert p.returncode == 0, err[-3000:]
    assert "the viewer closed (stdin is not a terminal; --viewer-wait keeps it serving" in err
    assert "keeps serving" not in err.replace("--viewer-wait keeps it serving", "")
    assert not _port_open(port)


def test_viewer_wait_flags(monkeypatch):
    """--viewer-wait / --no-viewer-wait decide; without them, whether stdin is a terminal; a
    --resume may carry them (watching changes nothing in a training)."""
    from warpnerf.cli.parser import build_parser
    from warpnerf.cli.train import _RESUME_FLAGS
    from warpnerf.cli.view import viewer_waits

    base = ["train", "box", "--data", "d", "--out", "o", "--viewer"]
    p = build_parser()
    assert p.parse_args(base).viewer_wait is None
    assert p.parse_args([*base, "--viewer-wait"]).viewer_wait is True
    assert p.parse_args([*base, "--no-viewer-wait"]).viewer_wait is False
    for model in ("nerf", "volsdf", "sdf"):
        assert p.parse_args(["train", model, "--out", "o", "--no-viewer-wait"]).viewer_wait is False

    class Stdin:
        def __init__(self, tty):
            self.tty = tty

        def isatty(self):
            return self.tty

    monkeypatch.setattr(sys, "stdin", Stdin(True))
    assert viewer_waits(p.parse_args(base)) is True
    assert viewer_waits(p.parse_args([*base, "--no-viewer-wait"])) is False
    monkeypatch.setattr(sys, "stdin", Stdin(False))
    assert viewer_waits(p.parse_args(base)) is False
    assert viewer_waits(p.parse_args([*base, "--viewer-wait"])) is True
    monkeypatch.setattr(sys, "stdin", None)
    assert viewer_waits(p.parse_args(base)) is False
    assert "viewer_wait" in _RESUME_FLAGS
