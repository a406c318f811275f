"""Mesh extraction (Warp's marching cubes, CPU and CUDA), the density level of a NeRF's mesh,
vertex colours, surface sampling and pyvista screenshots. PLY files: :mod:`warpnerf.ply`;
cleaning and culling: :mod:`warpnerf.mesh_clean` (both re-exported here).

``extract_mesh(field_fn, lower, upper, resolution, level)`` samples ``field_fn(points [m, 3]) ->
values [m]`` on a regular grid of ``resolution^3`` nodes spanning [lower, upper] (world
coordinates), in chunks, and runs marching cubes at ``level``: 0 for signed distances, a density
threshold for NeRFs (by default chosen from the grid by :func:`density_level`). Vertices come
back in world coordinates.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import warnings

import numpy as np
import torch

from . import mesh_clean
from .mesh_clean import *  # noqa: F403  (re-exported: mesh_clean.__all__)
from .outputs import atomic_path
from .ply import MAX_PLY_BYTES, read_ply, read_ply_points, write_ply

__all__ = [
    "extract_mesh",
    "density_level",
    "level_hint",
    "write_ply",
    "read_ply",
    "read_ply_points",
    "MAX_PLY_BYTES",
    "vertex_colors",
    "screenshot",
    "sample_surface",
    *mesh_clean.__all__,
]


@torch.no_grad()
def extract_mesh(field_fn, lower, upper, resolution: int, level: float = 0.0, device="cpu",
                 chunk: int = 1 << 18, return_values: bool = False):  # fmt: skip
    """(vertices [V, 3] float32 numpy, faces [F, 3] int32 numpy) of the level set; with
    ``return_values`` also the field's values on the grid (float32 tensor [resolution^3] on
    ``device``), e.g. for :func:`level_hint` when there is no surface. ``level``: a number, or
    a callable given those values that returns the level to march (chosen from the grid, e.g.
    with :func:`density_level`)."""
    import warp as wp

    from .ops.bridge import load_warp

    if resolution < 2:
        raise ValueError(f"resolution must be >= 2, got {resolution}")
    lo = torch.as_tensor(lower, dtype=torch.float32).reshape(3)
    hi = torch.as_tensor(upper, dtype=torch.float32).reshape(3)
    if not bool((hi > lo).all()):
        raise ValueError("upper must exceed lower on every axis")
    dev = torch.device(device)
    axes = [torch.linspace(float(lo[i]), float(hi[i]), resolution, device=dev) for i in range(3)]
    n = resolution**3
    vals = torch.empty(n, device=dev)
    for s in range(0, n, chunk):  # grid points made per chunk: memory ~ chunk, not resolution^3
        idx = torch.arange(s, min(s + chunk, n), device=dev)
        ix, iy, iz = (
            idx // (resolution * resolution),
            (idx // resolution) % resolution,
            idx % resolution,
        )
        pts = torch.stack([axes[0][ix], axes[1][iy], axes[2][iz]], -1)
        vals[s : s + len(idx)] = field_fn(pts).float().reshape(-1)
    if not bool(torch.isfinite(vals).all()):
        raise ValueError("the field has NaN/Inf values on the grid")
    if callable(level):
        level = level(vals)
    field = vals.reshape(resolution, resolution, resolution).contiguous()
    load_warp()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        verts, tris = wp.MarchingCubes.extract(
            wp.from_torch(field, dtype=wp.float32),
            float(level),
            lower=wp.vec3(*lo.tolist()),
            upper=wp.vec3(*hi.tolist()),
        )
    v = verts.numpy().reshape(-1, 3).astype(np.float32)
    f = tris.numpy().reshape(-1, 3).astype(np.int32)
    return (v, f, vals) if return_values else (v, f)


LEVEL_OPACITY = 0.5  # density_level: where a ray is this opaque (its median depth)
LEVEL_REACHED = 0.9  # density_level: the share of the opaque rays whose peak density it keeps
LEVEL_DIRECTIONS = 32  # density_level: directions of the parallel rays (a Fibonacci sphere)
LEVEL_RAYS = 32  # density_level: rays per side of each direction's square bundle
LEVEL_SAMPLES = 256  # density_level: samples per ray, over the box's diagonal


def _quantile(x: torch.Tensor, q: float) -> float:
    """The ``q`` quantile of a 1-D tensor, the lower of two values (kthvalue: no size limit)."""
    return float(x.kthvalue(max(1, math.ceil(q * len(x))))[0])


def _fibonacci_directions(n: int) -> torch.Tensor:
    """[n, 3] unit vectors spread evenly over the sphere (none along an axis for n > 2)."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = (1.0 - z * z).clamp_min(0).sqrt()
    th = math.pi * (3.0 - math.sqrt(5.0)) * i
    return torch.stack([r * th.cos(), r * th.sin(), z], -1).float()


