"""Pinhole cameras and camera paths (OpenGL camera-to-world: x right, y up, looking down -z)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import torch

from ..errors import UserError

__all__ = [
    "look_at", "camera_target", "intrinsics_from_fov", "spiral_path", "orbit_views",
    "frustum_bounds", "camera_rays",
]  # fmt: skip

# Limits every dataset loader applies to its cameras (check_poses, check_intrinsics):
MAX_CENTRE = 1e6  # |camera centre| in the units rays are made in (float32 rays)
ROTATION_EXACT = 1e-4  # max |R R^T - I| of a pose's rotation used as it is
ROTATION_FIX = 0.05  # up to this: replaced by the nearest rotation (SVD), with a warning
MAX_IMAGE_SIDE = 1 << 16  # pixels
MAX_FOCAL = 1e8  # pixels
MAX_TAN = 500.0  # tan of the widest ray's angle off the axis (about 89.9 degrees)
# ... and to the scene they are rendered in (check_scene_bounds; a run's near/far and box too):
MAX_DEPTH = 1e9  # near/far at most: float32 distances (a contracted scene's far, 1000 x its box)
MIN_EXTENT = 1e-3  # a scene box's half-size at least: below, its finest hash cell (2a / 2048)
# would be under the float32 spacing of positions at the cameras' distance (~5e-7 at 4)


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


def camera_target(c2w: torch.Tensor) -> torch.Tensor:
    """The point [3] (float64) nearest to all the cameras' optical axes (least squares): what a
    set of inward-facing cameras looks at. ``c2w`` [n, 3|4, 4], OpenGL."""
    c2w = torch.as_tensor(c2w).double().cpu()
    o, fwd = c2w[:, :3, 3], -c2w[:, :3, 2]
    eye = torch.eye(3, dtype=torch.float64)
    proj = eye - fwd.unsqueeze(-1) * fwd.unsqueeze(-2)
    return torch.linalg.lstsq(proj.sum(0), (proj @ o.unsqueeze(-1)).sum(0)).solution.squeeze(-1)


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


def undistort_points(xd: torch.Tensor, yd: torch.Tensor, dist, iters: int = 10):
    """Undistorted normalised image coordinates (x, y) of distorted ones, OpenCV's radial-
    tangential model with ``dist`` = (k1, k2, p1, p2) [4] or per point [n, 4]:

        x_d = x (1 + k1 r^2 + k2 r^4) + 2 p1 x y + p2 (r^2 + 2 x^2)   (y_d likewise)

    solved by Newton's method on the 2x2 Jacobian, in float64."""
    dt = xd.dtype
    xd, yd = xd.double(), yd.double()
    dist = torch.as_tensor(dist, dtype=torch.float64, device=xd.device)
    k1, k2, p1, p2 = dist.reshape(-1, 4).unbind(-1)
    x, y = xd.clone(), yd.clone()
    for _ in range(iters):
        r2 = x * x + y * y
        rad = 1 + k1 * r2 + k2 * r2 * r2
        fx = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd
        fy = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - yd
        drad = 2 * k1 + 4 * k2 * r2  # d rad / d(r^2) * 2
        a = rad + x * drad * x + 2 * p1 * y + 6 * p2 * x  # d fx / dx
        b = x * drad * y + 2 * p1 * x + 2 * p2 * y  # d fx / dy
        c = y * drad * x + 2 * p1 * x + 2 * p2 * y  # d fy / dx
        d = rad + y * drad * y + 6 * p1 * y + 2 * p2 * x  # d fy / dy
        det = a * d - b * c
        x, y = x - (d * fx - b * fy) / det, y - (a * fy - c * fx) / det
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2 * r2
    res = (x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd).abs() + (
        y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - yd
    ).abs()
    if bool((~(res < 1e-6)).any()):  # past the model's invertible range (or NaN)
        raise ValueError(
            f"undistortion did not converge for {int((~(res < 1e-6)).sum())} pixel(s) "
            f"(residual up to {float(res.nan_to_num(float('inf')).max()):.3g}): the distortion "
            "model is not invertible there; undistort the images with COLMAP instead"
        )
    return x.to(dt), y.to(dt)


