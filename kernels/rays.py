"""Pinhole ray generation and ray / axis-aligned-box intersection (pure Warp).

Cameras: intrinsics (fx, fy, cx, cy) in pixels, camera-to-world 4x4 in the OpenGL convention
(x right, y up, the camera looks down -z). The pixel (x, y) (x to the right, y down, pixel
centres at integer + 0.5) has the camera-space direction ((x - cx) / fx, -(y - cy) / fy, -1);
the world direction is R @ d and the origin the camera centre. Rays carry no gradient.
"""

from typing import Any

import warp as wp


@wp.kernel(enable_backward=False)
def generate_rays_fwd(
    c2w: wp.array3d(dtype=Any),  # [n_cams, 3|4, 4]
    intrinsics: wp.array2d(dtype=Any),  # [n_cams, 4] fx, fy, cx, cy
    use_grid: int,  # 1: every pixel of every camera in (cam, y, x) order; 0: the listed pixels
    width: int,
    height: int,
    cam_idx: wp.array(dtype=wp.int64),  # [n] (use_grid == 0)
    px: wp.array(dtype=Any),  # [n] continuous pixel coordinates (use_grid == 0)
    py: wp.array(dtype=Any),  # [n]
    normalize: int,
    origins: wp.array2d(dtype=Any),  # [n, 3] out
    directions: wp.array2d(dtype=Any),  # [n, 3] out
):
    tid = wp.tid()
    half = px.dtype(0.5)
    cam = 0
    x = px.dtype(0.0)
    y = px.dtype(0.0)
    if use_grid != 0:
        per_cam = width * height
        cam = tid // per_cam
        rem = tid - cam * per_cam
        row = rem // width
        x = px.dtype(rem - row * width) + half
        y = px.dtype(row) + half
    else:
        cam = int(cam_idx[tid])
        x = px[tid]
        y = py[tid]
    dx = (x - intrinsics[cam, 2]) / intrinsics[cam, 0]
    dy = -(y - intrinsics[cam, 3]) / intrinsics[cam, 1]
    dz = -px.dtype(1.0)
    wx = c2w[cam, 0, 0] * dx + c2w[cam, 0, 1] * dy + c2w[cam, 0, 2] * dz
    wy = c2w[cam, 1, 0] * dx + c2w[cam, 1, 1] * dy + c2w[cam, 1, 2] * dz
    wz = c2w[cam, 2, 0] * dx + c2w[cam, 2, 1] * dy + c2w[cam, 2, 2] * dz
    if normalize != 0:
        inv = px.dtype(1.0) / wp.sqrt(wx * wx + wy * wy + wz * wz)
        wx = wx * inv
        wy = wy * inv
        wz = wz * inv
    origins[tid, 0] = c2w[cam, 0, 3]
    origins[tid, 1] = c2w[cam, 1, 3]
    origins[tid, 2] = c2w[cam, 2, 3]
    directions[tid, 0] = wx
    directions[tid, 1] = wy
    directions[tid, 2] = wz


@wp.kernel(enable_backward=False)
def ray_aabb_fwd(
    origins: wp.array2d(dtype=Any),  # [n, 3]
    directions: wp.array2d(dtype=Any),  # [n, 3]
    aabb: wp.array(dtype=Any),  # [6] xmin, ymin, zmin, xmax, ymax, zmax
    t_clip: Any,  # lower bound on t (e.g. 0 or the camera's near plane)
    t_near: wp.array(dtype=Any),  # [n] out
    t_far: wp.array(dtype=Any),  # [n] out
    hit: wp.array(dtype=wp.bool),  # [n] out
):
    """Slab test. A zero direction component is handled exactly: the ray is inside that slab for
    every t (origin within [lo, hi]) or for none (origin outside), never 0 * inf = NaN. A tangent
    ray (t_near == t_far) counts as a hit with an empty interval. Misses get t_near = t_far =
    t_clip. A NaN anywhere makes the ray a miss with NaN bounds (never a plausible interval)."""
    tid = wp.tid()
    lo = t_clip
    hi = t_near.dtype(wp.inf)
    ok = True
    bad = False
    for a in range(3):
        o = origins[tid, a]
        d = directions[tid, a]
        bmin = aabb[a]
        bmax = aabb[a + 3]
        if d == t_near.dtype(0.0):
            if o < bmin or o > bmax:
                ok = False
        else:
            t1 = (bmin - o) / d
            t2 = (bmax - o) / d
            lo = wp.max(lo, wp.min(t1, t2))
            hi = wp.min(hi, wp.max(t1, t2))
        if wp.isnan(o) or wp.isnan(d):
            bad = True  # flagged, not folded into lo: CUDA's fmin/fmax drop NaN operands
    if bad:
        ok = False
        lo = t_near.dtype(wp.nan)
    if ok and lo <= hi:
        t_near[tid] = lo
        t_far[tid] = hi
        hit[tid] = True
    else:
        if not wp.isnan(lo):
            lo = t_clip
        t_near[tid] = lo
        t_far[tid] = lo
        hit[tid] = False


for _dt in (wp.float32, wp.float64):
    _a1 = wp.array(dtype=_dt)
    _a2 = wp.array2d(dtype=_dt)
    wp.overload(
        generate_rays_fwd,
        {
            "c2w": wp.array3d(dtype=_dt),
            "intrinsics": _a2,
            "px": _a1,
            "py": _a1,
            "origins": _a2,
            "directions": _a2,
        },
    )
    wp.overload(
        ray_aabb_fwd,
        {
            "origins": _a2,
            "directions": _a2,
            "aabb": _a1,
            "t_clip": _dt,
            "t_near": _a1,
            "t_far": _a1,
        },
    )
