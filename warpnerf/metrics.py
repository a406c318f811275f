"""Image quality metrics for NeRF evaluation: PSNR and SSIM on torch tensors (CPU or CUDA).

Both return Python floats and compute in float64 whatever the input dtype, so a score does not
depend on whether the render was float32 or float16. Settings follow the NeRF papers' evaluation
code (NeRF's ``tf.image.ssim``, multinerf's ``compute_ssim``):

- PSNR: ``-10 log10(MSE / max_val^2)`` with the MSE over all pixels, channels (and images).
- SSIM: Gaussian 11x11, sigma 1.5, K1 0.01, K2 0.03, valid region, mean over RGB channels.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

__all__ = ["psnr", "ssim"]

# Wang et al. 2004 constants, as in the NeRF / mip-NeRF / multinerf evaluation code.
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def _check_pair(pred: torch.Tensor, gt: torch.Tensor, ndims: tuple[int, ...], layout: str) -> None:
    if pred.shape != gt.shape:
        raise ValueError(
            f"pred and gt must have the same shape, got pred {tuple(pred.shape)} "
            f"and gt {tuple(gt.shape)}"
        )
    if pred.dim() not in ndims or pred.shape[-1] != 3:
        raise ValueError(f"expected images of shape {layout}, got {tuple(pred.shape)}")
    if pred.device != gt.device:
        raise ValueError(f"pred is on {pred.device} but gt is on {gt.device}")


def psnr(pred: torch.Tensor, gt: torch.Tensor, max_val: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB, over all pixels and channels (and images).

    ``PSNR = 10 log10(max_val^2 / MSE)``; ``inf`` when the images are identical.

    Args:
        pred: [H, W, 3] or [N, H, W, 3] predicted colours.
        gt: same shape as ``pred``, reference colours.
        max_val: the largest possible pixel value (1.0 for images in [0, 1]).

    Returns:
        The PSNR in dB as a Python float.

    Raises:
        ValueError: ``pred`` and ``gt`` differ in shape (both shapes are named) or device, or are
            not [H, W, 3] / [N, H, W, 3].
    """
    _check_pair(pred, gt, (3, 4), "[H, W, 3] or [N, H, W, 3]")
    diff = pred.detach().to(torch.float64) - gt.detach().to(torch.float64)
    mse = float((diff * diff).mean())
    if mse == 0.0:
        return math.inf
    return 10.0 * math.log10(max_val * max_val / mse)


def _gaussian_window(device: torch.device) -> torch.Tensor:
    """[SSIM_WINDOW] float64 1-D Gaussian taps (sigma SSIM_SIGMA), normalised to sum 1."""
    x = torch.arange(SSIM_WINDOW, dtype=torch.float64, device=device) - (SSIM_WINDOW - 1) / 2
    g = torch.exp(-0.5 * (x / SSIM_SIGMA) ** 2)
    return g / g.sum()


def _blur_valid(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian filter, 'valid' region: [B, 1, H, W] -> [B, 1, H - 10, W - 10]."""
    x = F.conv2d(x, g.view(1, 1, -1, 1))  # along H
    return F.conv2d(x, g.view(1, 1, 1, -1))  # along W


def ssim(pred: torch.Tensor, gt: torch.Tensor, max_val: float = 1.0) -> float:
    """Structural similarity (Wang et al. 2004) as used by the NeRF papers' evaluation.

    SSIM: Gaussian 11x11, sigma 1.5, K1 0.01, K2 0.03, valid region, mean over RGB channels.

    Per channel, with Gaussian-weighted local means ``mu``, variances ``s_xx``, ``s_yy`` and
    covariance ``s_xy`` (population, not sample, statistics) and ``C1 = (K1 max_val)^2``,
    ``C2 = (K2 max_val)^2``::

        SSIM = (2 mu_x mu_y + C1) (2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1) (s_xx + s_yy + C2))

    evaluated only where the 11x11 window lies inside the image ('valid' convolution, no padding,
    an (H - 10) x (W - 10) map per channel) and averaged over that map and the three channels.
    The window is the separable, normalised Gaussian ``exp(-i^2 / (2 * 1.5^2))``, i = -5..5. As in
    multinerf, variances that rounding makes slightly negative are clamped to 0 and ``|s_xy|`` to
    ``sqrt(s_xx s_yy)``; in float64 this changes results only at the rounding level. Matches
    ``skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=max_val, channel_axis=-1)``, whose default crop of 5
    pixels per border is exactly this valid region.

    Args:
        pred: [H, W, 3] predicted image, values in [0, max_val]; H, W >= 11.
        gt: [H, W, 3] reference image, same shape and device as ``pred``.
        max_val: the dynamic range of the pixel values (1.0 for images in [0, 1]).

    Returns:
        The mean SSIM as a Python float; 1.0 for identical images.

    Raises:
        ValueError: ``pred`` and ``gt`` differ in shape (both shapes are named) or device, are not
            [H, W, 3], or are smaller than the 11x11 window.
    """
    _check_pair(pred, gt, (3,), "[H, W, 3]")
    h, w = pred.shape[:2]
    if h < SSIM_WINDOW or w < SSIM_WINDOW:
        raise ValueError(
            f"ssim needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {h}x{w}"
        )
    # [H, W, 3] -> [3, 1, H, W]: each channel filtered on its own.
    x = pred.detach().to(torch.float64).permute(2, 0, 1).unsqueeze(1)
    y = gt.detach().to(torch.float64).permute(2, 0, 1).unsqueeze(1)
    g = _gaussian_window(x.device)

    mu_x = _blur_valid(x, g)
    mu_y = _blur_valid(y, g)
    s_xx = (_blur_valid(x * x, g) - mu_x * mu_x).clamp_min(0.0)
    s_yy = (_blur_valid(y * y, g) - mu_y * mu_y).clamp_min(0.0)
    s_xy = _blur_valid(x * y, g) - mu_x * mu_y
    s_xy = torch.sign(s_xy) * torch.minimum(torch.sqrt(s_xx * s_yy), s_xy.abs())

    c1 = (SSIM_K1 * max_val) ** 2
    c2 = (SSIM_K2 * max_val) ** 2
    num = (2.0 * mu_x * mu_y + c1) * (2.0 * s_xy + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (s_xx + s_yy + c2)
    return float((num / den).mean())
