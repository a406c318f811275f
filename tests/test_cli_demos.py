"""Smoke tests: every demo and CLI command runs as a subprocess with tiny settings; user errors
and refusals, a resume in the middle of a chain of commands and a demo's second run run
in-process (``warpnerf.cli.main``, a demo's ``main``, with the command's CPU launches: the
subprocess start-up, importing torch and warp, would dominate), end-to-end exit codes are checked
here and in test_bad_input.py. Independent subprocesses of one test run side by side (the suite's
torch uses one of the machine's cores)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ._scene import write_box_folder

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONUNBUFFERED="1")


def run(args, cwd, check=True):
    p = subprocess.run(
        [sys.executable, *args], cwd=cwd, capture_output=True, text=True, env=ENV, timeout=600
    )
    if check and p.returncode != 0:
        raise AssertionError(f"{args} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}")
    return p


def run_all(commands, cwd, check=True) -> list:
    """``run`` of each args in ``commands``, the processes side by side."""
    procs = [start(args, cwd) for args in commands]
    try:
        return [finish(p, check) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()


def start(args, cwd) -> subprocess.Popen:
    """``python *args`` started in folder ``cwd`` (``finish`` waits for it)."""
    return subprocess.Popen([sys.executable, *args], cwd=cwd, env=ENV, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip


def finish(p, check=True) -> subprocess.CompletedProcess:
    """Waits for the process ``p`` (of ``start``): ``run``'s result."""
    try:
        out, err = p.communicate(timeout=600)
    except subprocess.TimeoutExpired:
        p.kill()
        raise
    args = p.args[1:]
    if check and p.returncode != 0:
        raise AssertionError(f"{args} failed ({p.returncode}):\n{out}\n{err}")
    return subprocess.CompletedProcess(p.args, p.returncode, out, err)


def cli_ok(argv, cwd, monkeypatch, capsys) -> str:
    """stdout of ``warpnerf argv`` run in-process in folder ``cwd`` with Warp's CPU launches as
    the command makes them (exit status 0 asserted)."""
    from warpnerf.cli import main

    from ._launches import cli_cpu_launches

    monkeypatch.chdir(cwd)
    with cli_cpu_launches():
        rc = main(argv)
    out, err = capsys.readouterr()
    assert rc == 0, f"{argv} failed ({rc}):\n{out}\n{err}"
    return out


def demo_ok(demo, argv, cwd, monkeypatch, capsys) -> str:
    """stdout of demos/``demo``'s ``main(argv)`` run in-process in folder ``cwd`` with Warp's CPU
    launches as the command makes them (exit status 0 asserted)."""
    import importlib.util

    from ._launches import cli_cpu_launches

    spec = importlib.util.spec_from_file_location(f"demo_{demo[:2]}", ROOT / "demos" / demo)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    monkeypatch.chdir(cwd)
    with cli_cpu_launches():
        rc = mod.main(argv)
    out, err = capsys.readouterr()
    assert rc == 0, f"{demo} {argv} failed ({rc}):\n{out}\n{err}"
    return out


def cli_error(argv, cwd, monkeypatch, capsys) -> tuple[int, str]:
    """(exit status, stderr) of ``warpnerf argv`` run in-process in folder ``cwd``."""
    from warpnerf.cli import main

    monkeypatch.chdir(cwd)
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse
        rc = e.code
    return rc, capsys.readouterr().err


def last_json(stdout):
    return json.loads(stdout.strip().splitlines()[-1])


def test_cli_help_lists_subcommands(tmp_path):
    out = run(["-m", "warpnerf.cli", "--help"], tmp_path).stdout
    for cmd in ("demo", "train", "bench"):
        assert cmd in out


