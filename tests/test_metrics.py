"""PSNR and SSIM: closed forms, identities, an independent loop reference and skimage."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest
import torch

from warpnerf.metrics import psnr, ssim

_HAS_SKIMAGE = importlib.util.find_spec("skimage") is not None


def _ssim_loops(x: np.ndarray, y: np.ndarray, max_val: float = 1.0) -> float:
    """Direct SSIM: explicit 11x11 Gaussian window, a loop over every valid window position, and
    centred (two-pass) statistics, so it shares no code or formula rearrangement with ssim()."""
    win, sigma = 11, 1.5
    i = np.arange(win) - win // 2
    w = np.exp(-(i[:, None] ** 2 + i[None, :] ** 2) / (2.0 * sigma**2))
    w /= w.sum()
    c1, c2 = (0.01 * max_val) ** 2, (0.03 * max_val) ** 2
    h, wd, nc = x.shape
    values = []
    for c in range(nc):
        for r in range(h - win + 1):
            for q in range(wd - win + 1):
                px = x[r : r + win, q : q + win, c]
                py = y[r : r + win, q : q + win, c]
                mx, my = (w * px).sum(), (w * py).sum()
                vx = (w * (px - mx) ** 2).sum()
                vy = (w * (py - my) ** 2).sum()
                cxy = (w * (px - mx) * (py - my)).sum()
                values.append(
                    (2 * mx * my + c1) * (2 * cxy + c2) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
                )
    return float(np.mean(values))


def _image(h: int, w: int, device, dtype=torch.float64) -> torch.Tensor:
    return torch.rand(h, w, 3, dtype=torch.float64).to(device=device, dtype=dtype)


# ---- PSNR ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("e", [0.5, 0.1, 1e-3])
@pytest.mark.parametrize("shape", [(8, 9, 3), (2, 5, 4, 3)])
def test_psnr_constant_error_closed_form(device, e, shape):
    gt = torch.rand(shape, dtype=torch.float64).to(device)
    pred = gt + e * torch.where(torch.rand(shape) < 0.5, -1.0, 1.0).to(device, torch.float64)
    assert psnr(pred, gt) == pytest.approx(-10.0 * math.log10(e * e), abs=1e-10)


def test_psnr_max_val_scales(device):
    gt = _image(6, 7, device)
    pred = gt + 0.1
    assert psnr(255 * pred, 255 * gt, max_val=255.0) == pytest.approx(psnr(pred, gt), abs=1e-9)


def test_psnr_identical_is_inf(device):
    img = _image(5, 6, device, torch.float32)
    assert psnr(img, img.clone()) == math.inf
    assert psnr(img[None].expand(2, -1, -1, -1), img[None].repeat(2, 1, 1, 1)) == math.inf


# ---- SSIM ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ssim_identical_is_one(device, dtype):
    img = _image(32, 40, device, dtype)
    assert abs(ssim(img, img.clone()) - 1.0) <= 1e-12
    flat = torch.full((20, 20, 3), 0.3, dtype=dtype, device=device)  # zero variance everywhere
    assert abs(ssim(flat, flat.clone()) - 1.0) <= 1e-12


def test_ssim_symmetric(device):
    a, b = _image(24, 30, device), _image(24, 30, device)
    assert abs(ssim(a, b) - ssim(b, a)) <= 1e-14
    noisy = (a + 0.1 * torch.randn_like(a)).clamp(0, 1)
    assert abs(ssim(a, noisy) - ssim(noisy, a)) <= 1e-14


def test_ssim_decreases_with_noise(device):
    # A smooth image, so structure is there for noise to destroy.
    u = torch.linspace(0, 1, 48, dtype=torch.float64)
    img = torch.stack(
        [0.5 + 0.4 * torch.sin(6 * u[:, None] + c * u[None, :]) for c in (2.0, 5.0, 9.0)], -1
    ).to(device)
    noise = torch.randn(img.shape, dtype=torch.float64).to(device)
    scores = [ssim((img + s * noise).clamp(0, 1), img) for s in (0.0, 0.01, 0.05, 0.2, 0.5)]
    assert scores[0] == pytest.approx(1.0, abs=1e-12)
    assert all(a > b for a, b in zip(scores, scores[1:])), scores
    assert scores[-1] < 0.3


def test_ssim_constant_shift_closed_form(device):
    # Flat images: variances and covariance vanish, so SSIM is the luminance term alone.
    a, c = 0.4, 0.15
    x = torch.full((16, 16, 3), a, dtype=torch.float64, device=device)
    c1 = (0.01) ** 2
    want = (2 * a * (a + c) + c1) / (a * a + (a + c) ** 2 + c1)
    assert ssim(x + c, x) == pytest.approx(want, abs=1e-12)


@pytest.mark.parametrize("shift", [0.05, -0.2])
def test_ssim_matches_loop_reference(device, shift):
    gt = torch.rand(16, 16, 3, dtype=torch.float64)
    pred = gt + shift
    want = _ssim_loops(pred.numpy(), gt.numpy())
    assert ssim(pred.to(device), gt.to(device)) == pytest.approx(want, abs=1e-10)
    noisy = (gt + 0.1 * torch.randn_like(gt)).clamp(0, 1)  # structure differs too
    want = _ssim_loops(noisy.numpy(), gt.numpy())
    assert ssim(noisy.to(device), gt.to(device)) == pytest.approx(want, abs=1e-10)


def test_ssim_max_val_scales(device):
    gt = _image(20, 18, device)
    pred = (gt + 0.05 * torch.randn_like(gt)).clamp(0, 1)
    want = ssim(pred, gt)
    assert ssim(255 * pred, 255 * gt, max_val=255.0) == pytest.approx(want, abs=1e-12)


@pytest.mark.skipif(
    not _HAS_SKIMAGE, reason="scikit-image not installed: skimage comparison skipped"
)
@pytest.mark.parametrize("shape", [(11, 11), (32, 48), (57, 40)])
def test_ssim_matches_skimage(shape):
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(0)
    gt = rng.random((*shape, 3))
    pred = np.clip(gt + 0.1 * rng.standard_normal(gt.shape), 0, 1)
    kwargs = dict(
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=1.0,
        channel_axis=-1,
    )
    ours = ssim(torch.from_numpy(pred), torch.from_numpy(gt))
    # skimage filters the whole image (reflect padding) but averages only after cropping
    # (win_size - 1) // 2 = 5 pixels per border: exactly our valid region.
    assert ours == pytest.approx(structural_similarity(pred, gt, **kwargs), abs=1e-10)
    # The same, with the valid region cropped explicitly from skimage's full map.
    _, full = structural_similarity(pred, gt, full=True, **kwargs)
    assert ours == pytest.approx(float(full[5:-5, 5:-5].mean()), abs=1e-10)


# ---- validation ----------------------------------------------------------------------------------


@pytest.mark.parametrize("metric", [psnr, ssim])
def test_mismatched_shapes_name_both(metric):
    a, b = torch.rand(16, 16, 3), torch.rand(16, 17, 3)
    with pytest.raises(ValueError, match=r"\(16, 16, 3\).*\(16, 17, 3\)"):
        metric(a, b)


@pytest.mark.parametrize(
    "metric, shape",
    [(psnr, (16, 16)), (psnr, (16, 16, 4)), (ssim, (2, 16, 16, 3)), (ssim, (10, 16, 3))],
)
def test_bad_layout_raises(metric, shape):
    a = torch.rand(shape)
    with pytest.raises(ValueError, match=r"got"):
        metric(a, a.clone())
