"""Pure-PyTorch twins of every Warp op, same names and signatures (for tests and benchmarks)."""

from .activations import softplus
from .composite import render_dense, render_packed
from .distortion import distortion_loss
from .encoding import hash_encode
from .proposal import interlevel_loss, proposal_resample
from .rays import generate_rays, ray_aabb_intersect
from .sampling import stratified_samples

__all__ = [
    "generate_rays",
    "ray_aabb_intersect",
    "stratified_samples",
    "render_dense",
    "render_packed",
    "distortion_loss",
    "proposal_resample",
    "interlevel_loss",
    "hash_encode",
    "softplus",
]