def test_cli_demo_tiny(tmp_path):
    p = run(
        [
            "-m",
            "warpnerf.cli",
            "demo",
            "--out",
            "d",
            "--iters",
            "20",
            "--size",
            "16",
            "--frames",
            "3",
            "--video-size",
            "16",
            "--quiet",
        ],
        tmp_path,
    )
    m = json.loads((tmp_path / "d" / "metrics.json").read_text())
    assert m["center_max_abs_error"] < 0.2 and m["val_psnr"] > 10
    for f in (
        "spiral_rgb.mp4",
        "spiral_rgb.gif",
        "spiral_depth.gif",
        "spiral_depth_000.png",
        "val_gt_fit_diff.png",
    ):
        assert (tmp_path / "d" / f).stat().st_size > 0, f
    assert "center" in last_json(p.stdout)


def test_cli_user_errors_exit_2_without_traceback(tmp_path):
    cli = ["-m", "warpnerf.cli"]
    missing, iters, near_far = run_all(
        [
            [*cli, "train", "box", "--data", "missing_dir", "--out", "o"],
            [*cli, "demo", "--iters", "-3"],
            [*cli, "train", "box", "--data", ".", "--out", "o", "--near", "3", "--far", "1"],
        ],
        tmp_path,
        check=False,
    )
    assert missing.returncode == 2 and "missing_dir" in missing.stderr
    assert "Traceback" not in missing.stderr
    assert iters.returncode == 2 and "Traceback" not in iters.stderr
    assert near_far.returncode == 2 and "--far" in near_far.stderr
    assert not (tmp_path / "o").exists()


def test_cli_bench_quick(tmp_path):
    run(["-m", "warpnerf.cli", "bench", "composite", "--quick", "--json", "b.json"], tmp_path)
    rows = json.loads((tmp_path / "b.json").read_text())["rows"]
    assert rows and rows[0]["max_err_rgb"] < 1e-4 and rows[0]["max_err_v_sigmas"] < 1e-4


def test_cli_bench_composite_one_size(tmp_path):
    """--rays/--samples time one size; every variant is counted at the fewest bytes (64 B per
    sample + 56 B per ray forward+backward) and reports its own estimate of what it moves."""
    from warpnerf.bench import COMPOSITE_VARIANTS

    args = ["bench", "composite", "--rays", "64", "--samples", "8", "--json", "b.json"]
    p = run(["-m", "warpnerf.cli", *args], tmp_path)
    rows = json.loads((tmp_path / "b.json").read_text())["rows"]
    assert [r["kernel"] for r in rows] == [v[0] for v in COMPOSITE_VARIANTS]
    for r in rows:
        assert (r["n_rays"], r["n_samples"]) == (64, 512)
        assert r["bytes_fwdbwd"] == 64 * 512 + 56 * 64 and r["bytes_fwd"] == 24 * 512 + 28 * 64
        assert r["max_err_rgb"] < 1e-4 and r["max_err_v_sigmas"] < 1e-4 and r["check_ms"] > 0
    moved = {r["kernel"]: r["bytes_moved_fwdbwd"] for r in rows}
    assert moved["composite_packed"] == rows[0]["bytes_fwdbwd"] + 16 * 64
    assert moved["composite_packed_seq"] == moved["composite_packed"] + 8 * 512
    assert "% copy BW fwd / fwd+bwd" in p.stdout and "64 x 8: " in p.stdout


def test_cli_bench_encoding_quick(tmp_path):
    p = run(["-m", "warpnerf.cli", "bench", "encoding", "--quick", "--json", "b.json"], tmp_path)
    rows = json.loads((tmp_path / "b.json").read_text())["rows"]
    assert [r["kernel"] for r in rows] == ["hash_encode"] and "| hash_encode |" in p.stdout
    assert rows[0]["max_err_out"] < 1e-4 and rows[0]["max_err_v_table"] < 1e-3