@torch.no_grad()
def density_level(densities, resolution: int, lower, upper) -> tuple:
    """The density level that meshes a NeRF where it renders its surface, without holes where
    it renders opaque: (level, why), ``why`` a phrase saying how it was found.

    The grid's densities are composited along parallel rays through the box, as a renderer
    does: :data:`LEVEL_DIRECTIONS` directions spread over the sphere (not along the grid's axes,
    whose rays would graze the faces of axis-aligned objects), a square bundle of
    :data:`LEVEL_RAYS` x :data:`LEVEL_RAYS` rays each, :data:`LEVEL_SAMPLES` samples over the
    box's diagonal read by trilinear interpolation (no new evaluation of the field), optical
    depth by the trapezoidal rule. Of the rays that reach opacity :data:`LEVEL_OPACITY`
    (optical depth ln 2, the ray's median depth: where rendering puts the surface it sees), two
    figures: ``a``, the median density where they reach it (interpolated between samples), and
    ``b``, the largest density that :data:`LEVEL_REACHED` (90 %) of them reach somewhere (the
    10th percentile of their peaks). The level is min(a, b): the depth the run renders, lowered
    where that would let more than a tenth of the rays it finds opaque through the mesh
    (holes). No ray that opaque (a faint field): half the largest density.

    Measured on the built-in scene (the mesh culled and cleaned as `warpnerf mesh` delivers it;
    Chamfer: the mean of the mean |true SDF| at the vertices and the mean distance from the
    analytic surface to the mesh; 128^3 grid): the `--preset cpu` hash run (densities peak at
    22, 7.6 median on the true surface) at levels 4 .. 7 had Chamfer 0.042 .. 0.047 and the
    95th percentile of the surface's distance to the mesh 0.06 at 4, 0.11 at 5, 0.17 at 6, 0.27
    at the former fixed 10 (Chamfer 0.063: a holed sphere, the box in pieces); the mlp run
    (peak 5): Chamfer 0.048 and 0.07 at 2.45, 0.13 at 2.62, 0.56 at 3, no surface at 10. This
    rule gives a = 6.9, b = 4.8 (hash; 7.0 and 4.9 on the default 256^3 grid, whose mesh has
    mean |SDF| 0.048, completeness 0.036, 95th percentile 0.087, 2 pieces) and a = 2.67,
    b = 2.50 (mlp); on the scene's own density (Laplace, beta 0.02: 25 on the surface; 64^3)
    a = 20.5, b = 12.4, mean |SDF| 0.017 at the vertices. Rejected: ln 2 / march step (opacity
    0.5 over one step: 51 for the hash run, no surface), half the largest density (11: holes),
    and rays along the grid's axes (b = 5.0 on the scene's own density: rays grazing the box's
    faces).

    Args:
        densities: the densities on the grid, [resolution^3] (x slowest, as
            :func:`extract_mesh` samples them), any device.
        resolution: grid nodes per axis.
        lower, upper: the grid's corners.
    """
    import torch.nn.functional as F

    r = int(resolution)
    d = torch.as_tensor(densities).detach().reshape(r, r, r).float()
    dev = d.device
    lo = torch.as_tensor(lower, dtype=torch.float32).reshape(3).to(dev)
    hi = torch.as_tensor(upper, dtype=torch.float32).reshape(3).to(dev)
    center, size = (lo + hi) / 2, hi - lo
    diag = float(size.norm())
    ts = torch.linspace(-diag / 2, diag / 2, LEVEL_SAMPLES, device=dev)
    h = diag / (LEVEL_SAMPLES - 1)
    side = torch.linspace(-diag / 2, diag / 2, LEVEL_RAYS, device=dev)
    across = torch.stack(torch.meshgrid(side, side, indexing="ij"), -1).reshape(-1, 2)
    grid = d[None, None]  # grid_sample's [N, C, D, H, W]: D = x, H = y, W = z
    target = -math.log(1.0 - LEVEL_OPACITY)
    at, peak = [], []  # per opaque ray: the density where it reaches the opacity, its peak
    for v in _fibonacci_directions(LEVEL_DIRECTIONS).to(dev):
        helper = torch.tensor([1.0, 0.0, 0.0] if abs(float(v[0])) < 0.9 else [0.0, 1.0, 0.0],
                              device=dev)  # fmt: skip
        u = F.normalize(torch.linalg.cross(v, helper), dim=0)
        w = torch.linalg.cross(v, u)
        o = center + across[:, :1] * u + across[:, 1:] * w  # [R, 3]
        p = o[:, None, :] + ts[None, :, None] * v  # [R, S, 3]
        q = 2.0 * (p - lo) / size - 1.0  # [-1, 1] over the box
        sig = F.grid_sample(grid, q.flip(-1)[None, None], align_corners=True)[0, 0, 0]  # [R, S]
        c = torch.cumsum(sig, -1)
        tau = h * (c - 0.5 * (sig[:, :1] + sig))  # trapezoid from the first sample
        hit = tau[:, -1] >= target
        if not bool(hit.any()):
            continue
        sig, tau = sig[hit], tau[hit]
        i = (tau >= target).int().argmax(-1, keepdim=True).clamp_min(1)
        t0, t1 = tau.gather(1, i - 1), tau.gather(1, i)
        s0, s1 = sig.gather(1, i - 1), sig.gather(1, i)
        f = ((target - t0) / (t1 - t0).clamp_min(1e-30)).clamp(0, 1)
        at.append((s0 + f * (s1 - s0)).reshape(-1))
        peak.append(sig.amax(-1))
    if at:
        a = _quantile(torch.cat(at), 0.5)
        b = _quantile(torch.cat(peak), 1.0 - LEVEL_REACHED)
        n = sum(len(x) for x in at)
        if min(a, b) > 0:
            why = (f"min({a:.4g}, {b:.4g}): the median density where rays through the grid "
                   f"reach opacity {LEVEL_OPACITY:g} (the depth the run renders), and the peak "
                   f"density {LEVEL_REACHED:.0%} of those {n} rays reach (no holes)")  # fmt: skip
            return min(a, b), why
    top = float(d.max())
    return top / 2, (f"half the largest density (no ray through the grid reaches opacity "
                     f"{LEVEL_OPACITY:g})")  # fmt: skip


