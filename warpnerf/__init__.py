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
- :class:`OccupancyGrid`, :func:`march_rays` (packed marching through occupied cells),
  :func:`render_marched` (grid marching + early termination + compositing)
"""

from . import data
from .fields.encoding import HashEncoding, PositionalEncoding, SphericalHarmonics
from .fields.hash_nerf import HashNeRFField
from .fields.nerf import NeRFField
from .fields.sdf_volume import SDFVolume, laplace_cdf
from .metrics import psnr, ssim
from .occupancy import OccupancyGrid
from .ops import (
    HashGrid,
    Samples,
    generate_rays,
    hash_encode,
    importance_samples,
    packed_info_from_ray_indices,
    random_pixels,
    ray_aabb_intersect,
    render_dense,
    render_packed,
    stratified_samples,
)
from .ops.occupancy import march_rays
from .render import render_image, render_marched, render_nerf, render_rays, render_views

__version__ = "0.1.0"

__all__ = [
    "data",
    "generate_rays",
    "random_pixels",
    "ray_aabb_intersect",
    "stratified_samples",
    "importance_samples",
    "Samples",
    "render_packed",
    "render_dense",
    "packed_info_from_ray_indices",
    "SDFVolume",
    "laplace_cdf",
    "render_rays",
    "render_image",
    "render_views",
    "render_nerf",
    "PositionalEncoding",
    "NeRFField",
    "HashGrid",
    "hash_encode",
    "HashEncoding",
    "SphericalHarmonics",
    "HashNeRFField",
    "OccupancyGrid",
    "march_rays",
    "render_marched",
    "psnr",
    "ssim",
]
