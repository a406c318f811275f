"""experiments/recipe/worst_view_crops.py (issue 44's crops of the worst val views): the window
it picks is where the error is largest, and the script writes its figure from two eval folders."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location(
    "worst_view_crops", ROOT / "experiments/recipe/worst_view_crops.py"
)
crops_mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(crops_mod)


def test_worst_window_finds_the_largest_error():
    err = np.zeros((40, 50))
    err[22:30, 31:39] = 1.0
    assert crops_mod.worst_window(err, 8) == (22, 31)
    assert crops_mod.worst_window(err, 100) == (0, 0)  # (a window larger than the image: all)


def _eval_folder(path: Path, psnrs, noise, rng):
    import imageio.v3 as iio

    path.mkdir()
    gt = rng.uniform(0, 1, (24, 24, 3))
    for i in range(len(psnrs)):
        pred = np.clip(gt + noise * rng.normal(size=gt.shape), 0, 1)
        panel = np.concatenate([gt, pred, np.zeros_like(gt)], 1)
        iio.imwrite(path / f"val_{i:03d}.png", (255 * panel).astype(np.uint8))
    rows = [{"image": i, "psnr": p} for i, p in enumerate(psnrs)]
    (path / "metrics.json").write_text(json.dumps({"per_image": rows}))


def test_the_figure_from_two_eval_folders(tmp_path):
    rng = np.random.default_rng(0)
    _eval_folder(tmp_path / "a", [30.0, 20.0, 25.0], 0.1, rng)
    _eval_folder(tmp_path / "b", [31.0, 22.0, 24.0], 0.05, rng)
    rows = crops_mod.crops(tmp_path / "a", tmp_path / "b", views=2, window=8)
    assert [c.split(":")[0] for _, c in rows] == ["val 1", "val 2"]  # the after run's worst two
    assert all(t.shape == (8, 8, 3) for tiles, _ in rows for t in tiles)
    crops_mod.main([str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "c.png"),
                    "--views", "2", "--window", "8"])  # fmt: skip
    assert (tmp_path / "c.png").stat().st_size > 1000
