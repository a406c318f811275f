"""Cameras, camera paths and datasets."""

from .cameras import intrinsics_from_fov, look_at, orbit_views, spiral_path

__all__ = ["look_at", "intrinsics_from_fov", "spiral_path", "orbit_views"]
