"""Cameras, camera paths and datasets."""

from .blender import load_blender
from .cameras import intrinsics_from_fov, look_at, orbit_views, spiral_path
from .datasets import load_dataset
from .nerfstudio import load_nerfstudio

__all__ = [
    "load_dataset",
    "load_blender",
    "load_nerfstudio",
    "look_at",
    "intrinsics_from_fov",
    "spiral_path",
    "orbit_views",
]
