"""The training recipe of instant-ngp and tiny-cuda-nn, one option each (issue 44): random
backgrounds behind RGBA pixels, occupancy cells outside every training frustum, Adam that leaves
hash-table rows without a gradient alone, L2 on the MLP weights, an exponential moving average of
the weights, the Huber photometric loss, the opacity (mask) loss, half-precision MLPs and rays
through random points of their pixels. Each is a field of :class:`RecipeConfig`, a section of a
NeRF/VolSDF run's config; a config.json written before the section existed reads the values those
runs trained with (:data:`LEGACY`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..fields.mlp import PRECISIONS
from ..options import option

__all__ = [
    "RecipeConfig", "LEGACY", "HUBER_DELTA", "EMA_MAX", "MASK_LOSS_MAX", "random_background",
    "wants_alpha", "mask_weight", "TRAIN_SPP_MAX", "TRAIN_SPP_OBJECTS", "default_train_spp",
]  # fmt: skip

HUBER_DELTA = 0.1  # instant-ngp's Huber loss: quadratic below 0.1, linear above
MASK_LOSS_MAX = 100.0  # --mask-loss: a weight this large would drown the photometric term
MASK_PIXELS = ("all", "background")  # --mask-pixels: the pixels the opacity loss reads
TRAIN_SPP_MAX = 16  # --train-spp: rays a training pixel at most
EMA_MAX = 0.9999  # --ema above this would freeze the averaged weights for ~10^4+ steps
PRECISION_NAMES = tuple(PRECISIONS)  # --mlp-precision's choices (fields/mlp.py)

# what a run trained with before these options existed (its config.json lacks the keys)
LEGACY = {
    "random_background": "off",
    "view_cull": False,
    "sparse_adam": False,
    "mlp_weight_decay": 0.0,
    "ema": 0.0,
    "photometric_loss": "mse",
    "mask_loss": 0.0,
    "mask_pixels": "all",
    "mlp_precision": "fp32",
    "pixel_jitter": False,
    "train_spp": 1,
}


@dataclass
class RecipeConfig:
    """instant-ngp's training recipe, one option each (defaults: the measured winners)."""

    TITLE = "training recipe (instant-ngp, tiny-cuda-nn)"

    random_background: str = option(
        "off", "composite each training ray of an RGBA dataset onto a random background colour "
        "(its alpha kept; evaluation stays on the dataset's background); auto: on when the "
        "training images have alpha",
        choices=("auto", "on", "off"),
    )  # fmt: skip
    view_cull: bool = option(
        False, "occupancy grid: cells outside every training camera's frustum are empty from "
        "the start and stay empty (nothing no camera sees can become a floater)",
    )  # fmt: skip
    sparse_adam: bool = option(
        False, "hash field: Adam leaves table rows without a gradient this step untouched "
        "(values, moments and their step count), as tiny-cuda-nn's",
    )  # fmt: skip
    mlp_weight_decay: float = option(
        0.0, "L2 on the MLP weights only (not biases, tables or codes; instant-ngp: 1e-6)",
        check="nonnegative",
    )  # fmt: skip
    ema: float = option(
        0.0, "decay of an exponential moving average of the weights (tiny-cuda-nn: 0.95), "
        "used by eval, render, mesh and the viewer and saved in the checkpoint; 0: off",
        check="nonnegative",
    )  # fmt: skip
    photometric_loss: str | None = option(
        None, f"the colour loss: mse, or huber (delta {HUBER_DELTA}, instant-ngp); default: the "
        "field's, huber for hash_sdf (on an H200 lego +1.3 dB after 300 s and a closer "
        "materials mesh, docs/design/nerf.md \"Issue 44, eleventh round\"), mse for the others",
        choices=("mse", "huber"),
    )  # fmt: skip
    mask_loss: float = option(
        0.0, "weight of the opacity loss: binary cross-entropy of each training ray's rendered "
        "opacity against its pixel's alpha (instant-nsr-pl: 0.1; `train volsdf`'s default); "
        "images without alpha: off (said in the log); 0: off",
        check="nonnegative",
    )  # fmt: skip
    mask_pixels: str = option(
        "all", "the pixels of --mask-loss: all (the cross-entropy against every pixel's alpha), "
        "or background (only pixels with alpha below 0.5, whose rendered opacity it pushes to "
        "0; the object's own opacity is left to the colour loss)",
        choices=MASK_PIXELS,
    )  # fmt: skip
    mlp_precision: str = option(
        "fp32", "--field hash: the MLPs' matrix products in training steps, fp32, or bf16 / "
        "fp16 under autocast (float32 weights; fp16's gradients scaled inside the MLP); "
        "validation and renders stay float32",
        choices=PRECISION_NAMES,
    )  # fmt: skip
    pixel_jitter: bool = option(
        False, "each training ray passes through a uniform random point of its pixel instead "
        "of the pixel's centre (instant-ngp's training rays), against the pixel's colour; on "
        "lego 0.8-1.2 dB below one ray through the centre (it learns the pixels' blur once "
        "more); --train-spp models area-averaged pixels instead",
    )  # fmt: skip
    train_spp: int | None = option(
        None, f"each training pixel rendered as the mean of N rays through fixed points of it "
        f"(a k x k grid for N = k^2; at most {TRAIN_SPP_MAX}) against its colour: the image of "
        "a dataset downsampled by area averaging; N times the rays a pixel (the batch adapts to "
        "--target-samples); eval and validation render N rays a pixel too. Default: 4 for "
        "--field hash on CUDA with rendered objects (Blender format; measured on lego), else 1",
        check="positive",
    )  # fmt: skip

    def check_section(self, fail) -> None:
        if self.random_background not in ("auto", "on", "off"):
            raise fail(
                "random_background", f"must be one of auto, on, off, got {self.random_background!r}"
            )
        if self.photometric_loss not in ("mse", "huber", None):  # (None: the field's)
            raise fail("photometric_loss", f"must be mse or huber, got {self.photometric_loss!r}")
        w = self.mlp_weight_decay
        if not (isinstance(w, (int, float)) and math.isfinite(w) and 0 <= w <= 1):
            raise fail("mlp_weight_decay", f"must be in [0, 1], got {w}")
        e = self.ema
        if not (isinstance(e, (int, float)) and math.isfinite(e) and (e == 0 or 0 < e <= EMA_MAX)):
            raise fail("ema", f"must be 0 (off) or in (0, {EMA_MAX}], got {e}")
        if self.mlp_precision not in PRECISION_NAMES:
            raise fail("mlp_precision", f"must be one of {', '.join(PRECISION_NAMES)}, got "
                       f"{self.mlp_precision!r}")  # fmt: skip
        t = self.train_spp
        if t is not None and (isinstance(t, bool) or not isinstance(t, int)
                              or not 1 <= t <= TRAIN_SPP_MAX):  # fmt: skip
            raise fail("train_spp", f"must be an integer in [1, {TRAIN_SPP_MAX}], got {t!r}")
        if t is not None and t > 1 and self.pixel_jitter:
            raise fail("train_spp", "cannot be combined with pixel_jitter (--pixel-jitter): "
                       "fixed points of each pixel, or one random point")  # fmt: skip
        m = self.mask_loss
        if not (isinstance(m, (int, float)) and math.isfinite(m) and 0 <= m <= MASK_LOSS_MAX):
            raise fail("mask_loss", f"must be in [0, {MASK_LOSS_MAX:g}], got {m}")
        if self.mask_pixels not in MASK_PIXELS:
            raise fail("mask_pixels", f"must be one of {', '.join(MASK_PIXELS)}, got "
                       f"{self.mask_pixels!r}")  # fmt: skip


