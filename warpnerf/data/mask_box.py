"""How large a scene box RGBA images ask for. A Blender-format scene's box is [-1.5, 1.5]^3 by
convention (the NeRF synthetic scenes fit in it); an object that reaches past it (the materials
scene's ground disk, radius 1.6) is cut off by the field's box and rendered as background there.
Every opaque pixel (alpha >= 1/2) shows something its ray meets between near and far, so the box
must reach that ray: the smallest origin-centred cube a ray enters is min over t of
|o + t d|_inf (convex in t), and the box the images ask for is the largest of these over the
opaque pixels. A lower bound of the object's reach (the thing may lie deeper along the ray), with
no guess where the cameras cannot carve (:func:`warpnerf.train.nerf_run.box_from_alpha`)."""

from __future__ import annotations

import torch

__all__ = ["OPAQUE", "SILHOUETTE", "ray_reach", "opaque_reach", "shows_silhouette"]

OPAQUE = 0.5  # alpha from which a pixel counts as showing the object
SILHOUETTE = 0.01  # shows_silhouette: transparent pixels at least this fraction of a split's
_CHUNK = 1 << 20  # opaque pixels' rays at once
_ITERS = 60  # ternary-search steps (the interval shrinks by (2/3)^60 ~ 3e-11)


def ray_reach(o, d, near: float, far: float):
    """[n] min over t in [near, far] of |o + t d|_inf for rays o, d [n, 3] (float64): the
    half-size of the smallest origin-centred cube each ray enters within its depth range."""
    lo = torch.full(o.shape[:1], float(near), dtype=o.dtype, device=o.device)
    hi = torch.full_like(lo, float(far))

    def f(t):
        return (o + t[:, None] * d).abs().amax(-1)

    for _ in range(_ITERS):  # (a convex function of t: ternary search)
        m1, m2 = lo + (hi - lo) / 3, hi - (hi - lo) / 3
        left = f(m1) < f(m2)
        hi, lo = torch.where(left, m2, hi), torch.where(left, lo, m1)
    return f(0.5 * (lo + hi))


def _opaque(alpha):
    """bool mask of the opaque pixels (alpha >= :data:`OPAQUE`; uint8 alpha counts 255 as 1)."""
    scale = 255.0 if alpha.dtype == torch.uint8 else 1.0
    return alpha.float() >= OPAQUE * scale


def shows_silhouette(alpha) -> bool:
    """Whether a split's alpha [N, H, W] outlines an object: at least :data:`SILHOUETTE` of its
    pixels transparent (alpha < 1/2). Opaque images (a background rendered in, RGB saved as
    RGBA) bound nothing: their box stays the convention's."""
    clear = sum(int((~_opaque(a)).sum()) for a in alpha)
    return clear >= SILHOUETTE * alpha.numel()


def opaque_reach(c2w, intrinsics, alpha, near: float, far: float, box: float) -> float:
    """The half-size of the smallest origin-centred cube that every opaque pixel's ray enters
    between ``near`` and ``far``, at least ``box``. ``c2w`` [N, 4, 4] (OpenGL), ``intrinsics``
    [N, 4] (fx, fy, cx, cy in pixels of ``alpha``), ``alpha`` [N, H, W] (float in [0, 1] or
    uint8). Rays whose closest point to the origin lies inside the ``box`` cube cannot ask for
    more and are skipped (most of them), the others searched exactly (:func:`ray_reach`)."""
    from .cameras import camera_rays

    if alpha.dim() != 3 or not alpha.shape[0] == c2w.shape[0] == intrinsics.shape[0]:
        raise ValueError("alpha [N, H, W], c2w [N, 4, 4] and intrinsics [N, 4] must agree in N")
    h, w = alpha.shape[1:]
    reach = float(box)
    for k in range(alpha.shape[0]):
        ys, xs = torch.nonzero(_opaque(alpha[k]), as_tuple=True)
        if ys.numel() == 0:
            continue
        dev = c2w.device
        for a in range(0, ys.numel(), _CHUNK):  # (bounded memory for large images)
            y, x = ys[a : a + _CHUNK].to(dev), xs[a : a + _CHUNK].to(dev)
            cam = torch.full(y.shape, k, dtype=torch.int64, device=dev)
            o, d = camera_rays(c2w, intrinsics, w, h, cam_idx=cam, px=x.float() + 0.5,
                               py=y.float() + 0.5)  # fmt: skip
            o, d = o.double(), d.double()
            t = (-(o * d).sum(-1) / (d * d).sum(-1)).clamp(float(near), float(far))
            bound = (o + t[:, None] * d).abs().amax(-1)  # (|o + t d|_inf at one t: >= the min)
            ask = bound > reach
            if ask.any():
                reach = max(reach, float(ray_reach(o[ask], d[ask], near, far).max()))
    return reach
