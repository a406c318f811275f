"""Fields (torch nn.Modules): the analytic SDF volume, encodings, NeRF's MLP and the hash field."""

# The built-in radiance fields register themselves in their own modules, as an added field does
# (docs/ARCHITECTURE.md); imported here in the order of --field's choices: mlp, hash, volsdf,
# hash_sdf. Fields of outside packages come through the "warpnerf.fields" entry points.
from . import nerf  # noqa: F401, I001  (mlp)
from . import hash_nerf  # noqa: F401  (hash)
from . import volsdf  # noqa: F401  (volsdf)
from . import hash_sdf  # noqa: F401  (hash_sdf)
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
