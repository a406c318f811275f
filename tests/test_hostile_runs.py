"""Security and reliability, round 2: hostile run folders, concurrent runs, failing encoders,
foreign files, divergence, OS faults and impossible sizes.

Each class of the issue has at least one test here that failed on the code before the fix:
  1  a crafted checkpoint.pt (pickle with __reduce__) never runs: every command that reads a run
  3  two trainings into one --out: the second is refused (run-folder lock; stale locks taken over)
  4  a failing video encoder leaves no .mp4 and the command exits 2
  5  eval --out DIR keeps files it did not write (and refuses to replace them)
  7  a diverging training stops at the first non-finite step, exit 3, strict JSON, good checkpoint
  8  OS errors (ENAMETOOLONG, ENOSPC, EROFS, EACCES, ENOTDIR) and impossible sizes: one line, exit 2
The other classes (2 packed indices, 6 cameras, 9 stored inputs) are in test_op_bounds.py,
test_loader_fuzz.py and test_config_validation.py.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

import warpnerf.mesh
from warpnerf import outputs
from warpnerf.cli import main
from warpnerf.errors import Diverged, UserError, describe_failure

from .test_datasets import make_blender

TN = ["--iters", "2", "--batch", "32", "--samples", "4", "--layers", "2", "--width", "16"]
TN += ["--pos-freqs", "1", "--dir-freqs", "1", "--val-images", "0", "--quiet"]
SDF = ["--batch", "32", "--layers", "2", "--width", "16", "--pos-freqs", "1", "--resolution", "8"]
BOX = ["--batch", "16", "--samples", "4", "--frames", "0", "--quiet"]


def _no_screenshot(*args, **kwargs):
    raise ImportError("screenshots are skipped in these tests")


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Tiny finished runs of every kind (NeRF, VolSDF, neural SDF, box) and their data."""
    w = tmp_path_factory.mktemp("hostile")
    make_blender(w / "bl", n=2)
    make_blender(w / "bl", n=2, split="val")
    import numpy as np

    g = np.random.default_rng(0).normal(size=(200, 3))
    np.savez(w / "ok.npz", points=g / np.linalg.norm(g, axis=1, keepdims=True))
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(w)
        mp.setattr(warpnerf.mesh, "screenshot", _no_screenshot)
        bl = str(w / "bl")  # the runs' config.json name their data by absolute path
        assert main(["train", "nerf", "--data", bl, "--out", "nerf", *TN]) == 0
        assert main(["train", "volsdf", "--data", bl, "--out", "volsdf", *TN]) == 0
        assert main(["train", "sdf", "--points", "ok.npz", "--out", "sdf", "--iters", "2", *SDF,
                     "--quiet"]) == 0  # fmt: skip
        assert main(["train", "box", "--data", bl, "--out", "box", "--iters", "1", *BOX]) == 0
    return w


def _copy(runs: Path, kind: str, dst: Path) -> Path:
    shutil.copytree(runs / kind, dst / kind)
    shutil.copytree(runs / "bl", dst / "bl", dirs_exist_ok=True)
    return dst / kind


def _one_line(capsys, rc, status=2, *needles) -> str:
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.strip()]
    assert rc == status, (rc, err)
    assert "Traceback" not in err
    assert len(lines) == 1, err
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def _strict_json(path: Path):
    def no_constants(name):
        raise ValueError(f"{path}: non-standard JSON constant {name}")

    return json.loads(path.read_text(), parse_constant=no_constants)


# ------------------------------------------------------------ 1: crafted checkpoints never run


class _Payload:
    """Unpickling this runs ``exec(code)``: what a crafted checkpoint.pt would do."""

    def __init__(self, code: str):
        self.code = code

    def __reduce__(self):
        return (exec, (self.code,))


def _plant(run: Path, marker: Path, legacy: bool = False) -> None:
    code = f"open({str(marker)!r}, 'w').write('pwned')"
    state = {"step": 1, "fields": {}, "model": {}, "volume": {}, "evil": _Payload(code)}
    torch.save(state, run / "checkpoint.pt", _use_new_zipfile_serialization=not legacy)