def ndc_rays(origins, directions, ndc, near: float = 1.0):
    """NeRF's normalised device coordinates for forward-facing scenes: the frustum z in
    [-inf, -near] of the camera ``ndc`` = (fx, fy, W, H) maps to the cube [-1, 1]^3 (z = 1 at
    infinity). Rays start on the near plane; returns origins [n, 3] and unit directions [n, 3]
    in NDC space (distances along them are NDC lengths, not world lengths)."""
    fx, fy, w, h = (float(v) for v in ndc)
    o, d = origins, directions
    t = -(near + o[:, 2]) / d[:, 2]
    o = o + t[:, None] * d
    ax, ay = -2.0 * fx / w, -2.0 * fy / h
    oz = o[:, 2]
    o_ndc = torch.stack([ax * o[:, 0] / oz, ay * o[:, 1] / oz, 1.0 + 2.0 * near / oz], -1)
    d_ndc = torch.stack(
        [
            ax * (d[:, 0] / d[:, 2] - o[:, 0] / oz),
            ay * (d[:, 1] / d[:, 2] - o[:, 1] / oz),
            -2.0 * near / oz,
        ],
        -1,
    )
    return o_ndc, torch.nn.functional.normalize(d_ndc, dim=-1)


def camera_rays(
    c2w,  # [n_cams, 3|4, 4] or [4, 4], OpenGL camera-to-world
    intrinsics,  # [n_cams, 4] or [4]
    width: int | None = None,
    height: int | None = None,
    *,
    cam_idx=None,  # [n] (a batch of pixels) or None (every pixel)
    px=None,  # [n] continuous pixel x of the (distorted) image
    py=None,  # [n]
    distortion=None,  # [n_cams, 4] (k1, k2, p1, p2) or None
    ndc=None,  # (fx, fy, W, H) of the NDC camera, or None
    check: bool = True,
):
    """Rays of dataset pixels: :func:`warpnerf.ops.generate_rays` after undistorting the pixel
    positions (when ``distortion`` is non-zero), then mapped to NDC (when ``ndc`` is given).
    ``check=False`` skips the range check of ``cam_idx`` (a host sync on CUDA) for indices the
    caller drew itself (a training batch from :func:`warpnerf.ops.random_pixels`).
    Returns origins [n, 3], unit directions [n, 3]."""
    from ..ops import generate_rays

    undistort = distortion is not None and bool(torch.as_tensor(distortion).abs().max() > 0)
    if not undistort:
        o, d = generate_rays(
            c2w, intrinsics, width, height, cam_idx=cam_idx, px=px, py=py, check=check
        )
    else:
        k = intrinsics if intrinsics.dim() == 2 else intrinsics[None]
        dist = torch.as_tensor(distortion, device=k.device)
        dist = dist if dist.dim() == 2 else dist[None]
        if cam_idx is None:  # every pixel of every camera, (camera, row, column) order
            n_cams = k.shape[0]
            ys, xs = torch.meshgrid(
                torch.arange(height, device=k.device, dtype=k.dtype) + 0.5,
                torch.arange(width, device=k.device, dtype=k.dtype) + 0.5,
                indexing="ij",
            )
            cam_idx = torch.arange(n_cams, device=k.device).repeat_interleave(width * height)
            px, py = xs.reshape(-1).repeat(n_cams), ys.reshape(-1).repeat(n_cams)
        kk = k[cam_idx]
        x, y = undistort_points(
            (px - kk[:, 2]) / kk[:, 0], (py - kk[:, 3]) / kk[:, 1], dist[cam_idx]
        )
        px, py = x * kk[:, 0] + kk[:, 2], y * kk[:, 1] + kk[:, 3]
        o, d = generate_rays(c2w, intrinsics, cam_idx=cam_idx, px=px, py=py, check=check)
    if ndc is not None:
        o, d = ndc_rays(o, d, ndc)
    return o, d


def forward_facing_spiral(c2w, n_frames: int, focus: float = 4.0, rots: float = 2.0):
    """[n_frames, 4, 4] cameras for a forward-facing capture normalised so that the mean camera
    looks down -z from the origin (as the NeRF paper's render path): an ellipse through the 90th
    percentile of the cameras' |x|, |y|, |z| offsets, ``rots`` turns, all looking at (0, 0,
    -focus)."""
    c2w = torch.as_tensor(c2w, dtype=torch.float64).cpu()
    rads = c2w[:, :3, 3].abs().quantile(0.9, dim=0).clamp_min(1e-3)
    mats = []
    for i in range(n_frames):
        th = 2 * math.pi * rots * i / max(n_frames, 1)
        eye = torch.tensor([math.cos(th), -math.sin(th), -math.sin(0.5 * th)]) * rads
        mats.append(look_at(eye, (0.0, 0.0, -focus), up=(0.0, 1.0, 0.0)))
    return torch.stack(mats)


