"""experiments/recipe/materials_regions.py (where a materials run's val error lies): pixels are
labelled by the analytic shape their centre ray hits, the error is attributed to the shape where
it was put, and the noise bound reads the noise's variance on a flat image."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest

from warpnerf.data import look_at

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location(
    "materials_regions", ROOT / "experiments/recipe/materials_regions.py"
)
mr = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mr)

ANGLE = 0.6911112070083618  # the materials scene's camera_angle_x


def _camera(elev_deg=35.0, azim_deg=20.0):
    e, a = math.radians(elev_deg), math.radians(azim_deg)
    eye = (4 * math.cos(e) * math.cos(a), 4 * math.cos(e) * math.sin(a), 4 * math.sin(e))
    return look_at(eye, up=(0.0, 0.0, 1.0)).double().numpy()


def test_labels_follow_the_analytic_scene():
    c2w = _camera()
    lab = mr.pixel_labels(c2w, ANGLE, 64, 64)
    names = mr.names()
    # the image centre looks at the origin: on the disk between the spheres (x = +-0.35 apart)
    assert names[lab[32, 32]] in ("disk", "green diffuse", "aluminium", "copper", "glass")
    assert set(np.unique(lab)) >= {names.index("disk"), names.index("background")}
    # the pixel through a sphere's centre shows that sphere
    from warpnerf.data.materials_truth import MATERIALS_SPHERES

    for k in (0, 3, 6):
        cam = np.linalg.inv(c2w) @ np.array([*MATERIALS_SPHERES[k], 1.0])
        f = 0.5 * 64 / math.tan(0.5 * ANGLE)
        u, v = 32 + f * cam[0] / -cam[2], 32 - f * cam[1] / -cam[2]
        if 0 <= u < 64 and 0 <= v < 64:
            assert lab[int(v), int(u)] == k


def test_the_error_is_attributed_where_it_was_put(tmp_path):
    import imageio.v3 as iio

    data, ev = tmp_path / "data", tmp_path / "eval"
    data.mkdir()
    ev.mkdir()
    poses = [_camera(30 + 10 * i, 40 * i).tolist() for i in range(2)]
    frames = [{"file_path": f"./val/r_{i}", "transform_matrix": m} for i, m in enumerate(poses)]
    (data / "transforms_val.json").write_text(json.dumps({"camera_angle_x": ANGLE,
                                                          "frames": frames}))  # fmt: skip
    rng = np.random.default_rng(0)
    names = mr.names()
    for i, fr in enumerate(frames):
        lab = mr.pixel_labels(np.array(fr["transform_matrix"]), ANGLE, 48, 48)
        gt = np.full((48, 48, 3), 0.5)
        pred = gt.copy()
        gold = lab == names.index("gold")
        pred[gold] += 0.2 * rng.choice([-1, 1], (int(gold.sum()), 3))
        panel = np.concatenate([gt, np.clip(pred, 0, 1), np.zeros_like(gt)], 1)
        iio.imwrite(ev / f"val_{i:03d}.png", np.round(255 * panel).astype(np.uint8))
    res = mr.regions(ev, data)
    rows = {r["shape"]: r for r in res["rows"]}
    assert res["views"] == 2
    assert rows["gold"]["error_share"] == pytest.approx(1.0)
    assert rows["gold"]["psnr"] == pytest.approx(-10 * math.log10((51 / 255) ** 2), abs=0.05)
    assert rows["gold"]["psnr_if_exact"] == math.inf and rows["disk"]["error_share"] == 0.0
    assert sum(r["pixel_share"] for r in res["rows"]) == pytest.approx(1.0)
    assert "| gold |" in mr.table(res)


def test_the_noise_bound_reads_flat_noise():
    rng = np.random.default_rng(1)
    img = 0.5 + 0.02 * rng.standard_normal((64, 64, 3))
    lab = np.zeros((64, 64), dtype=np.int64)
    lab[:, 40:] = 1
    r, rl = mr.noise_residual(img, lab)
    assert np.mean(r[rl == 0]) == pytest.approx(0.02**2, rel=0.1)
    assert not np.any((rl == 0) & (rl == 1)) and set(np.unique(rl)) == {0, 1}
