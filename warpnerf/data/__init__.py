"""Cameras, camera paths and datasets."""

from .blender import load_blender
from .cameras import intrinsics_from_fov, look_at, orbit_views, spiral_path
from .dataset import Dataset, LoadRequest, holdout_indices, register_format
from .datasets import FORMATS, detect_format, load_dataset
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
