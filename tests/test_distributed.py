"""Data-parallel training (train/distributed.py) with two CPU processes on gloo, launched with
torchrun as a user would: the same loss curve as one process with the whole batch, files
written by rank 0 only, and a resume with another number of ranks. The one-process runs they
are compared with run in the test's process (``warpnerf.cli.main``, Warp's CPU launches and one
torch thread as in the ranks: the same arithmetic as a command, without a second import of
torch and Warp)."""

import json
import os
import socket
import subprocess
import sys

import pytest

from ._launches import cli_cpu_launches

ARGS = ("--data builtin --builtin-size 12 --batch 96 --samples 16 --near 1 --far 4 "
        "--val-every 3 --val-images 1 --ckpt-every 3 --lr 5e-3 --no-tensorboard "
        "--quiet").split()  # fmt: skip
MLP = "--layers 2 --width 16 --pos-freqs 3 --dir-freqs 1".split()  # (the MLP fields' flags)


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _train(out, extra, ranks: int, resume=False, iters=6, model="nerf"):
    cmd = ["train", model, "--out", str(out), "--iters", str(iters)]
    hashed = any(a in ("hash", "hash_sdf") for a in extra)  # (no MLP flags: refused there)
    base = ARGS + ([] if hashed else MLP)
    cmd = cmd + (["--resume"] if resume else base) + list(extra)  # (extra overrides ARGS)
    if ranks == 1:
        from warpnerf.cli import main

        with cli_cpu_launches():
            assert main(cmd) == 0
        return json.loads((out / "history.json").read_text())
    env = dict(os.environ, WARPNERF_DIST_TIMEOUT="120", OMP_NUM_THREADS="1")
    argv = [sys.executable, "-m", "torch.distributed.run", f"--nproc-per-node={ranks}",
            "--master-addr=127.0.0.1", f"--master-port={_port()}", "-m", "warpnerf.cli",
            *cmd]  # fmt: skip
    res = subprocess.run(argv, capture_output=True, text=True, timeout=600, env=env)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-4000:]
    _train.output = res.stdout + res.stderr  # (the last run's, for the tests that read it)
    return json.loads((out / "history.json").read_text())


HASH_GRID = ["--field", "hash", "--hash-levels", "4", "--hash-log2-size", "10",
             "--hash-max-res", "32", "--hidden", "16", "--grid-res", "8", "--grid-every", "2",
             "--grid-warmup", "2", "--march-step", "0.05", "--target-samples", "2000",
             "--aabb", "1.2"]  # fmt: skip


@pytest.mark.parametrize(
    "extra",
    [
        ["--fine-samples", "8", "--coarse-fine"],  # the NeRF MLP, stratified + importance
        HASH_GRID + ["--distortion-loss", "0.1"],  # its term: each rank's share, averaged
        HASH_GRID,  # grid + hash
    ],
    ids=["mlp", "hash_grid_distortion", "hash_grid"],
)
@pytest.mark.slow
def test_two_ranks_follow_one_process(tmp_path, extra):
    one = _train(tmp_path / "one", extra, 1)
    two = _train(tmp_path / "two", extra, 2)
    assert two["step"] == one["step"] == list(range(1, 7))
    for a, b in zip(one["loss"], two["loss"]):  # (the same draws; float32 sums in another order)
        assert abs(a - b) <= 1e-5 * abs(a), (one["loss"], two["loss"])
    if "batch" in one:  # the adaptive batch follows the global sample count
        assert one["batch"] == two["batch"]
        for a, b in zip(one["samples_per_ray"], two["samples_per_ray"]):
            assert abs(a - b) <= 1e-12 * abs(a), (one["samples_per_ray"], two["samples_per_ray"])
    for a, b in zip(one.get("distortion", []), two.get("distortion", [])):
        assert abs(a - b) <= 1e-5 * abs(a), (one["distortion"], two["distortion"])
    assert len(two.get("distortion", [])) == len(one.get("distortion", []))
    assert len(two["val_psnr"]) == len(one["val_psnr"]) == 2
    # rank 0 wrote the run; nothing else did (one manifest of outputs, no stray files)
    names = sorted(p.name for p in (tmp_path / "two").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "one").iterdir()), names