def _label(labels, i: int) -> str:
    if labels is None:
        return f"camera {i}"
    return labels(i) if callable(labels) else str(labels[i])


def check_poses(c2w, where, labels=None, max_centre: float = MAX_CENTRE) -> np.ndarray:
    """Camera-to-world poses [N, 4, 4] (or [N, 3, 4]) checked where a loader reads them; returns a
    float64 copy (rotations slightly off re-orthonormalised). UserError naming ``where`` (the file)
    and the camera (``labels[i]`` or ``labels(i)``) otherwise.

    - every value finite;
    - the rotation R (upper-left 3x3) orthonormal with determinant +1: up to ``ROTATION_EXACT``
      of max |R R^T - I| (float32 round-off, rounded decimals) it is used as it is; up to
      ``ROTATION_FIX`` it is replaced by the nearest rotation (U V^T of its SVD) with a
      UserWarning; beyond that, or det R <= 0 (mirrored, zero, rank-deficient), it is refused;
    - the camera centre within ``max_centre`` of the origin.
    """
    c2w = np.array(c2w, dtype=np.float64)
    finite = np.isfinite(c2w).all(axis=(1, 2))
    if not finite.all():
        i = int(np.argmin(finite))
        raise UserError(f"{where}: {_label(labels, i)}: the pose has non-finite values")
    r = c2w[:, :3, :3]
    with np.errstate(all="ignore"):
        err = np.abs(r @ r.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2), initial=0.0)
        det = np.linalg.det(r) if len(r) else np.zeros(0)
    bad = ~(err <= ROTATION_FIX) | ~(det > 0)
    if bad.any():
        i = int(np.argmax(bad))
        raise UserError(
            f"{where}: {_label(labels, i)}: the pose's 3x3 part is not a rotation "
            f"(max |R R^T - I| = {err[i]:.3g}, det = {det[i]:.3g}; need orthonormal axes with "
            f"determinant +1, off by at most {ROTATION_FIX}: a degenerate, scaled or mirrored "
            "matrix is refused)"
        )
    fix = err > ROTATION_EXACT
    if fix.any():
        u, _, vt = np.linalg.svd(r[fix])
        c2w[fix, :3, :3] = u @ vt
        i = int(np.argmax(err))
        warnings.warn(
            f"{where}: {int(fix.sum())} pose rotation(s) slightly off orthonormal (up to "
            f"{err[i]:.2g}, {_label(labels, i)}); replaced by the nearest rotation",
            UserWarning,
            stacklevel=2,
        )
    with np.errstate(over="ignore"):
        dist = np.linalg.norm(c2w[:, :3, 3], axis=1)
    far = ~(dist <= max_centre)
    if far.any():
        i = int(np.argmax(far))
        raise UserError(
            f"{where}: {_label(labels, i)}: camera centre {c2w[i, :3, 3].tolist()} is "
            f"{dist[i]:.3g} from the origin, more than the {max_centre:g} allowed (wrong units or "
            "a corrupt pose)"
        )
    return c2w


def scene_bounds_problem(near, far, aabb, inner=None) -> tuple[str, str] | None:
    """What is wrong with a scene's depth range and box: (the value's name, the rule it breaks:
    "must be ..."), or None. The one rule for an exported capture's ``warpnerf_scene`` and a
    run's saved ``scene``: finite numbers with 0 <= near < far <= :data:`MAX_DEPTH`; the box's
    half-size ``aabb`` and the contracted scene's inner cube ``inner`` (None: absent) in
    [:data:`MIN_EXTENT`, :data:`MAX_CENTRE`]."""
    values = {"near": near, "far": far, "aabb": aabb, "inner": inner}
    for name, v in values.items():
        if (v is not None or name != "inner") and not (
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        ):
            return name, f"must be a finite number, got {v!r}"[:200]
    if not 0 <= near < far <= MAX_DEPTH:
        return "far", (f"must satisfy 0 <= near < far <= {MAX_DEPTH:g}, got near {near:g}, "
                       f"far {far:g}")  # fmt: skip
    for name in ("aabb", "inner"):
        v = values[name]
        if v is not None and not MIN_EXTENT <= v <= MAX_CENTRE:
            return name, (f"must be in [{MIN_EXTENT:g}, {MAX_CENTRE:g}] (a half-size of the "
                          f"scene's box), got {v:g}")  # fmt: skip
    return None