# (run kind, argv after the run folder is substituted for RUN)
READERS = [
    ("nerf", ["eval", "RUN", "--max-images", "1"]),
    ("nerf", ["render", "RUN", "--frames", "1", "--size", "8x8"]),
    ("nerf", ["mesh", "RUN", "--out", "m.ply", "--resolution", "8", "--no-screenshot"]),
    ("nerf", ["train", "nerf", "--out", "RUN", "--resume", "--iters", "5", "--quiet"]),
    ("volsdf", ["train", "volsdf", "--out", "RUN", "--resume", "--iters", "5", "--quiet"]),
    ("volsdf", ["eval", "RUN", "--max-images", "1"]),
    ("volsdf", ["mesh", "RUN", "--out", "m.ply", "--resolution", "8", "--no-screenshot"]),
    ("sdf", ["train", "sdf", "--out", "RUN", "--resume", "--iters", "5", "--quiet"]),
    ("sdf", ["mesh", "RUN", "--out", "m.ply", "--resolution", "8", "--no-screenshot"]),
    ("box", ["train", "box", "--out", "RUN", "--resume", "--iters", "5", "--quiet"]),
]


@pytest.mark.parametrize("kind,argv", READERS, ids=lambda x: x if isinstance(x, str) else x[0])
def test_crafted_checkpoint_never_runs_code(runs, tmp_path, monkeypatch, capsys, kind, argv):
    run = _copy(runs, kind, tmp_path)
    marker = tmp_path / "PWNED"
    _plant(run, marker)
    monkeypatch.chdir(tmp_path)
    rc = main([str(run) if a == "RUN" else a for a in argv])
    assert not marker.exists(), "the crafted checkpoint ran code"
    _one_line(capsys, rc, 2, str(run / "checkpoint.pt"), "refused")


def test_crafted_legacy_pickle_never_runs_code(runs, tmp_path, capsys):
    """The pre-zip torch format (a bare pickle) goes through the same restricted unpickler."""
    run = _copy(runs, "nerf", tmp_path)
    marker = tmp_path / "PWNED"
    _plant(run, marker, legacy=True)
    rc = main(["eval", str(run), "--max-images", "1"])
    assert not marker.exists()
    _one_line(capsys, rc, 2, "checkpoint.pt")


def test_own_checkpoints_load_without_pickle(runs):
    """What warpnerf writes is tensors and plain data: the restricted loader takes it as is."""
    for kind in ("nerf", "volsdf", "sdf", "box"):
        ckpt = outputs.load_checkpoint(runs / kind / "checkpoint.pt", "cpu", ("step", "history"))
        assert ckpt["step"] >= 1


# ------------------------------------------------------------ 3: one process per run folder

_HOLD = """
import sys, time
from warpnerf.outputs import output_lock
with output_lock(sys.argv[1]):
    print("locked", flush=True)
    time.sleep(120)
"""


def _holder(folder: Path) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", _HOLD, str(folder)], stdout=subprocess.PIPE,
                         text=True)  # fmt: skip
    assert p.stdout.readline().strip() == "locked"
    return p


def test_second_writer_is_refused_and_a_dead_holders_lock_is_stale(runs, tmp_path, capsys):
    run = _copy(runs, "nerf", tmp_path)
    before = (run / "history.json").read_text()
    p = _holder(run)
    try:
        rc = main(["train", "nerf", "--out", str(run), "--resume", "--iters", "4", "--quiet"])
        line = _one_line(capsys, rc, 2, str(run), f"pid {p.pid}", "in use")
        assert "choose another" in line
        rc = main(["eval", str(run), "--max-images", "1", "--out", str(run)])
        _one_line(capsys, rc, 2, "in use")
        assert (run / "history.json").read_text() == before
    finally:
        p.send_signal(signal.SIGKILL)  # dies holding the lock: the file stays, the lock goes
        p.wait()
    assert (run / outputs.LOCK).exists()
    assert main(["train", "nerf", "--out", str(run), "--resume", "--iters", "3", "--quiet"]) == 0
    assert _strict_json(run / "history.json")["step"][-1] == 3


