"""Torch bridge for ray generation and ray/box intersection (kernels/rays.py). No gradients."""

from __future__ import annotations

import torch

from . import bridge

__all__ = ["generate_rays", "ray_aabb_intersect", "random_pixels"]


def _cameras(c2w, intrinsics):
    if c2w.dim() == 2:
        c2w = c2w.unsqueeze(0)
    if intrinsics.dim() == 1:
        intrinsics = intrinsics.unsqueeze(0)
    bridge.check_float("c2w", c2w, (None, None, 4))
    if c2w.shape[1] not in (3, 4):
        raise ValueError(f"c2w must have shape [n_cams, 3|4, 4], got {list(c2w.shape)}")
    n_cams = c2w.shape[0]
    bridge.check_float("intrinsics", intrinsics, (n_cams, 4), c2w.dtype, c2w.device)
    return c2w.contiguous(), intrinsics.contiguous()


def generate_rays(
    c2w: torch.Tensor,  # [n_cams, 3|4, 4] or [4, 4], OpenGL camera-to-world
    intrinsics: torch.Tensor,  # [n_cams, 4] or [4]: fx, fy, cx, cy in pixels
    width: int | None = None,
    height: int | None = None,
    *,
    cam_idx: torch.Tensor | None = None,  # [n] int
    px: torch.Tensor | None = None,  # [n] continuous pixel x (pixel centre = x + 0.5)
    py: torch.Tensor | None = None,  # [n]
    normalize: bool = True,
    check: bool = True,
):
    """Pinhole rays, either for every pixel or for a list of (camera, x, y) pixels.

    Every pixel (pass width and height): rays in (camera, row, column) order through pixel centres,
    ``origins, directions`` of shape [n_cams * height * width, 3]. A batch (pass cam_idx, px, py):
    one ray per entry, e.g. from :func:`random_pixels`. Direction in camera space
    ((x - cx) / fx, -(y - cy) / fy, -1), rotated by c2w; unit length if ``normalize``.

    ``cam_idx`` must be an int32/int64 tensor (IndexDtypeError, a TypeError and ValueError, for
    floats) with values in [0, n_cams) (ValueError): one reduction and one host sync per call on
    CUDA, which ``check=False`` skips for indices the caller drew itself (e.g. from
    :func:`random_pixels`; an index out of range then reads outside c2w).

    Returns:
        origins [n, 3], directions [n, 3] (no gradient).
    """
    from warpnerf.kernels import rays as K

    c2w, intrinsics = _cameras(c2w, intrinsics)
    dev, dt = c2w.device, c2w.dtype
    grid = cam_idx is None
    if grid:
        if px is not None or py is not None:
            raise ValueError("pass cam_idx together with px and py")
        if width is None or height is None:
            raise ValueError("width and height (positive) are needed to generate every pixel's ray")
        width = bridge.check_int("width", width, lo=1)
        height = bridge.check_int("height", height, lo=1)
        n = c2w.shape[0] * width * height
        if n > bridge.INT32_MAX:
            raise ValueError(f"n_cams * width * height = {n} rays exceed int32 indices")
        cam_idx = torch.empty(0, device=dev, dtype=torch.int64)
        px = py = torch.empty(0, device=dev, dtype=dt)
    else:
        if px is None or py is None:
            raise ValueError("pass px and py together with cam_idx")
        bridge.check_index("cam_idx", cam_idx, (None,))
        n = cam_idx.shape[0]
        if n > bridge.INT32_MAX:
            raise ValueError(f"{n} rays exceed int32 indices: generate fewer at once")
        bridge.check_float("px", px.to(dt), (n,), dt, dev)
        bridge.check_float("py", py.to(dt), (n,), dt, dev)
        cam_idx, px, py = cam_idx.to(dev, torch.int64), px.to(dt), py.to(dt)
        if check and n:
            lo, hi = torch.aminmax(cam_idx)
            lo_ok, hi_ok = bridge.host_flags(lo >= 0, hi < c2w.shape[0])  # one sync
            if not (lo_ok and hi_ok):
                raise ValueError(f"cam_idx must lie in [0, {c2w.shape[0]})")
        width = height = 0
    origins = torch.empty(n, 3, device=dev, dtype=dt)
    directions = torch.empty(n, 3, device=dev, dtype=dt)
    a = bridge.arr
    bridge.launch(
        K.generate_rays_fwd,
        n,
        [
            a(c2w),
            a(intrinsics),
            int(grid),
            int(width),
            int(height),
            a(cam_idx),
            a(px),
            a(py),
            int(normalize),
            a(origins),
            a(directions),
        ],
        dev,
    )
    return origins, directions


