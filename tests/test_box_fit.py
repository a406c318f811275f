"""Convergence: the box fit recovers a known box (center and sides within 0.02)."""

import pytest

from warpnerf.box_demo import GT_BOX
from warpnerf.data import intrinsics_from_fov, orbit_views
from warpnerf.fields import SDFVolume
from warpnerf.metrics import psnr
from warpnerf.train import BoxFitConfig, fit_box, render_box_views


def _max_err(a, b):
    return max(abs(x - y) for x, y in zip(a, b))


@pytest.mark.slow
def test_fit_box_recovers_known_box(device):
    cfg = BoxFitConfig(iters=150, batch=2048)
    gt = SDFVolume("box", **GT_BOX).to(device)
    cams = orbit_views(16, radius=3.0).to(device)
    k = intrinsics_from_fov(40, 40, 0.7).to(device).expand(16, 4)
    images, _ = render_box_views(gt, cams, k, 40, 40, cfg)
    res = fit_box(images, cams, k, cfg)
    assert _max_err(res["center"], GT_BOX["center"]) < 0.02, res["center"]
    assert _max_err(res["side_lengths"], GT_BOX["side_lengths"]) < 0.02, res["side_lengths"]
    assert res["final_loss"] < 0.1 * res["losses"][0]
    fitted, _ = render_box_views(res["volume"], cams[:2], k[:2], 40, 40, cfg)
    assert psnr(fitted, images[:2]) > 35.0


def test_fit_box_moves_towards_truth_quickly():
    """A short run must already reduce the center error: catches a gradient of the wrong sign."""
    cfg = BoxFitConfig(iters=25, batch=1024, n_samples=48)
    gt = SDFVolume("box", **GT_BOX)
    cams = orbit_views(8, radius=3.0)
    k = intrinsics_from_fov(24, 24, 0.7).expand(8, 4)
    images, _ = render_box_views(gt, cams, k, 24, 24, cfg)
    res = fit_box(images, cams, k, cfg)
    start = _max_err((0.0, 0.0, 0.0), GT_BOX["center"])
    assert _max_err(res["center"], GT_BOX["center"]) < 0.5 * start
    assert res["final_loss"] < 0.5 * res["losses"][0]