@pytest.mark.slow
def test_cli_bench_march_and_sphere_trace_quick(tmp_path):
    """Marching: samples per ray grow with occupancy, the kernel matches the float64 brute force
    (at most a boundary sample off); sphere tracing matches the float64 twin."""
    p, _ = run_all(
        [
            ["-m", "warpnerf.cli", "bench", "march", "--quick", "--json", "m.json"],
            ["-m", "warpnerf.cli", "bench", "sphere-trace", "--quick", "--json", "s.json"],
        ],
        tmp_path,
    )
    rows = json.loads((tmp_path / "m.json").read_text())["rows"]
    assert [r["kernel"] for r in rows] == ["march", "march"] and "| march |" in p.stdout
    assert rows[0]["occupancy"] < rows[1]["occupancy"]
    assert rows[0]["samples_per_ray"] < rows[1]["samples_per_ray"]
    assert all(r["count_mismatch"] <= 2 and r["max_err_t"] < 1e-5 for r in rows)
    (row,) = json.loads((tmp_path / "s.json").read_text())["rows"]
    assert row["status_mismatch"] <= 2 and row["max_err_t"] < 2e-4 and row["evals_per_ray"] > 1


def test_demo_10_occupancy_grid_tiny(tmp_path):
    args = [str(ROOT / "demos" / "10_occupancy_grid.py"), "--out", "o", "--iters", "8"]
    args += ["--batch", "64", "--samples", "8", "--builtin-size", "12", "--eval-images", "1"]
    p = run(args + ["--grid-res", "8"], tmp_path)
    res = last_json(p.stdout)
    assert 0 < res["occupancy"] <= 1 and res["samples_per_ray_no_grid"] == 8
    assert res["psnr_grid"] == res["psnr_grid"] and res["samples_per_ray_grid"] > 0
    assert (tmp_path / "o" / "occupancy.png").exists()


def test_demo_01_render_volume(tmp_path):
    p = run(
        [
            str(ROOT / "demos" / "01_render_volume.py"),
            "--out",
            "o",
            "--frames",
            "2",
            "--size",
            "16",
            "--samples",
            "32",
            "--shape",
            "torus",
        ],
        tmp_path,
    )
    res = last_json(p.stdout)
    assert res["frames"] == 2 and 0 < res["covered_pixel_fraction"] < 1
    assert (tmp_path / "o" / "spiral_rgb.mp4").exists() and (
        tmp_path / "o" / "spiral_depth_000.png"
    ).exists()


def test_demo_02_fit_box_builtin(tmp_path):
    p = run(
        [
            str(ROOT / "demos" / "02_fit_box.py"),
            "--out",
            "o",
            "--iters",
            "15",
            "--size",
            "16",
            "--views",
            "6",
            "--batch",
            "512",
        ],
        tmp_path,
    )
    res = last_json(p.stdout)
    assert set(res) >= {"center", "side_lengths", "final_loss"}


@pytest.mark.slow
def test_demo_02_fit_box_data_folder(tmp_path):
    """--data on a generated Blender folder recovers the box that rendered it."""
    write_box_folder(tmp_path / "scene", n_views=16, size=40, name="transforms_train.json")
    p = run(
        [
            str(ROOT / "demos" / "02_fit_box.py"),
            "--data",
            "scene",
            "--out",
            "o",
            "--iters",
            "150",
            "--batch",
            "2048",
            "--frames",
            "2",
        ],
        tmp_path,
    )
    res = last_json(p.stdout)
    assert set(res) == {"center", "side_lengths", "final_loss"}
    from warpnerf.box_demo import GT_BOX

    assert max(abs(a - b) for a, b in zip(res["center"], GT_BOX["center"])) < 0.02
    assert max(abs(a - b) for a, b in zip(res["side_lengths"], GT_BOX["side_lengths"])) < 0.02
    assert (tmp_path / "o" / "result.json").exists()


def test_demo_02_bad_data_is_a_clean_error(tmp_path):
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "transforms.json").write_text('{"frames": []}')
    p = run(
        [str(ROOT / "demos" / "02_fit_box.py"), "--data", "bad", "--out", "o"],
        tmp_path,
        check=False,
    )
    assert p.returncode == 2 and "frames" in p.stderr and "Traceback" not in p.stderr