def level_hint(values, density: bool = False) -> str:
    """Why a level set is empty, for an error line: the range of the grid's ``values`` (the
    densities themselves when ``density``) and, for a density, a level to try.

    The suggested density level is half the largest density on the grid: a VolSDF-style density
    (the built-in scene's, sigma = Psi_beta(-sdf) / beta) is half its interior value on the
    surface. Measured on built-in-scene runs trained with ``--preset cpu`` (peak densities 5.0
    (mlp) and 20 (hash); 64^3 grid), the mean |true SDF| at the vertices was 0.051 and 0.037,
    the best or within 0.001 of the best of the rules compared (99th and 95th percentiles, a
    quarter of the peak, geometric means of the peak and the minimum or median: 0.036 to 0.22).
    When half the peak is not above the smallest density (a field nearly constant inside the
    box), the middle of the range is suggested instead.

    Args:
        values: the field on the grid (any shape), as returned by ``extract_mesh(...,
            return_values=True)``.
        density: ``values`` are densities (a NeRF): suggest a level.
    """
    v = torch.as_tensor(values).detach().reshape(-1).float().cpu().numpy()
    lo, hi = float(v.min()), float(v.max())
    p50, p99 = (float(x) for x in np.percentile(v, [50, 99]))
    what = "densities" if density else "values"
    msg = f"the {what} on the grid range from {lo:.4g} to {hi:.4g} (median {p50:.4g}, 99th "
    msg += f"percentile {p99:.4g})"
    if not density:
        return msg
    if hi <= lo:
        return msg + "; the density is constant inside the box: try a larger --bounds"
    half = hi / 2
    if half > lo:
        return msg + f"; try --level {half:.3g} (half the largest density)"
    return msg + f"; try --level {(lo + hi) / 2:.3g} (the middle of the range)"


