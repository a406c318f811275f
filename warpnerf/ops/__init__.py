"""Torch bridge: one private autograd.Function per kernel family, behind a checking
public function."""

from .activations import softplus
from .composite import packed_info_from_ray_indices, render_dense, render_packed
from .distortion import distortion_loss
from .encoding import HashGrid, hash_encode
from .proposal import interlevel_loss, proposal_resample
from .rays import generate_rays, random_pixels, ray_aabb_intersect
from .sampling import Samples, importance_samples, stratified_samples

__all__ = [
    "generate_rays",
    "random_pixels",
    "ray_aabb_intersect",
    "stratified_samples",
    "importance_samples",
    "Samples",
    "render_packed",
    "render_dense",
    "packed_info_from_ray_indices",
    "distortion_loss",
    "proposal_resample",
    "interlevel_loss",
    "HashGrid",
    "hash_encode",
    "softplus",
]