@pytest.mark.slow
def test_two_trainings_into_one_out_at_once(runs, tmp_path):
    """Two real processes race for one --out: one trains, the other exits 2 naming the folder;
    the folder holds one run's config, checkpoint and history."""
    out = tmp_path / "race"
    args = [sys.executable, "-m", "warpnerf.cli", "train", "nerf", "--data", str(runs / "bl"),
            "--out", str(out), *TN[:1], "30", *TN[2:]]  # fmt: skip
    procs = [subprocess.Popen([*args, "--seed", str(s)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for s in (1, 2)]  # fmt: skip
    res = [(p.wait(timeout=300), p.stderr.read()) for p in procs]
    codes = sorted(r[0] for r in res)
    assert codes == [0, 2], res
    loser = next(err for rc, err in res if rc == 2)
    assert "Traceback" not in loser and str(out) in loser
    winner_seed = 1 if res[0][0] == 0 else 2
    cfg = _strict_json(out / "config.json")
    ckpt = outputs.load_checkpoint(out / "checkpoint.pt", "cpu", ("config",))
    assert cfg["seed"] == ckpt["config"]["seed"] == winner_seed
    assert _strict_json(out / "history.json")["step"][-1] == 30


def test_output_lock_releases_on_error(tmp_path):
    with pytest.raises(RuntimeError), outputs.output_lock(tmp_path / "a"):
        raise RuntimeError("boom")
    p = _holder(tmp_path / "a")  # another process can take it now
    p.kill()
    p.wait()


# ------------------------------------------------------------ 4: failing video encoders

_BROKEN_FFMPEG = """#!/bin/sh
# writes a truncated file where the output should go, then fails like a full disk would
for a; do last=$a; done
printf 'junk' > "$last"
cat > /dev/null
echo "av_interleaved_write_frame(): No space left on device" >&2
exit 1
"""


@pytest.fixture
def broken_ffmpeg(tmp_path, monkeypatch):
    exe = tmp_path / "ffmpeg"
    exe.write_text(_BROKEN_FFMPEG)
    exe.chmod(0o755)
    import imageio_ffmpeg

    monkeypatch.setattr(imageio_ffmpeg, "get_ffmpeg_exe", lambda: str(exe))
    return exe


def test_failing_encoder_leaves_no_video(tmp_path, broken_ffmpeg):
    import numpy as np

    frames = [np.zeros((8, 8, 3), np.uint8)] * 3
    with pytest.raises(UserError, match="No space left on device"):
        outputs.write_video(tmp_path / "v" / "v.mp4", frames)
    assert not [p for p in (tmp_path / "v").iterdir() if p.suffix == ".mp4"]


def test_render_with_failing_encoder_exits_2(runs, tmp_path, capsys, broken_ffmpeg):
    run = _copy(runs, "nerf", tmp_path)
    rc = main(["render", str(run), "--frames", "2", "--size", "8x8"])
    _one_line(capsys, rc, 2, "rgb.mp4", "ffmpeg")
    assert not list((run / "render_spiral").glob("*.mp4"))


def test_good_encoder_writes_a_readable_mp4(tmp_path):
    import imageio.v3 as iio
    import numpy as np

    frames = [np.full((10, 14, 3), 40 * i, np.uint8) for i in range(4)]
    outputs.write_video(tmp_path / "v.mp4", frames)
    assert iio.imread(tmp_path / "v.mp4", index=None).shape == (4, 10, 14, 3)


# ------------------------------------------------------------ 5: foreign files are kept


def test_eval_keeps_files_it_did_not_write(runs, tmp_path, capsys):
    run = _copy(runs, "nerf", tmp_path)
    out = tmp_path / "mine"
    out.mkdir()
    (out / "val_005.png").write_bytes(b"the user's own picture")
    (out / "notes.txt").write_text("the user's notes")
    assert main(["eval", str(run), "--max-images", "1", "--out", str(out)]) == 0
    assert (out / "val_005.png").read_bytes() == b"the user's own picture"
    assert (out / "notes.txt").read_text() == "the user's notes"
    assert (out / "val_000.png").exists()
    # a second, smaller evaluation removes only the stale images warpnerf wrote itself
    assert main(["eval", str(run), "--max-images", "2", "--out", str(out)]) == 0
    assert main(["eval", str(run), "--max-images", "1", "--out", str(out)]) == 0
    assert not (out / "val_001.png").exists() and (out / "val_005.png").exists()
    capsys.readouterr()
    (out / "metrics.json").unlink()
    (out / "metrics.json").write_text("the user's metrics")  # a file of the same name: refused
    rc = main(["eval", str(run), "--max-images", "1", "--out", str(out)])
    _one_line(capsys, rc, 2, "metrics.json", "not written by warpnerf")
    assert (out / "metrics.json").read_text() == "the user's metrics"


def test_mesh_without_screenshot_keeps_a_foreign_png(runs, tmp_path, capsys):
    run = _copy(runs, "sdf", tmp_path)
    (tmp_path / "m.png").write_bytes(b"a picture")
    args = ["mesh", str(run), "--out", str(tmp_path / "m.ply"), "--resolution", "8"]
    assert main([*args, "--no-screenshot"]) == 0
    assert (tmp_path / "m.png").read_bytes() == b"a picture"
    capsys.readouterr()
    _one_line(capsys, main(args), 2, "m.png", "not written by warpnerf")


def test_new_box_fit_keeps_foreign_files(runs, tmp_path, capsys):
    out = tmp_path / "fit"
    out.mkdir()
    (out / "result.json").write_text("someone else's result")
    rc = main(["train", "box", "--data", str(runs / "bl"), "--out", str(out), "--iters", "1",
               *BOX])  # fmt: skip
    _one_line(capsys, rc, 2, "result.json", "not written by warpnerf")
    assert (out / "result.json").read_text() == "someone else's result"


def test_manifest_cannot_widen_deletion(tmp_path):
    """The manifest is untrusted: names with separators or '..' are ignored."""
    (tmp_path / "sub").mkdir()
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    stamp = [victim.stat().st_size, victim.stat().st_mtime_ns]
    names = {"../victim.txt": stamp, "/etc/passwd": stamp, "..": stamp}
    (tmp_path / "sub" / outputs.MANIFEST).write_text(json.dumps(names))
    assert outputs.owned_files(tmp_path / "sub") == set()
    assert outputs.remove_own(tmp_path / "sub", ["../victim.txt"]) == []
    assert victim.read_text() == "keep"
    (tmp_path / "sub" / outputs.MANIFEST).write_text("[" * 100000)  # nested too deeply: empty
    assert outputs.owned_files(tmp_path / "sub") == set()


# ------------------------------------------------------------ 7: divergence


def test_diverging_nerf_stops_at_the_first_nonfinite_step(runs, tmp_path, capsys):
    out = tmp_path / "div"
    args = ["train", "nerf", "--data", str(runs / "bl"), "--out", str(out), *TN[:1], "40",
            *TN[2:], "--ckpt-every", "1", "--lr", "1e30"]  # fmt: skip
    rc = main(args)
    line = _one_line(capsys, rc, 3, "diverged at step", "--lr")
    step = int(line.split("diverged at step ")[1].split(":")[0])
    assert step < 40
    hist = _strict_json(out / "history.json")  # valid JSON: no NaN token
    assert hist["step"][-1] == step - 1
    assert all(v is not None for v in hist["loss"])
    ckpt = outputs.load_checkpoint(out / "checkpoint.pt", "cpu", ("fields",))
    assert ckpt["step"] == step - 1
    for state in ckpt["fields"].values():
        for t in (state or {}).values():
            assert torch.isfinite(t).all()


def test_diverging_sdf_and_box_stop(runs, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(warpnerf.mesh, "screenshot", _no_screenshot)
    rc = main(["train", "sdf", "--points", str(runs / "ok.npz"), "--out", str(tmp_path / "s"),
               "--iters", "30", *SDF, "--lr", "1e30", "--quiet"])  # fmt: skip
    _one_line(capsys, rc, 3, "diverged at step")
    from warpnerf.train import box_fit

    real = box_fit.render_rays

    def poisoned(*a, **k):  # a NaN colour at the third step
        out = real(*a, **k)
        if poisoned.calls == 2:
            out["rgb"] = out["rgb"] * float("nan")
        poisoned.calls += 1
        return out

    poisoned.calls = 0
    monkeypatch.setattr(box_fit, "render_rays", poisoned)
    rc = main(["train", "box", "--data", str(runs / "bl"), "--out", str(tmp_path / "b"),
               "--iters", "5", "--ckpt-every", "1", *BOX])  # fmt: skip
    _one_line(capsys, rc, 3, "diverged at step 3")
    assert _strict_json(tmp_path / "b" / "history.json")["step"] == [1, 2]


def test_check_finite_names_gradients():
    from warpnerf.train.divergence import check_finite

    p = torch.nn.Parameter(torch.ones(3))
    p.grad = torch.tensor([0.0, float("inf"), 1.0])
    with pytest.raises(Diverged, match="step 7: a gradient"):
        check_finite(7, torch.tensor(1.0), [p], "run", 0.1)
    p.grad = torch.tensor([1e30, -1e30, 0.0])  # huge but finite: fine
    check_finite(7, torch.tensor(1.0), [p], "run", 0.1)


def test_json_writers_are_strict(tmp_path):
    outputs.write_json(tmp_path / "a.json", {"psnr": float("inf"), "x": [1.0, float("nan")]})
    assert _strict_json(tmp_path / "a.json") == {"psnr": None, "x": [1.0, None]}
    assert outputs.json_dumps({"a": float("-inf")}) == '{"a": null}'


# ------------------------------------------------------------ 8: OS faults and impossible sizes


def _raise_os(err: int):
    def fail(*a, **k):  # names the first path-like argument, as the OS would
        path = next((x for x in a if isinstance(x, (str, os.PathLike))), "x")
        raise OSError(err, os.strerror(err), os.fspath(path))

    return fail


@pytest.mark.parametrize(
    "err,where",
    [(errno.ENOSPC, "save"), (errno.EROFS, "replace"), (errno.EACCES, "mkstemp"),
     (errno.EDQUOT, "save")],
)  # fmt: skip
def test_train_os_errors_are_one_line(runs, tmp_path, monkeypatch, capsys, err, where):
    import tempfile

    target = {"save": (torch, "save"), "replace": (os, "replace"),
              "mkstemp": (tempfile, "mkstemp")}[where]  # fmt: skip
    monkeypatch.setattr(*target, _raise_os(err))
    rc = main(["train", "nerf", "--data", str(runs / "bl"), "--out", str(tmp_path / "r"), *TN])
    line = _one_line(capsys, rc, 2, errno.errorcode[err])
    assert "warpnerf train: error:" in line
    assert not [
        p
        for p in (tmp_path / "r").rglob(".*")
        if p.suffix in (".pt", ".json") and p.name != outputs.MANIFEST
    ]  # fmt: skip  (no temporary files left)


def test_name_too_long_and_not_a_folder(runs, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc = main(["train", "nerf", "--data", str(runs / "bl"), "--out", "x" * 300, *TN])
    _one_line(capsys, rc, 2, "ENAMETOOLONG", "too long")
    run = _copy(runs, "nerf", tmp_path)
    rc = main(["eval", str(run), "--max-images", "1", "--out", "y" * 300])
    _one_line(capsys, rc, 2, "ENAMETOOLONG")
    rc = main(["mesh", str(run), "--out", "z" * 300 + ".ply", "--resolution", "8"])
    _one_line(capsys, rc, 2, "ENAMETOOLONG")


@pytest.mark.slow
def test_eval_render_mesh_bench_disk_full(runs, tmp_path, monkeypatch, capsys):
    import imageio.v3 as iio

    run = _copy(runs, "nerf", tmp_path)
    sdf = _copy(runs, "sdf", tmp_path)
    monkeypatch.setattr(iio, "imwrite", _raise_os(errno.ENOSPC))
    _one_line(capsys, main(["eval", str(run), "--max-images", "1"]), 2, "ENOSPC")
    rc = main(["render", str(run), "--frames", "1", "--size", "8x8"])
    _one_line(capsys, rc, 2, "no space left")
    monkeypatch.setattr(os, "replace", _raise_os(errno.EROFS))
    rc = main(["mesh", str(sdf), "--out", str(tmp_path / "m.ply"), "--resolution", "8",
               "--no-screenshot"])  # fmt: skip
    _one_line(capsys, rc, 2, "read-only", "EROFS")
    rc = main(["bench", "composite", "--quick", "--json", str(tmp_path / "b.json")])
    _one_line(capsys, rc, 2, "EROFS")
    assert not (tmp_path / "m.ply").exists() and not (tmp_path / "b.json").exists()


def test_impossible_sizes_are_refused_before_allocating(runs, tmp_path, capsys):
    run = _copy(runs, "nerf", tmp_path)
    t0 = time.perf_counter()
    # (a size past the videos' limits is refused earlier: test_untrusted_round4_limits.py)
    rc = main(["render", str(run), "--frames", "100000", "--size", "8192x8192"])
    _one_line(capsys, rc, 2, "100000 frames of 8192x8192", "more than")
    assert time.perf_counter() - t0 < 30
    assert not (run / "render_spiral").exists()


def test_allocator_failures_are_described():
    e = RuntimeError(
        "[enforce fail at alloc_cpu.cpp:117] data. DefaultCPUAllocator: can't "
        "allocate memory: you tried to allocate 4000000000000 bytes. Error code 12"
    )
    assert "tried to allocate 3.6 TiB" in describe_failure(e)
    cuda = RuntimeError("CUDA out of memory. Tried to allocate 20.00 GiB (GPU 0; 79.1 GiB)")
    assert "out of memory" in describe_failure(cuda)
    assert "20.00 GiB" in describe_failure(cuda)
    assert describe_failure(MemoryError()).startswith("out of memory")
    assert describe_failure(RuntimeError("a bug")) is None
    oserr = OSError(errno.ENOTDIR, "Not a directory", "a/b")
    assert describe_failure(oserr) == "a/b: a part of the path is a file, not a folder (ENOTDIR)"


def test_seeds_beyond_31_bits_are_refused(tmp_path, capsys):
    for seed in ("100000000000000000000000", "-1", str(2**31)):
        with pytest.raises(SystemExit) as e:
            main(
                ["train", "nerf", "--data", "builtin", "--out", str(tmp_path / "r"), "--seed", seed]
            )
        assert e.value.code == 2
        assert "--seed" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


# ------------------------------------------------- 9: a run's config.json is validated on load


def _tamper(run: Path, **fields) -> None:
    cfg = json.loads((run / "config.json").read_text())
    for k, v in fields.items():
        if v is _DROP:
            cfg.pop(k, None)
        else:
            cfg[k] = v
    text = json.dumps(cfg).replace('"__NAN__"', "NaN")
    (run / "config.json").write_text(text)


_DROP = object()
TAMPERED = [  # (kind, fields, words in the message)
    ("nerf", {"iters": "10"}, ["'iters'", "an integer"]),
    ("nerf", {"lr": True}, ["'lr'"]),
    ("nerf", {"near": 5.0, "far": 1.0}, ["near"]),
    ("nerf", {"colour": 1}, ["unknown field", "colour"]),
    ("nerf", {"seed": 2**70}, ["'seed'"]),
    ("nerf", {"lr": "__NAN__"}, ["'lr'"]),
    ("nerf", {"batch": [[[[1]]]]}, ["'batch'"]),
    ("volsdf", {"beta_min": -1.0}, ["beta"]),
    ("sdf", {"width": 1.5}, ["'width'"]),
    ("sdf", {"pos_freqs": 1000}, ["pos_freqs"]),
    ("box", {"near": 4.0, "far": 1.0}, ["near"]),
    ("box", {"batch": None}, ["'batch'"]),
]
COMMANDS = {
    "nerf": ["eval", "RUN", "--max-images", "1"],
    "volsdf": ["mesh", "RUN", "--out", "m.ply", "--resolution", "8", "--no-screenshot"],
    "sdf": ["mesh", "RUN", "--out", "m.ply", "--resolution", "8", "--no-screenshot"],
    "box": ["train", "box", "--out", "RUN", "--resume", "--iters", "5", "--quiet"],
}


@pytest.mark.parametrize("kind,fields,words", TAMPERED, ids=lambda x: str(x)[:30])
def test_tampered_config_is_one_line_naming_the_field(runs, tmp_path, capsys, kind, fields,
                                                      words):  # fmt: skip
    run = _copy(runs, kind, tmp_path)
    _tamper(run, **fields)
    rc = main([str(run) if a == "RUN" else a for a in COMMANDS[kind]])
    _one_line(capsys, rc, 2, "config.json", *words)


def test_tampered_config_refused_by_every_reader(runs, tmp_path, capsys):
    readers = (
        ["eval", "RUN", "--max-images", "1"],
        ["render", "RUN", "--frames", "1"],
        ["train", "nerf", "--out", "RUN", "--resume", "--iters", "9", "--quiet"],
    )
    for argv in readers:
        run = _copy(runs, "nerf", tmp_path / argv[0])
        _tamper(run, n_samples="64")
        rc = main([str(run) if a == "RUN" else a for a in argv])
        _one_line(capsys, rc, 2, "config.json", "n_samples")


def test_deeply_nested_config_is_not_a_recursion_error(runs, tmp_path, capsys):
    run = _copy(runs, "sdf", tmp_path)
    (run / "config.json").write_text("[" * 200_000 + "]" * 200_000)
    rc = main(["mesh", str(run), "--out", "m.ply", "--no-screenshot"])
    _one_line(capsys, rc, 2, "config.json", "nested too deeply")
