"""Ground truth of the materials scene (its data README): the analytic spheres and ground disk
the scene was rendered from, points sampled on them, first hits along rays, the shape nearest to
a point and which surface points the cameras see. What geometry evaluation compares a run's
surface and rendered depth against (:mod:`warpnerf.train.geometry_eval`)."""

from __future__ import annotations

import math

import torch

__all__ = [
    "MATERIALS_SPHERES",
    "MATERIALS_RADIUS",
    "MATERIALS_DISK",
    "MATERIALS_BELOW",
    "MATERIALS_NAMES",
    "materials_reference",
    "sphere_depth",
    "materials_depth",
    "materials_shape_ids",
    "materials_signed_distances",
    "materials_visible",
]


# The materials scene's analytic geometry (its data README): 8 spheres of radius 0.32 at
# z = 0.32, x in {-1.05, -0.35, 0.35, 1.05}, y in {-0.4, 0.4}; a ground disk of radius 1.6 at z = 0.
MATERIALS_SPHERES = [(x, y, 0.32) for y in (-0.4, 0.4) for x in (-1.05, -0.35, 0.35, 1.05)]


MATERIALS_RADIUS, MATERIALS_DISK = 0.32, 1.6


# A closed SDF must give the infinitely thin disk some thickness: its underside (below this z)
# has no counterpart in the reference and is left out of the accuracy.
MATERIALS_BELOW = -0.1


