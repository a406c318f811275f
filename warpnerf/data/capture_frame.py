"""A real capture's frame (:mod:`warpnerf.data.capture`): the scene normalisation computed from
the camera poses (forward-facing: the mean pose becomes the identity, NDC rays; otherwise centred
on the viewing axes, cameras near radius 4), its application to poses and its inverse for points
(meshes back in world units), and the checks of the cameras before and after it."""

from __future__ import annotations

import numpy as np
import torch

from ..errors import UserError
from .cameras import MAX_CENTRE, check_intrinsics, check_poses
from .colmap import MAX_WORLD

__all__ = [
    "NDC_NEAR",
    "CAMERA_RADIUS",
    "FORWARD_FACING_DEGREES",
    "check_capture_cameras",
    "check_capture_scene",
    "check_undistortion",
    "scene_normalisation",
    "apply_transform",
    "normalised_to_world",
]


NDC_NEAR = 1.0


FORWARD_FACING_DEGREES = 45.0


CAMERA_RADIUS = 4.0


def _labels(sc: dict):
    """Names of a capture's cameras for messages: COLMAP image names, LLFF rows."""
    if sc.get("format") == "llff":
        return lambda i: f"row {i} ({sc['names'][i]})"
    return lambda i: f"image {sc['names'][i]!r}"


def check_capture_cameras(sc: dict):
    """The shared camera checks (:mod:`warpnerf.data.cameras`) on a capture's poses in world units
    (centres within ``MAX_WORLD``; rotations slightly off re-orthonormalised, with a warning) and
    on its intrinsics for the images read; COLMAP depth bounds and points finite and bounded."""
    labels = _labels(sc)
    check_intrinsics(sc["intrinsics"], sc["size"], sc["model"], labels)
    sc["c2w"] = check_poses(sc["c2w"], sc["model"], labels, max_centre=MAX_WORLD)
    b = sc["bounds"]
    if b is not None and not (np.isnan(b) | ((b > 0) & np.isfinite(b))).all():
        raise UserError(f"{sc['model']}: depth bounds must be finite and positive")


def check_capture_scene(sc: dict):
    """The normalised scene: camera centres within ``MAX_CENTRE``, 0 < near < far <= MAX_CENTRE,
    a finite box (else the capture is degenerate: all cameras at one point, absurd bounds)."""
    where = sc["model"]
    check_poses(sc["c2w_norm"], f"{where} (normalised)", _labels(sc))
    near, far, aabb = sc["near"], sc["far"], sc["aabb"]
    if not (0 < near < far <= MAX_CENTRE and 0 < aabb <= MAX_CENTRE):
        raise UserError(
            f"{where}: degenerate capture: normalised near {near:.3g}, far {far:.3g}, box "
            f"{aabb:.3g} (need 0 < near < far <= {MAX_CENTRE:g}); the cameras coincide or the "
            "depth bounds / sparse points are absurd"
        )


def check_undistortion(sc: dict):
    """Every border pixel of every distorted camera must undistort (the model must be invertible
    over the whole image), else a UserError now rather than NaN rays in training."""
    from .cameras import undistort_points

    w, h = sc["size"]
    u = torch.cat([torch.linspace(0, w, 64), torch.full((64,), float(w)), torch.zeros(64)])
    v = torch.cat([torch.zeros(64), torch.linspace(0, h, 64), torch.linspace(0, h, 64)])
    u, v = torch.cat([u, torch.linspace(0, w, 64)]), torch.cat([v, torch.full((64,), float(h))])
    for i in np.flatnonzero(np.abs(sc["distortion"]).max(1) > 0):
        k = sc["intrinsics"][i]
        try:
            undistort_points((u - k[2]) / k[0], (v - k[3]) / k[1], sc["distortion"][i])
        except ValueError as e:
            raise UserError(f"{sc['model']}: image {sc['names'][i]}: {e}") from None


def scene_normalisation(c2w: np.ndarray, bounds) -> tuple[np.ndarray, bool, float]:
    """(transform [4, 4] world -> normalised, forward_facing, scale) from the camera poses."""
    back = c2w[:, :3, 2]
    mean_back = back.mean(0)
    mean_back /= np.linalg.norm(mean_back)
    cos = np.clip(back @ mean_back, -1.0, 1.0)
    forward = bool(np.degrees(np.arccos(cos)).max() < FORWARD_FACING_DEGREES)
    centres = c2w[:, :3, 3]
    up = c2w[:, :3, 1].mean(0)
    if forward:  # mean pose -> identity, then NeRF's 1 / (0.75 * min near)
        z = mean_back
        x = np.cross(up, z)
        x /= np.linalg.norm(x)
        rot = np.stack([x, np.cross(z, x), z])  # rows: world -> camera-aligned axes
        centre = centres.mean(0)
        near = np.nanmin(bounds[:, 0]) if bounds is not None else None
        if near is None:  # no bounds: the cameras' spread sets the scale
            near = max(np.linalg.norm(centres - centre, axis=1).max(), 1e-6) * 10
        scale = 1.0 / (0.75 * near)
    else:  # centre on the viewing axes' closest point, +z up, cameras near radius 4
        fwd = -back
        proj = np.eye(3)[None] - fwd[:, :, None] * fwd[:, None, :]
        centre = np.linalg.lstsq(proj.sum(0), (proj @ centres[:, :, None]).sum(0), rcond=None)[0]
        centre = centre[:, 0]
        z = up / np.linalg.norm(up)
        x = np.cross(np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0, 0]), z)
        x /= np.linalg.norm(x)
        rot = np.stack([x, np.cross(z, x), z])
        dist = np.median(np.linalg.norm(centres - centre, axis=1))
        scale = CAMERA_RADIUS / max(dist, 1e-12)
    t = np.eye(4)
    t[:3, :3] = scale * rot
    t[:3, 3] = -scale * rot @ centre
    return t, forward, float(scale)


def apply_transform(transform: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """Camera-to-world poses [N, 4, 4] in the normalised frame (rotations stay orthonormal)."""
    scale = np.cbrt(np.linalg.det(transform[:3, :3]))
    out = transform @ c2w
    out[:, :3, :3] /= scale
    return out


def normalised_to_world(points, transform, ndc=None, near: float = NDC_NEAR) -> np.ndarray:
    """Points [n, 3] of the normalised frame (or of NDC space when ``ndc`` = (fx, fy, W, H) is
    given) back in the capture's world units: the inverse of the loaders' mapping. NDC points
    at z = 1 (infinity) come back non-finite; z > 1 is behind the camera."""
    p = np.asarray(points, dtype=np.float64)
    if ndc is not None:
        fx, fy, w, h = ndc
        with np.errstate(divide="ignore", invalid="ignore"):
            z = 2.0 * near / (p[:, 2] - 1.0)
            p = np.stack([p[:, 0] * z / (-2 * fx / w), p[:, 1] * z / (-2 * fy / h), z], -1)
    t = np.asarray(transform, dtype=np.float64)
    return (p - t[:3, 3]) @ np.linalg.inv(t[:3, :3]).T