def random_pixels(
    n_cams: int, width: int, height: int, batch: int, generator=None, device="cpu",
    host_index: bool = False,
):  # fmt: skip
    """A uniform random batch of pixels across all images: cam_idx [batch] int64, px, py [batch]
    float32 at pixel centres, plus the flat pixel index [batch] (cam, row, column order); with
    ``host_index`` that last item is the pair (index on ``device``, the same on the host), for
    gathering from images kept in host memory. The indices are drawn on the host from
    ``generator`` (a CPU generator), so a batch is the same on every device.
    Sizes must be ints: n_cams, width, height >= 1 and batch >= 0 (ValueError otherwise)."""
    n_cams = bridge.check_int("n_cams", n_cams, lo=1)
    width = bridge.check_int("width", width, lo=1)
    height = bridge.check_int("height", height, lo=1)
    batch = bridge.check_int("batch", batch, lo=0, hi=2**62)
    if n_cams * width * height >= 2**62:
        raise ValueError(f"n_cams * width * height = {n_cams * width * height} pixels is too many")
    host = torch.randint(0, n_cams * width * height, (batch,), generator=generator, device="cpu")
    if torch.device(device).type == "cuda":  # (a pageable copy would synchronise the host)
        flat = host.pin_memory().to(device, non_blocking=True)
    else:
        flat = host.to(device)
    cam = flat // (width * height)
    rem = flat % (width * height)
    py = (rem // width).to(torch.float32) + 0.5
    px = (rem % width).to(torch.float32) + 0.5
    return cam, px, py, ((flat, host) if host_index else flat)


def ray_aabb_intersect(
    origins: torch.Tensor,  # [n, 3]
    directions: torch.Tensor,  # [n, 3]
    aabb,  # [6] xmin, ymin, zmin, xmax, ymax, zmax
    t_min: float = 0.0,
):
    """Exact slab intersection of rays with an axis-aligned box, clipped to t >= t_min.

    Axis-parallel rays (zero direction components) are exact, with no 0 * inf; tangent rays hit
    with t_near == t_far; misses return t_near = t_far = t_min and hit = False. A non-finite or
    inverted (min > max) box, or a NaN t_min, raises ValueError (a NaN box would report hits).

    Returns:
        t_near [n], t_far [n], hit [n] bool.
    """
    from warpnerf.kernels import rays as K

    bridge.check_float("origins", origins, (None, 3))
    n, dev, dt = origins.shape[0], origins.device, origins.dtype
    bridge.check_float("directions", directions, (n, 3), dt, dev)
    box = torch.as_tensor(aabb, dtype=dt).reshape(-1)  # checked where it is (host: no sync)
    if box.shape != (6,) or not bool(torch.isfinite(box).all() & (box[:3] <= box[3:]).all()):
        raise ValueError(
            "aabb must be 6 finite numbers [xmin, ymin, zmin, xmax, ymax, zmax] with min <= max"
        )
    if t_min != t_min:
        raise ValueError("t_min must not be NaN")
    box = bridge.constant(box.tolist(), dev, dt) if box.device.type == "cpu" else box.to(dev)
    t_near = torch.empty(n, device=dev, dtype=dt)
    t_far = torch.empty(n, device=dev, dtype=dt)
    hit = torch.empty(n, device=dev, dtype=torch.bool)
    a = bridge.arr
    bridge.launch(
        K.ray_aabb_fwd,
        n,
        [a(origins), a(directions), a(box), bridge.scalar(t_min, dt), a(t_near), a(t_far), a(hit)],
        dev,
    )
    return t_near, t_far, hit