@pytest.mark.parametrize("field", ["hash_sdf", "volsdf"])
@pytest.mark.slow
def test_two_ranks_follow_one_process_with_sdf_fields(tmp_path, field):
    """VolSDF's eikonal term on the rendered samples is the mean over every rank's samples (each
    rank's count differs with the grid's marching), so two ranks still follow one process."""
    if field == "hash_sdf":
        extra = [a for a in HASH_GRID if a not in ("hash", "--target-samples", "2000")]
        extra = ["--field", "hash_sdf"] + extra[1:] + ["--c2f-every", "2"]
    else:
        extra = ["--field", "volsdf", "--fine-samples", "8", "--width", "32"]
    extra += ["--eikonal-weight", "1.0"]  # (a term large enough to tell the two means apart)
    one = _train(tmp_path / "one", extra, 1, model="volsdf")
    two = _train(tmp_path / "two", extra, 2, model="volsdf")
    assert two["step"] == one["step"] == list(range(1, 7))
    for a, b in zip(one["loss"], two["loss"]):
        assert abs(a - b) <= 1e-5 * abs(a), (one["loss"], two["loss"])


@pytest.mark.slow
def test_two_rank_run_resumes_on_one(tmp_path):
    """A checkpoint of two ranks holds nothing rank-specific: resumed by one process it goes on
    as the checkpoint of a one-process run does."""
    extra = ["--fine-samples", "8", "--coarse-fine"]
    _train(tmp_path / "a", extra, 1, iters=3)
    _train(tmp_path / "b", extra, 2, iters=3)
    a = _train(tmp_path / "a", [], 1, resume=True, iters=6)
    b = _train(tmp_path / "b", [], 1, resume=True, iters=6)
    assert a["step"] == b["step"] == list(range(1, 7))
    for x, y in zip(a["loss"], b["loss"]):
        assert abs(x - y) <= 1e-4 * abs(x), (a["loss"], b["loss"])


@pytest.mark.parametrize("command", ["train sdf", "train box", "eval", "render", "mesh"])
@pytest.mark.slow
def test_other_commands_refuse_torchrun(tmp_path, monkeypatch, capsys, command):
    """In-process with torchrun's WORLD_SIZE (the command reads it from its environment; the
    exit status through the interpreter: test_cli_demos.py, test_bad_input.py)."""
    from warpnerf.cli import main

    monkeypatch.setenv("WORLD_SIZE", "2")
    argv = [*command.split(), str(tmp_path / "r")]
    if command.startswith("train"):
        argv.insert(-1, "--out")
    elif command == "mesh":
        argv += ["--out", str(tmp_path / "m.ply")]
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2 and "runs in one process" in err, err
    assert "Traceback" not in err and not (tmp_path / "r").exists()


@pytest.mark.slow
def test_only_rank_zero_logs(tmp_path):
    """A two-rank run prints its log lines once (rank 0's), and leaves its process group
    (no NCCL/gloo warning of a group left open at exit)."""
    _train(tmp_path / "r", ["--max-seconds", "0.001"], 2, iters=6)
    out = _train.output
    assert out.count("stopping at step 1: --max-seconds") == 1, out[-3000:]
    assert "destroy_process_group() was not called" not in out, out[-3000:]


def test_ray_cap_is_per_rank():
    """The adaptive batch's ray cap is per rank: N ranks may draw N times the rays of one."""
    from types import SimpleNamespace

    from warpnerf.train.distributed import Dist
    from warpnerf.train.nerf import MAX_RAYS_PER_RANK, NeRFTask

    for world in (None, 2, 3):
        t = SimpleNamespace(cfg=SimpleNamespace(target_samples=1 << 30), batch=1 << 15,
                            dist=None if world is None else Dist(0, world))  # fmt: skip
        NeRFTask._next_batch(t, 1 << 15)  # one sample a ray: wants 2^30 rays
        assert t.batch == MAX_RAYS_PER_RANK * (world or 1)
        NeRFTask._next_batch(t, 1 << 52)  # far too many samples: the floor
        assert t.batch == 64