def materials_reference(n: int, seed: int = 0):
    """n points uniformly (by area) on the materials scene's analytic spheres and disk [n, 3]."""
    import numpy as np

    rng = np.random.default_rng(seed)
    r0, rd = MATERIALS_RADIUS, MATERIALS_DISK
    a_sph, a_disk = 8 * 4 * math.pi * r0 * r0, math.pi * rd * rd
    n_s = int(n * a_sph / (a_sph + a_disk))
    d = rng.normal(size=(n_s, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sph = np.asarray(MATERIALS_SPHERES)[rng.integers(0, 8, n_s)] + r0 * d
    r, th = rd * np.sqrt(rng.random(n - n_s)), rng.random(n - n_s) * 2 * math.pi
    disk = np.stack([r * np.cos(th), r * np.sin(th), np.zeros_like(r)], 1)
    return np.concatenate([sph, disk]).astype(np.float32)


def sphere_depth(o: torch.Tensor, d: torch.Tensor, centers, radius: float) -> torch.Tensor:
    """Distance along unit rays to the first of the spheres, inf on a miss: the smallest
    positive root of |o + t d - c|^2 = r^2.

    Args:
        o: [n_rays, 3] origins (outside the spheres).
        d: [n_rays, 3] unit directions.
        centers: [k, 3] sphere centres.
        radius: their radius.

    Returns:
        t [n_rays].
    """
    t_best = torch.full(o.shape[:1], math.inf, dtype=o.dtype, device=o.device)
    for c in torch.as_tensor(centers, dtype=o.dtype).reshape(-1, 3).to(o.device):
        oc = o - c
        b = (oc * d).sum(-1)
        disc = b * b - (oc * oc).sum(-1) + radius * radius
        t = -b - torch.sqrt(disc.clamp_min(0))
        t_best = torch.where((disc > 0) & (t > 0) & (t < t_best), t, t_best)
    return t_best


def materials_depth(o: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Distance along unit rays [n_rays, 3] to the materials scene's first analytic surface (its
    spheres, or the ground disk z = 0 of radius 1.6), inf on a miss [n_rays]."""
    t_sph = sphere_depth(o, d, MATERIALS_SPHERES, MATERIALS_RADIUS)
    with torch.no_grad():
        t = -o[:, 2] / d[:, 2]  # (inf / nan for rays parallel to the disk: no hit below)
    p = o + t.unsqueeze(-1) * d
    hit = (t > 0) & (p[:, 0] ** 2 + p[:, 1] ** 2 <= MATERIALS_DISK**2)
    return torch.where(hit & (t < t_sph), t, t_sph)


# the shapes' names, the spheres in MATERIALS_SPHERES' order
MATERIALS_NAMES = ("gold", "copper", "aluminium", "red plastic", "blue plastic", "green diffuse",
                   "glass", "purple paint", "disk")  # fmt: skip


def materials_signed_distances(points):
    """[n, 9] signed distance from each point [n, 3] to each analytic shape, in
    :data:`MATERIALS_NAMES`' order: to a sphere |p - c| - r (negative inside); to the infinitely
    thin disk the distance to it, signed by the side (z: negative below)."""
    import numpy as np

    p = np.asarray(points, dtype=np.float64)
    c = np.asarray(MATERIALS_SPHERES)
    d_sph = np.linalg.norm(p[:, None] - c[None], axis=-1) - MATERIALS_RADIUS  # [n, 8]
    rho = np.linalg.norm(p[:, :2], axis=-1)
    d_disk = np.copysign(np.hypot(p[:, 2], np.maximum(rho - MATERIALS_DISK, 0.0)), p[:, 2])
    return np.concatenate([d_sph, d_disk[:, None]], 1)


def materials_shape_ids(points):
    """[n] index into :data:`MATERIALS_NAMES` of the analytic shape nearest to each point."""
    import numpy as np

    return np.argmin(np.abs(materials_signed_distances(points)), 1)


def materials_visible(points, c2w, intrinsics, width: int, height: int, chunk: int = 2048,
                      device="cpu"):  # fmt: skip
    """[n] bool: which analytic surface points [n, 3] of the materials scene at least one camera
    sees (c2w [k, 4, 4], OpenGL convention; intrinsics [k, 4] fx, fy, cx, cy in pixels of
    ``width`` x ``height`` images): the point projects into the image and no sphere nor the disk
    crosses the segment from the camera to it (up to 1e-4 of its length before the point). The
    analytic counterpart of DTU's observation masks: surface no training view shows (the disk
    under the spheres, their undersides) cannot be reconstructed from the images."""
    import numpy as np

    p = torch.as_tensor(np.asarray(points), dtype=torch.float64, device=device)
    cams = torch.as_tensor(np.asarray(c2w), dtype=torch.float64, device=device)[:, :3]
    k = torch.as_tensor(np.asarray(intrinsics), dtype=torch.float64, device=device)  # [k, 4]
    o = cams[:, :, 3]  # [k, 3]
    end = 1.0 - 1e-4
    seen = torch.zeros(len(p), dtype=torch.bool, device=device)
    for s in range(0, len(p), chunk):
        v = p[s : s + chunk][None] - o[:, None]  # [k, m, 3]: camera -> point, t in [0, 1]
        c = torch.einsum("kji,kmj->kmi", cams[:, :, :3], v)  # in the camera frame
        z = (-c[..., 2]).clamp_min(1e-12)
        u = k[:, None, 2] + k[:, None, 0] * c[..., 0] / z
        w = k[:, None, 3] - k[:, None, 1] * c[..., 1] / z
        ok = (c[..., 2] < 0) & (u >= 0) & (u <= width) & (w >= 0) & (w <= height)
        a = (v * v).sum(-1)
        for centre in MATERIALS_SPHERES:  # |o + t v - centre| = r for some t in (0, end)
            q = o[:, None] - torch.tensor(centre, dtype=torch.float64, device=device)
            b = (v * q).sum(-1)
            disc = b * b - a * ((q * q).sum(-1) - MATERIALS_RADIUS**2)
            r = disc.clamp_min(0).sqrt()
            t1, t2 = (-b - r) / a, (-b + r) / a
            hit = (disc > 0) & (((t1 > 0) & (t1 < end)) | ((t2 > 0) & (t2 < end)))
            ok &= ~hit
        vz = v[..., 2]
        t = -o[:, None, 2] / torch.where(vz.abs() > 1e-12, vz, torch.full_like(vz, 1e-12))
        x = o[:, None, :2] + t.unsqueeze(-1) * v[..., :2]
        ok &= ~((t > 0) & (t < end) & (x.norm(dim=-1) <= MATERIALS_DISK))
        seen[s : s + chunk] = ok.any(0)
    return seen.cpu().numpy()