TINY_NERF = [
    "--iters",
    "4",
    "--batch",
    "64",
    "--samples",
    "8",
    "--layers",
    "2",
    "--width",
    "16",
    "--builtin-size",
    "12",
    "--eval-images",
    "1",
]


@pytest.mark.slow
def test_cli_train_eval_render_nerf(tmp_path, monkeypatch, capsys):
    p = run(
        [
            "-m",
            "warpnerf.cli",
            "train",
            "nerf",
            "--data",
            "builtin",
            "--out",
            "r",
            "--iters",
            "4",
            "--batch",
            "64",
            "--samples",
            "8",
            "--layers",
            "2",
            "--width",
            "16",
            "--pos-freqs",
            "2",
            "--dir-freqs",
            "1",
            "--builtin-size",
            "12",
            "--val-every",
            "2",
            "--ckpt-every",
            "2",
            "--coarse-fine",
            "--fine-samples",
            "8",
            "--quiet",
        ],
        tmp_path,
    )
    assert last_json(p.stdout)["step"] == 4
    cfg = json.loads((tmp_path / "r" / "config.json").read_text())
    assert cfg["n_fine"] == 8 and cfg["near"] == 1.0 and cfg["lr_decay_steps"] == 4
    # the resume in-process (the command's subprocess ran above)
    out = cli_ok(["train", "nerf", "--out", "r", "--resume", "--iters", "6", "--quiet"], tmp_path,
                 monkeypatch, capsys)  # fmt: skip
    assert last_json(out)["step"] == 6
    p = run(["-m", "warpnerf.cli", "eval", "r", "--split", "val", "--max-images", "1"], tmp_path)
    assert last_json(p.stdout)["n_images"] == 1
    run(["-m", "warpnerf.cli", "render", "r", "--frames", "2", "--size", "8x6"], tmp_path)
    assert (tmp_path / "r" / "render_spiral" / "rgb.mp4").exists()


@pytest.mark.parametrize(
    "args, needle",
    [
        (["train", "nerf", "--data", "missing_dir", "--out", "o"], "missing_dir"),
        (["train", "nerf", "--out", "o"], "--data"),
        (["train", "nerf", "--out", "o", "--resume", "--iters", "3"], "o: not found"),
        (["eval", "nothing"], "not found"),
        (["render", "nothing", "--size", "10by3"], "WxH"),
        (["train", "nerf", "--data", "builtin", "--out", "o", "--near", "5", "--far", "1"], "near"),
        (["train", "nerf", "--out", "o", "--resume", "--iters", "9", "--batch", "7"], "--batch"),
        (["eval", "nothing", "--max-images", "-1"], "max-images"),
        (
            ["train", "nerf", "--data", "builtin", "--out", "o", "--field", "hash"]
            + ["--hash-max-res", "8"],
            "max_res",
        ),
        (["train", "nerf", "--data", "builtin", "--out", "o", "--grid-res", "8"], "--field hash"),
        (
            ["train", "nerf", "--data", "builtin", "--out", "o", "--field", "hash"]
            + ["--grid-res", "7"],
            "even",
        ),
    ],
)
def test_cli_nerf_user_errors(tmp_path, monkeypatch, capsys, args, needle):
    rc, err = cli_error(args, tmp_path, monkeypatch, capsys)
    assert rc == 2, err
    assert needle in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_cli_train_hash_field_then_eval(tmp_path):
    args = ["train", "nerf", "--data", "builtin", "--out", "r", "--field", "hash", "--iters", "3"]
    args += ["--builtin-size", "8", "--samples", "8", "--coarse-fine", "--fine-samples", "8"]
    args += ["--hash-levels", "2", "--hash-log2-size", "8", "--hash-max-res", "16", "--quiet"]
    args += ["--grid-res", "16", "--march-step", "0.05", "--grid-every", "2"]
    p = run(["-m", "warpnerf.cli", *args, "--val-every", "3", "--batch", "64"], tmp_path)
    assert last_json(p.stdout)["step"] == 3
    cfg = json.loads((tmp_path / "r" / "config.json").read_text())
    assert cfg["field"] == "hash" and cfg["lr"] == 1e-2 and cfg["aabb"] > 0
    assert cfg["grid_res"] == 16 and cfg["march_step"] == 0.05
    p = run(["-m", "warpnerf.cli", "eval", "r", "--max-images", "1"], tmp_path)
    assert last_json(p.stdout)["psnr"] > 5


