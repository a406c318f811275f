"""Fields (torch nn.Modules): analytic SDF volumes now; NeRF MLPs and neural SDFs later."""

from .sdf_volume import SDFVolume, laplace_cdf, sdf_box, sdf_sphere, sdf_torus

__all__ = ["SDFVolume", "laplace_cdf", "sdf_box", "sdf_sphere", "sdf_torus"]
