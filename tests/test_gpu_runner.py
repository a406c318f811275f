"""scripts/gpu.py, the one GPU runner, on the CPU: it lists its phases, each phase's bash script
parses (``bash -n``) and names only files that exist, every old harness has a phase, and the
tables it prints come out of made-up run folders. (Running a phase needs the lent GPU.)"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GPU = ROOT / "scripts" / "gpu.py"
OLD = ["gpu_check.sh", "gpu_graph.sh", "gpu_hash_sdf.sh", "gpu_nerf.sh", "gpu_next.sh",
       "gpu_overhead.sh", "gpu_before_after.sh", "gpu_recipe_ablation.sh", "gpu_scaling.sh",
       "gpu_surfaces.sh"]  # fmt: skip


def _gpu(*args, **kw) -> str:
    p = subprocess.run([sys.executable, GPU, *map(str, args)], capture_output=True, text=True,
                       cwd=ROOT, timeout=60, **kw)  # fmt: skip
    assert p.returncode == 0, p.stderr
    return p.stdout


def _phases() -> list:
    return [line.split()[0] for line in _gpu("--list").splitlines()]


def test_the_runner_lists_its_phases_and_each_old_harness_has_one():
    listing = _gpu("--list")
    assert {"check", "ttq", "ablation", "hash_sdf", "before_after", "scaling_one"} <= set(_phases())
    for old in OLD:
        assert f"was {old}" in listing or f"; {old}" in listing, old
    assert "PHASE" in _gpu("--help")
    assert not list((ROOT / "scripts").glob("*gpu_*.sh"))  # the one-off harnesses are gone


@pytest.mark.parametrize("phase", _phases())
def test_each_phase_parses_and_names_files_that_exist(phase):
    text = _gpu("--print", phase)
    subprocess.run(["bash", "-n"], input=text, text=True, check=True)
    for path in re.findall(r"\b((?:scripts|experiments|demos)/[\w/]+\.py)\b", text):
        assert (ROOT / path).is_file(), f"{phase}: {path}"


def test_an_unknown_phase_is_refused():
    p = subprocess.run([sys.executable, GPU, "nope"], capture_output=True, text=True)
    assert p.returncode == 2 and "unknown phase" in p.stderr


def test_the_summaries_on_made_up_runs(tmp_path):
    run = tmp_path / "abl_lego_base"
    (run).mkdir()
    (tmp_path / "abl_lego_base_eval").mkdir()
    history = {"seconds": [0.01 * i for i in range(400)], "step": list(range(1, 401))}
    (run / "history.json").write_text(json.dumps(history))
    metrics = {"n_images": 2, "psnr": 30.0, "ssim": 0.9, "render_ms_median": 5.0}
    (tmp_path / "abl_lego_base_eval" / "metrics.json").write_text(json.dumps(metrics))
    (tmp_path / "abl_lego_base.log").write_text("ok\n")
    row = _gpu("--summary", "ablation", run, "lego", "base", "", "60")
    assert row.startswith("| lego | base |") and "30.000" in row and "| graph |" in row
    fog = tmp_path / "fog.json"
    shares = {"share": 0.0123, "rays_over_10pct": 0.045}
    fog.write_text(json.dumps({"overall": {"near_median": shares, "near_centre": shares}}))
    row = _gpu("--summary", "fog", run, fog, "lego", "near", "--near-loss 0.1", "60")
    assert row.startswith("| lego | near | `--near-loss 0.1` | 60 | 400 | 30.000 |")
    assert row.count("0.0123 | 0.045") == 2
    assert "failed" in _gpu("--summary", "fog", run, tmp_path / "none.json", "l", "n", "", "1")
    prof = tmp_path / "prof.json"
    prof.write_text(json.dumps({"step_ms_median": 8.2, "top_device_ops_ms_per_step": {"k": 1.0}}))
    assert "8.2" in _gpu("--summary", "graph_profile", prof, "off")
    assert "[('k', 1.0)]" in _gpu("--summary", "graph_profile", prof, "hash_sdf auto")


def test_a_phase_runs_through_bash(tmp_path):
    """graph_summary, the one phase that needs no GPU: the runner's bash, $OUT and $GPU."""
    (tmp_path / "prof_off.json").write_text(json.dumps({"step_ms_median": 8.25}))
    out = _gpu("graph_summary", env={**os.environ, "OUT": str(tmp_path)})
    assert "=== graph_summary" in out and "'step_ms_median': 8.25" in out
