"""Cameras, camera paths and datasets."""

from .blender import load_blender
from .cameras import intrinsics_from_fov, look_at, orbit_views, spiral_path

__all__ = ["load_blender", "look_at", "intrinsics_from_fov", "spiral_path", "orbit_views"]