def vertex_colors(
    field, fn, vertices: np.ndarray, device, chunk: int = 1 << 16, h: float = 1e-3
) -> np.ndarray:
    """Bakes a radiance field's colour into mesh vertices, uint8 [V, 3]: at each vertex x the
    outward normal n is the normalised central-difference gradient of the level-set function
    ``fn`` (an SDF, or minus a density: both grow outwards), and the colour is the field's
    ``forward(x, -n)`` colour, i.e. seen by a camera looking straight at the surface."""
    import torch

    out = []
    e = torch.eye(3, device=device)
    with torch.no_grad():
        for s in range(0, len(vertices), chunk):
            x = torch.as_tensor(vertices[s : s + chunk], dtype=torch.float32, device=device)
            pts = torch.cat([x + h * e[i] for i in range(3)] + [x - h * e[i] for i in range(3)])
            d = fn(pts).float().reshape(6, -1)
            g = ((d[:3] - d[3:]) / (2 * h)).T
            n = torch.nn.functional.normalize(torch.nan_to_num(g), dim=-1)
            n = torch.where(
                n.norm(dim=-1, keepdim=True) > 0, n, torch.tensor([0.0, 0.0, 1.0], device=device)
            )
            _, rgb = field(x, -n)
            out.append((rgb.float().clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu())
    return torch.cat(out).numpy() if out else np.zeros((0, 3), np.uint8)


def sample_surface(vertices, faces, n: int, seed: int = 0, return_faces: bool = False):
    """n points uniformly on the triangle mesh (area-weighted), [n, 3]; with ``return_faces``
    also the index [n] of the face each lies on (the same points)."""
    rng = np.random.default_rng(seed)
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    idx = rng.choice(len(faces), n, p=area / area.sum())
    u, w = rng.random(n), rng.random(n)
    flip = u + w > 1
    u[flip], w[flip] = 1 - u[flip], 1 - w[flip]
    t = tri[idx]
    p = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + w[:, None] * (t[:, 2] - t[:, 0])
    return (p, idx) if return_faces else p


def screenshot(path, vertices, faces, size=(640, 480), color="#d8b25a", colors=None) -> None:
    """Offscreen pyvista render of the mesh (no window), written atomically; ``colors`` (uint8
    [V, 3]) paints the vertices instead of the flat ``color``."""
    import pyvista as pv

    pv.OFF_SCREEN = True
    cells = np.hstack([np.full((len(faces), 1), 3), faces]).astype(np.int64).ravel()
    mesh = pv.PolyData(np.asarray(vertices, dtype=np.float64), cells)
    with _headless_vtk():
        plotter = pv.Plotter(off_screen=True, window_size=list(size))
        if colors is not None:
            mesh.point_data["rgb"] = np.asarray(colors, dtype=np.uint8)
            plotter.add_mesh(mesh, scalars="rgb", rgb=True, smooth_shading=True)
        else:
            plotter.add_mesh(mesh, color=color, smooth_shading=True)
        plotter.set_background("white")
        plotter.camera_position = "iso"
        try:
            with atomic_path(path) as tmp:  # the temporary name keeps the .png suffix
                plotter.screenshot(str(tmp))
        finally:
            plotter.close()


@contextlib.contextmanager
def _headless_vtk():
    """On Linux without an X display, VTK's render window asks for EGL directly.

    VTK (9.4+) picks its OpenGL window at run time: X first, then EGL, then OSMesa, and it logs
    why it fell back ("vtkXOpenGLRenderWindow ... WARN| bad X server connection. DISPLAY=", with
    raw ANSI colour codes) to stderr on every headless screenshot. Without ``DISPLAY`` the X try
    cannot succeed, so ``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow`` skips it; VTK still falls
    back to OSMesa (with its own messages) when EGL fails. A value the user set wins, and the
    variable is restored afterwards (VTK reads it when the render window is made)."""
    key = "VTK_DEFAULT_OPENGL_WINDOW"
    if not sys.platform.startswith("linux") or os.environ.get("DISPLAY") or key in os.environ:
        yield
        return
    os.environ[key] = "vtkEGLRenderWindow"
    try:
        yield
    finally:
        os.environ.pop(key, None)