# --train-spp's default where it is measured to win: the hash NeRF on CUDA, on renders of an
# object (lego 400x400, the 2x2 means of 800x800 renders: +1.3 dB at 60 s, +1.8 at 300 s, each
# scored with 4 rays a pixel; materials, rendered at its own size: -0.02 dB. One H200,
# 2026-12-02, docs/design/nerf.md "Issue 44, fifth round")
TRAIN_SPP_OBJECTS = 4


def default_train_spp(cfg, data_format: str | None) -> int:
    """--train-spp when not given: :data:`TRAIN_SPP_OBJECTS` for ``--field hash`` on CUDA with
    a dataset of rendered objects (``data_format`` "blender"), else 1 (photo captures, the
    built-in scene, which warpnerf renders through the pixels' centres, SDF fields, the paper's
    MLP and CPU runs: not measured)."""
    cuda = str(cfg.device).startswith("cuda")
    return TRAIN_SPP_OBJECTS if cfg.field == "hash" and data_format == "blender" and cuda else 1


def wants_alpha(cfg) -> bool:
    """Whether a run reads its training images' alpha: --random-background on or auto, on a run
    with an occupancy grid (the renderers that take a colour per ray), or --mask-loss."""
    bg = bool(cfg.grid_res) and cfg.random_background != "off"
    return bg or float(getattr(cfg, "mask_loss", 0.0) or 0.0) > 0


def mask_weight(cfg, train) -> float:
    """The opacity loss's weight on the split ``train``: --mask-loss where its images have
    alpha, else 0."""
    w = float(getattr(cfg, "mask_loss", 0.0) or 0.0)
    return w if getattr(train, "alpha", None) is not None else 0.0


def random_background(cfg, train) -> bool:
    """Whether the training rays of a run on the split ``train`` see random backgrounds: always
    when the scene is contracted (no fixed colour lies behind it), else with --random-background
    on, or auto when the split has alpha; runs with an occupancy grid only."""
    if not cfg.grid_res:
        return False
    if cfg.contract == "on" or cfg.random_background == "on":
        return True
    return cfg.random_background == "auto" and getattr(train, "alpha", None) is not None
