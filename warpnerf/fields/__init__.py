"""Fields (torch nn.Modules): the analytic SDF volume, encodings, NeRF's MLP and the hash field."""

from .encoding import HashEncoding, PositionalEncoding, SphericalHarmonics
from .hash_nerf import HashNeRFField
from .model import (
    FIELDS,
    FieldTraits,
    RadianceModel,
    build_model,
    field_traits,
    fields_with,
    register_field,
)  # fmt: skip
from .nerf import NeRFField
from .sdf_volume import SDFVolume, laplace_cdf, sdf_box, sdf_sphere, sdf_torus

__all__ = [
    "SDFVolume",
    "laplace_cdf",
    "sdf_box",
    "sdf_sphere",
    "sdf_torus",
    "PositionalEncoding",
    "HashEncoding",
    "SphericalHarmonics",
    "NeRFField",
    "HashNeRFField",
    "RadianceModel",
    "FIELDS",
    "FieldTraits",
    "field_traits",
    "fields_with",
    "register_field",
    "build_model",
]
