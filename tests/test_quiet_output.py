"""CPU commands print nothing but their own output and progress bars: no "Warp CUDA warning: Could
not find or load the NVIDIA CUDA driver" (warpnerf/ops/bridge.py holds it back at Warp's init),
no Warp "Module ... load" lines, no VTK "bad X server connection" line from pyvista's offscreen
screenshot (warpnerf/mesh.py asks VTK for EGL when there is no X display), no Python warnings
(the commands run with PYTHONWARNINGS=default, which shows the ones hidden by default)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import pytest
import torch

from tests.test_mesh_tools import red_box_run

# a tqdm bar ("fit:  40%|####  | 2/5 [00:01<00:01, ...]", or "12it [00:00, ...]" without a total)
_BAR = re.compile(r"\d+%\||\d+(/\d+|it) \[")


def _run(args, tmp_path, timeout=300):
    env = dict(os.environ, PYTHONWARNINGS="default", PYTHONUNBUFFERED="1")
    env.pop("WARPNERF_VERBOSE", None)
    return subprocess.run([sys.executable, "-m", "warpnerf.cli", *args], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=timeout)  # fmt: skip


def _noise(stderr: str) -> list:
    """Everything on stderr that is not a progress bar (tqdm redraws with carriage returns)."""
    parts = (p.strip() for p in re.split(r"[\r\n]", stderr))
    return [p for p in parts if p and not _BAR.search(p)]


def _check_stdout(stdout: str) -> dict:
    """No Warp lines on stdout either; the last line is the command's JSON."""
    assert not [ln for ln in stdout.splitlines() if "Warp" in ln or ln.startswith("Module ")]
    return json.loads(stdout.strip().splitlines()[-1])


def test_demo_on_cpu_prints_only_progress(tmp_path):
    out = tmp_path / "demo"
    p = _run(["demo", "--out", str(out), "--device", "cpu", "--iters", "5", "--size", "16",
              "--frames", "2", "--video-size", "16"], tmp_path)  # fmt: skip
    assert p.returncode == 0, p.stderr[-2000:]
    assert _noise(p.stderr) == [], p.stderr[-2000:]
    assert "val_psnr" in _check_stdout(p.stdout)


def test_mesh_with_screenshot_prints_nothing_else(tmp_path):
    run = red_box_run(tmp_path)
    ply = tmp_path / "mesh.ply"
    p = _run(["mesh", str(run), "--out", str(ply), "--resolution", "16", "--bounds", "1.25",
              "--colors"], tmp_path)  # fmt: skip
    assert p.returncode == 0, p.stderr[-2000:]
    assert _noise(p.stderr) == [], p.stderr[-2000:]
    res = _check_stdout(p.stdout)
    assert res["screenshot"] and (tmp_path / "mesh.png").stat().st_size > 0


@pytest.mark.slow
def test_train_sdf_prints_only_progress(tmp_path):
    run = tmp_path / "sdf"
    p = _run(["train", "sdf", "--points", "builtin", "--out", str(run), "--device", "cpu",
              "--iters", "5", "--batch", "64", "--layers", "2", "--width", "16", "--pos-freqs",
              "1", "--resolution", "16", "--no-tensorboard"], tmp_path)  # fmt: skip
    assert p.returncode == 0, p.stderr[-2000:]
    assert _noise(p.stderr) == [], p.stderr[-2000:]
    assert "chamfer" in _check_stdout(p.stdout)
    assert (run / "mesh.png").stat().st_size > 0  # the screenshot was taken


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_asked_for_without_a_driver_still_says_so(tmp_path, capsys):
    """The held-back driver warning is not lost: `--device cuda` fails with the CLI's one clear
    line, and asking Warp itself for a CUDA device names the missing driver."""
    from warpnerf.cli.parser import main

    ply = tmp_path / "t.ply"
    assert main(["mesh", "--sdf", "torus", "--device", "cuda", "--out", str(ply)]) == 2
    err = capsys.readouterr().err
    assert "--device cuda: no CUDA device" in err and len(err.strip().splitlines()) == 1
    code = "\n".join([
        "import sys, torch", "from warpnerf.ops import bridge", "bridge.load_warp()",
        "sys.stderr.write('init done\\n')", "try:",
        "    bridge.wp_device(torch.device('cuda', 0))",
        "except RuntimeError as e:", "    print(e)",
    ])  # fmt: skip
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and p.stderr.strip() == "init done", p.stderr
    if "Warp has no CUDA here" not in p.stdout:
        pytest.skip("Warp found a CUDA driver here (no GPU for PyTorch, though)")
    assert "Could not find or load the NVIDIA CUDA driver" in p.stdout
