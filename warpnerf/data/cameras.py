"""Pinhole cameras and camera paths (OpenGL camera-to-world: x right, y up, looking down -z)."""

from __future__ import annotations

import math

import torch

__all__ = ["look_at", "intrinsics_from_fov", "spiral_path", "orbit_views"]


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), dtype=torch.float32) -> torch.Tensor:
    """Camera-to-world [4, 4] of a camera at ``eye`` looking at ``target`` (OpenGL convention)."""
    eye = torch.as_tensor(eye, dtype=torch.float64)
    target = torch.as_tensor(target, dtype=torch.float64)
    up = torch.as_tensor(up, dtype=torch.float64)
    back = eye - target
    if float(back.norm()) == 0.0:
        raise ValueError("eye and target coincide")
    back = back / back.norm()
    right = torch.linalg.cross(up, back)
    if float(right.norm()) < 1e-9:  # looking along `up`: pick another up
        right = torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), back)
    right = right / right.norm()
    true_up = torch.linalg.cross(back, right)
    m = torch.eye(4, dtype=torch.float64)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, true_up, back, eye
    return m.to(dtype)


def intrinsics_from_fov(width: int, height: int, fov_x: float, dtype=torch.float32):
    """[4] (fx, fy, cx, cy) for a horizontal field of view in radians, square pixels, centred."""
    f = 0.5 * width / math.tan(0.5 * fov_x)
    return torch.tensor([f, f, 0.5 * width, 0.5 * height], dtype=dtype)


def spiral_path(
    n_frames: int,
    radius: float = 4.0,
    elevation=(15.0, 45.0),
    turns: float = 1.0,
    target=(0.0, 0.0, 0.0),
    dtype=torch.float32,
) -> torch.Tensor:
    """[n_frames, 4, 4] cameras circling ``target`` (z up) while the elevation (degrees) swings
    from the first value to the second and back."""
    mats = []
    for i in range(n_frames):
        s = i / max(n_frames, 1)
        az = 2.0 * math.pi * turns * s
        el = math.radians(
            elevation[0] + (elevation[1] - elevation[0]) * 0.5 * (1 - math.cos(2 * math.pi * s))
        )
        eye = (
            radius * math.cos(el) * math.cos(az),
            radius * math.cos(el) * math.sin(az),
            radius * math.sin(el),
        )
        eye = tuple(e + t for e, t in zip(eye, target))
        mats.append(look_at(eye, target, dtype=dtype))
    return torch.stack(mats)


def orbit_views(n_views: int, radius: float = 4.0, seed: int = 0, dtype=torch.float32):
    """[n_views, 4, 4] cameras spread over the upper and lower hemispheres (Fibonacci sphere),
    looking at the origin: a well-conditioned set of training views."""
    mats = []
    golden = math.pi * (3.0 - math.sqrt(5.0))
    for i in range(n_views):
        z = 1.0 - 2.0 * (i + 0.5) / n_views
        r = math.sqrt(max(1.0 - z * z, 0.0))
        th = golden * i + seed
        mats.append(
            look_at((radius * r * math.cos(th), radius * r * math.sin(th), radius * z), dtype=dtype)
        )
    return torch.stack(mats)