@pytest.mark.parametrize(
    "demo", ["03_nerf_lego.py", "04_nerf_view_dependence.py", "05_positional_encoding.py"]
)
@pytest.mark.slow
def test_nerf_demos_tiny(tmp_path, demo):
    extra = ["--frames", "2"] if demo.startswith("03") else []
    p = run([str(ROOT / "demos" / demo), "--out", "o", *TINY_NERF, *extra], tmp_path)
    res = last_json(p.stdout)
    assert res and all(v == v for v in res.values() if isinstance(v, float))  # no NaN
    if demo.startswith("05"):
        assert (tmp_path / "o" / "grid.png").exists() and set(res) == {"psnr_0", "psnr_3", "psnr_6"}


@pytest.mark.parametrize("demo", ["06_sphere_trace_torus.py", "07_sphere_trace_scene.py"])
@pytest.mark.slow
def test_sphere_trace_demos_tiny(tmp_path, demo):
    p = run([str(ROOT / "demos" / demo), "--out", "o", "--frames", "2", "--size", "24"], tmp_path)
    res = last_json(p.stdout)
    out = tmp_path / "o"
    assert (out / "frame_000.png").exists() and (out / "metrics.json").exists()
    if demo.startswith("06"):
        assert (out / "spiral.gif").exists() and (out / "spiral.mp4").exists()
        assert res["rays_per_s"] > 0 and 1 <= res["mean_iters_per_ray"] <= 256
    else:
        assert res["primitives"] > 20 and (out / "orbit.gif").exists()
        assert res["omega_1"]["mean_iters_per_ray"] >= 1 and 0 <= res["disagreement"] <= 1


def test_cli_mesh_sdf_scene(tmp_path):
    from warpnerf.mesh import read_ply

    p = run(["-m", "warpnerf.cli", "mesh", "--sdf", "torus", "--resolution", "32", "--out",
             "m/t.ply"], tmp_path)  # fmt: skip
    res = last_json(p.stdout)
    v, f = read_ply(tmp_path / "m" / "t.ply")
    assert res["faces"] == len(f) > 100 and res["vertices"] == len(v)
    assert (tmp_path / "m" / "t.png").stat().st_size > 1000
    assert max(abs(x) for x in res["bounds_max"] + res["bounds_min"]) < 1.0


@pytest.mark.parametrize(
    "args, needle",
    [
        (["mesh", "--out", "x.ply"], "run folder or --sdf"),
        (["mesh", "--sdf", "none.json", "--out", "x.ply"], "no such scene"),
        (["mesh", "--sdf", "torus", "--out", "x.obj"], ".ply"),
        (["mesh", "--sdf", "torus", "--out", "x.ply", "--resolution", "2"], "--resolution"),
        (["mesh", "norun", "--out", "x.ply"], "not found"),
        (["mesh", "--sdf", "torus", "--bounds", "inf", "--out", "x.ply"], "--bounds"),
        (["mesh", "--sdf", "torus", "--out", "afile/x.ply"], "is a file"),
    ],
)
def test_cli_mesh_user_errors(tmp_path, monkeypatch, capsys, args, needle):
    (tmp_path / "afile").write_text("not a folder")
    rc, err = cli_error(args, tmp_path, monkeypatch, capsys)
    assert rc == 2 and needle in err and "Traceback" not in err
    assert not list(tmp_path.glob("x.*"))