def check_intrinsics(intrinsics, size, where, labels=None) -> None:
    """UserError naming ``where`` and the camera unless the image ``size`` (w, h) is positive and
    at most ``MAX_IMAGE_SIDE`` pixels a side, and each camera's (fx, fy, cx, cy) [N, 4] (pixels)
    is finite with 0 < fx, fy <= ``MAX_FOCAL`` and a field of view below about 179.8 degrees (the
    image corners at most ``MAX_TAN`` focal lengths off the principal point)."""
    w, h = size
    if not all(isinstance(v, (int, np.integer)) and 1 <= v <= MAX_IMAGE_SIDE for v in (w, h)):
        raise UserError(
            f"{where}: image size {w}x{h} must be positive whole pixels, at most {MAX_IMAGE_SIDE} "
            "a side"
        )
    k = np.asarray(intrinsics, dtype=np.float64).reshape(-1, 4)
    for i, (fx, fy, cx, cy) in enumerate(k):
        what = f"{where}: {_label(labels, i)}"
        if not all(math.isfinite(v) for v in (fx, fy, cx, cy)):
            raise UserError(f"{what}: intrinsics (fx, fy, cx, cy) = {k[i].tolist()} not finite")
        if not (0 < fx <= MAX_FOCAL and 0 < fy <= MAX_FOCAL):
            raise UserError(
                f"{what}: focal lengths (fx, fy) = ({fx:g}, {fy:g}) must be positive and at most "
                f"{MAX_FOCAL:g} pixels"
            )
        tan = max(max(abs(cx), abs(w - cx)) / fx, max(abs(cy), abs(h - cy)) / fy)
        if not tan <= MAX_TAN:
            deg = 2 * math.degrees(math.atan(tan))
            raise UserError(
                f"{what}: field of view too wide ({deg:.6g} degrees across; at most "
                f"{2 * math.degrees(math.atan(MAX_TAN)):.4g}): (fx, fy, cx, cy) = "
                f"{k[i].tolist()} for a {w}x{h} image"
            )


_EDGE_SAMPLES = 257  # points per image edge whose undistorted rays bound a distorted camera


def frustum_bounds(intrinsics, width: int, height: int, distortion=None) -> torch.Tensor:
    """[N, 4] float64 (x_lo, x_hi, y_lo, y_hi): each camera's image [0, W] x [0, H] (pixel
    edges) as the tangents ``x / d``, ``y / d`` of its rays in camera space (y up, d the depth
    along -z): ``x_lo = -cx / fx``, ``x_hi = (W - cx) / fx``, ``y_lo = -(H - cy) / fy``,
    ``y_hi = cy / fy``. With ``distortion`` [N, 4] (k1, k2, p1, p2): the extremes of the
    undistorted rays through the image's border (sampled densely, widened by the largest step
    between neighbouring samples)."""
    k = torch.as_tensor(intrinsics).reshape(-1, 4).double()
    fx, fy, cx, cy = k.unbind(-1)
    w, h = float(width), float(height)
    if distortion is None or not bool(torch.as_tensor(distortion).abs().max() > 0):
        return torch.stack([-cx / fx, (w - cx) / fx, -(h - cy) / fy, cy / fy], -1)
    t = torch.linspace(0, 1, _EDGE_SAMPLES, dtype=torch.float64, device=k.device)
    z, o = torch.zeros_like(t), torch.ones_like(t)
    px = torch.cat([t * w, t * w, z, o * w])  # the four edges, each in order along it
    py = torch.cat([z, o * h, t * h, t * h])
    n, m = k.shape[0], px.shape[0]
    dist = torch.as_tensor(distortion, dtype=torch.float64, device=k.device).reshape(-1, 4)
    x, y = undistort_points(((px - cx[:, None]) / fx[:, None]).reshape(-1),
                            ((py - cy[:, None]) / fy[:, None]).reshape(-1),
                            dist.repeat_interleave(m, 0))  # fmt: skip
    x, y = x.reshape(n, 4, -1), -y.reshape(n, 4, -1)  # (y up)
    slack = torch.maximum(x.diff(dim=-1).abs().amax((1, 2)), y.diff(dim=-1).abs().amax((1, 2)))
    x, y = x.reshape(n, -1), y.reshape(n, -1)
    return torch.stack([x.amin(-1) - slack, x.amax(-1) + slack, y.amin(-1) - slack,
                        y.amax(-1) + slack], -1)  # fmt: skip
