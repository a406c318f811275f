"""Cameras, camera paths and datasets."""

# The built-in folder formats register themselves in their own modules, as an added format does
# (docs/ARCHITECTURE.md), imported here in detection order: a folder with split files is Blender
# even when it also holds a COLMAP model. The built-in scene registers in data/synthetic.py
# (imported by the package); formats of outside packages come through the "warpnerf.formats"
# entry points, asked after these.
from . import blender  # noqa: F401, I001
from . import nerfstudio  # noqa: F401
from . import capture  # noqa: F401  (colmap, llff)
from .blender import load_blender
from .cameras import intrinsics_from_fov, look_at, orbit_views, spiral_path
from .dataset import Dataset, LoadRequest, holdout_indices, register_format
from .loading import FORMATS, detect_format, load_dataset
from .nerfstudio import load_nerfstudio

__all__ = [
    "Dataset",
    "LoadRequest",
    "load_dataset",
    "detect_format",
    "register_format",
    "holdout_indices",
    "FORMATS",
    "load_blender",
    "load_nerfstudio",
    "look_at",
    "intrinsics_from_fov",
    "spiral_path",
    "orbit_views",
]
