"""warpnerf: differentiable volume and surface rendering with NVIDIA Warp kernels and PyTorch.

Public API (torch tensors in and out, CPU or CUDA; nothing compiles at import):

- :func:`generate_rays`, :func:`random_pixels`, :func:`ray_aabb_intersect`
- :func:`stratified_samples` (dense or packed :class:`Samples`)
- :func:`render_packed`, :func:`render_dense` (emission-absorption compositing, exact backward)
- :func:`importance_samples` (coarse-to-fine inverse-CDF sampling, merged with the coarse edges)
- :class:`SDFVolume` (the analytic box/sphere/torus scene), :func:`render_rays` (rays -> image)
- :class:`NeRFField`, :class:`PositionalEncoding`, :func:`render_nerf`, :func:`psnr`, :func:`ssim`
- :class:`HashGrid`, :func:`hash_encode` (hash-grid encoding), :class:`HashEncoding`,
  :class:`SphericalHarmonics`, :class:`HashNeRFField` (the fast NeRF field)
- :class:`RadianceModel` (a run's fields and occupancy grid; ``warpnerf.fields.FIELDS`` registers
  fields by name)
- :class:`OccupancyGrid`, :func:`march_rays` (packed marching through occupied cells),
  :func:`render_marched` (grid marching + early termination + compositing)
"""

from . import data, ops
from .data import synthetic as _synthetic  # noqa: F401  (registers the built-in scene)
from .fields.encoding import HashEncoding, PositionalEncoding, SphericalHarmonics
from .fields.hash_nerf import HashNeRFField
from .fields.model import RadianceModel
from .fields.nerf import NeRFField
from .fields.sdf_volume import SDFVolume, laplace_cdf
from .metrics import psnr, ssim
from .occupancy import OccupancyGrid
from .ops import *  # noqa: F403  (the public ops: ops.__all__)
from .ops.occupancy import march_rays
from .render import render_image, render_marched, render_nerf, render_rays, render_views

__version__ = "0.1.0"

__all__ = [
    "data",
    *ops.__all__,
    "SDFVolume",
    "laplace_cdf",
    "render_rays",
    "render_image",
    "render_views",
    "render_nerf",
    "PositionalEncoding",
    "NeRFField",
    "HashEncoding",
    "SphericalHarmonics",
    "HashNeRFField",
    "RadianceModel",
    "OccupancyGrid",
    "march_rays",
    "render_marched",
    "psnr",
    "ssim",
]