@pytest.mark.slow
def test_cli_train_sdf_resume_and_mesh(tmp_path, monkeypatch, capsys):
    import numpy as np

    g = np.random.default_rng(0).normal(size=(400, 3))
    np.savez(tmp_path / "pts.npz", verts=(g / np.linalg.norm(g, axis=1, keepdims=True)) * 2 + 5)
    args = ["train", "sdf", "--points", "pts.npz", "--out", "r", "--iters", "3", "--batch", "64"]
    args += ["--layers", "2", "--width", "16", "--pos-freqs", "2", "--resolution", "16", "--quiet"]
    p = run(["-m", "warpnerf.cli", *args], tmp_path)
    assert last_json(p.stdout)["step"] == 3 and (tmp_path / "r" / "mesh.ply").exists()
    # the resume in-process (the command's subprocess ran above)
    out = cli_ok(["train", "sdf", "--out", "r", "--resume", "--iters", "5", "--quiet"], tmp_path,
                 monkeypatch, capsys)  # fmt: skip
    assert last_json(out)["step"] == 5
    p = run(["-m", "warpnerf.cli", "mesh", "r", "--resolution", "16", "--out", "m.ply",
             "--no-screenshot"], tmp_path)  # fmt: skip
    res = last_json(p.stdout)
    assert res["faces"] > 0 and min(res["bounds_min"]) > 2  # back in the points' units (centre 5)


@pytest.mark.slow
def test_cli_resume_refuses_changed_flags_and_wrong_run_kinds(tmp_path, monkeypatch, capsys):
    """In-process (the refusals are the command's, not the process's: test_bad_input.py and
    test_cli_user_errors_exit_2_without_traceback check exit 2 through the interpreter)."""
    args = ["train", "sdf", "--points", "builtin", "--out", "s", "--iters", "2", "--batch", "32"]
    args += ["--layers", "2", "--width", "32", "--pos-freqs", "2", "--resolution", "8", "--quiet"]
    cli_ok(args, tmp_path, monkeypatch, capsys)
    rc, err = cli_error(["train", "sdf", "--out", "s", "--resume", "--iters", "4", "--lr", "0.5"],
                        tmp_path, monkeypatch, capsys)  # fmt: skip
    assert rc == 2 and "drop --lr" in err
    for cmd in (["eval", "s"], ["render", "s"]):
        rc, err = cli_error(cmd, tmp_path, monkeypatch, capsys)
        assert rc == 2 and "neural-SDF run" in err and "Traceback" not in err
    rc, err = cli_error(["train", "volsdf", "--data", "builtin", "--out", "v", "--field", "mlp"],
                        tmp_path, monkeypatch, capsys)  # fmt: skip
    assert rc == 2 and "volsdf" in err


@pytest.mark.parametrize(
    "args, needle",
    [
        (
            ["train", "volsdf", "--data", "builtin", "--out", "o", "--eikonal-weight", "nan"],
            "eikonal",
        ),  # fmt: skip
        (["train", "sdf", "--out", "o"], "--points"),
        (["train", "sdf", "--points", "none.npz", "--out", "o"], "no such point-cloud"),
        (["train", "sdf", "--out", "o", "--resume", "--iters", "4"], "o: not found"),
    ],
)
def test_cli_sdf_user_errors(tmp_path, monkeypatch, capsys, args, needle):
    rc, err = cli_error(args, tmp_path, monkeypatch, capsys)
    assert rc == 2 and needle in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_demo_08_neural_sdf_tiny(tmp_path, monkeypatch, capsys):
    p = run([str(ROOT / "demos" / "08_neural_sdf.py"), "--out", "o", "--iters", "5", "--batch",
             "128", "--width", "48", "--resolution", "24", "--frames", "2", "--size", "16"],
            tmp_path)  # fmt: skip
    res = last_json(p.stdout)
    assert (tmp_path / "o" / "turntable.gif").exists() and res["trace_mean_iters"] >= 1
    assert res["chamfer"] > 0 and (tmp_path / "o" / "run" / "mesh.ply").exists()
    # run again: the demo starts afresh, removing only what warpnerf wrote in its run folder
    (tmp_path / "o" / "run" / "notes.txt").write_text("mine")
    (tmp_path / "o" / "run" / "sub").mkdir()
    (tmp_path / "o" / "run" / "sub" / "data.bin").write_bytes(b"x")
    # (the second run in-process: the first ran the script)
    out = demo_ok("08_neural_sdf.py", ["--out", "o", "--iters", "3", "--batch", "128", "--width",
                  "48", "--resolution", "24", "--frames", "1", "--size", "16"], tmp_path,
                  monkeypatch, capsys)  # fmt: skip
    assert last_json(out)["iters"] == 3  # a fresh run (a resume would refuse iters 3 < 5)
    assert (tmp_path / "o" / "run" / "notes.txt").read_text() == "mine"
    assert (tmp_path / "o" / "run" / "sub" / "data.bin").read_bytes() == b"x"


@pytest.mark.slow
def test_cli_train_volsdf_render_mesh_and_demo_09(tmp_path):
    args = ["train", "volsdf", "--data", "builtin", "--out", "r", "--iters", "3", "--quiet"]
    args += ["--builtin-size", "8", "--layers", "2", "--width", "48", "--samples", "8"]
    args += ["--fine-samples", "8", "--batch", "64", "--val-every", "3"]
    # demo 09 runs beside the commands
    demo = start([str(ROOT / "demos" / "09_volsdf.py"), "--out", "o", "--iters", "2", "--batch",
                  "32", "--samples", "4", "--layers", "2", "--width", "48", "--builtin-size", "8",
                  "--frames", "1", "--eval-images", "1"], tmp_path)  # fmt: skip
    try:
        assert last_json(run(["-m", "warpnerf.cli", *args], tmp_path).stdout)["step"] == 3
        cfg = json.loads((tmp_path / "r" / "config.json").read_text())
        assert cfg["field"] == "volsdf" and cfg["n_fine"] == 8 and cfg["pos_freqs"] == 6
        run(["-m", "warpnerf.cli", "render", "r", "--frames", "2", "--size", "8x8"], tmp_path)
        assert (tmp_path / "r" / "render_spiral" / "geometry.gif").exists()
        p = run(["-m", "warpnerf.cli", "mesh", "r", "--resolution", "16", "--out", "m.ply",
                 "--no-screenshot"], tmp_path, check=False)  # fmt: skip
        assert p.returncode in (0, 2) and "Traceback" not in p.stderr  # 2: no surface yet
        res = last_json(finish(demo).stdout)
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait()
    assert res["iters"] == 2 and res["beta"] > 0 and res["val_psnr"] > 0


@pytest.mark.slow
def test_demo_11_hash_sdf_tiny(tmp_path):
    """The surface workflow demo: train hash_sdf, eval, spiral renders with geometry, a mesh with
    baked colours (read back)."""
    from warpnerf.mesh import read_ply

    p = run([str(ROOT / "demos" / "11_hash_sdf.py"), "--out", "o", "--iters", "3", "--batch",
             "64", "--hash-levels", "3", "--hash-log2-size", "8", "--hash-max-res", "16",
             "--grid-res", "8", "--builtin-size", "8", "--frames", "1", "--eval-images", "1",
             "--mesh-resolution", "16"], tmp_path)  # fmt: skip
    res = last_json(p.stdout)
    assert res["iters"] == 3 and res["beta"] > 0 and res["val_psnr"] > 0
    assert res["sphere_traced_psnr"] > 0 and res["sphere_traced_ms_median"] > 0
    assert (tmp_path / "o" / "run" / "render_spiral" / "geometry_000.png").is_file()
    if res["mesh_faces"]:
        v, f, rgb = read_ply(tmp_path / "o" / "mesh.ply", colors=True)
        assert len(f) == res["mesh_faces"] and rgb.shape == (len(v), 3)
