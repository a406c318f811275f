"""Mesh extraction (Warp's marching cubes, CPU and CUDA), PLY output and pyvista screenshots.

``extract_mesh(field_fn, lower, upper, resolution, level)`` samples ``field_fn(points [m, 3]) ->
values [m]`` on a regular grid of ``resolution^3`` nodes spanning [lower, upper] (world
coordinates), in chunks, and runs marching cubes at ``level``: 0 for signed distances, a density
threshold for NeRFs. Vertices come back in world coordinates.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch

from .io import atomic_path

__all__ = ["extract_mesh", "write_ply", "read_ply", "screenshot", "sample_surface"]


@torch.no_grad()
def extract_mesh(field_fn, lower, upper, resolution: int, level: float = 0.0, device="cpu",
                 chunk: int = 1 << 18):  # fmt: skip
    """(vertices [V, 3] float32 numpy, faces [F, 3] int32 numpy) of the level set."""
    import warp as wp

    from .ops._bridge import _wp

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
    field = vals.reshape(resolution, resolution, resolution).contiguous()
    _wp()
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
    return v, f


def write_ply(path, vertices: np.ndarray, faces: np.ndarray, replace_foreign: bool = False) -> None:
    """Binary little-endian PLY (float32 xyz, int32 triangle indices), written atomically."""
    v = np.ascontiguousarray(vertices, dtype="<f4")
    f = np.ascontiguousarray(faces, dtype="<i4")
    head = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode()
    body = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    body["n"], body["i"] = 3, f
    with atomic_path(path, replace_foreign) as tmp, open(tmp, "wb") as fh:
        fh.write(head)
        fh.write(v.tobytes())
        fh.write(body.tobytes())


def read_ply(path):
    """Reads what :func:`write_ply` writes (vertices [V, 3], faces [F, 3])."""
    data = open(path, "rb").read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    head = data[:end].decode().splitlines()
    nv = int(next(x for x in head if x.startswith("element vertex")).split()[-1])
    nf = int(next(x for x in head if x.startswith("element face")).split()[-1])
    v = np.frombuffer(data, "<f4", nv * 3, end).reshape(nv, 3)
    body = np.frombuffer(data, [("n", "u1"), ("i", "<i4", (3,))], nf, end + nv * 12)
    return v.copy(), body["i"].copy()


def sample_surface(vertices, faces, n: int, seed: int = 0) -> np.ndarray:
    """n points uniformly on the triangle mesh (area-weighted), [n, 3]."""
    rng = np.random.default_rng(seed)
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    idx = rng.choice(len(faces), n, p=area / area.sum())
    u, w = rng.random(n), rng.random(n)
    flip = u + w > 1
    u[flip], w[flip] = 1 - u[flip], 1 - w[flip]
    t = tri[idx]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + w[:, None] * (t[:, 2] - t[:, 0])


def screenshot(path, vertices, faces, size=(640, 480), color="#d8b25a") -> None:
    """Offscreen pyvista render of the mesh (no window), written atomically."""
    import pyvista as pv

    pv.OFF_SCREEN = True
    cells = np.hstack([np.full((len(faces), 1), 3), faces]).astype(np.int64).ravel()
    mesh = pv.PolyData(np.asarray(vertices, dtype=np.float64), cells)
    plotter = pv.Plotter(off_screen=True, window_size=list(size))
    plotter.add_mesh(mesh, color=color, smooth_shading=True)
    plotter.set_background("white")
    plotter.camera_position = "iso"
    try:
        with atomic_path(path) as tmp:  # the temporary name keeps the .png suffix
            plotter.screenshot(str(tmp))
    finally:
        plotter.close()


def read_ply_points(path):
    """(points [N, 3], normals [N, 3] or None) of a PLY file's vertices (ascii or binary LE)."""
    data = open(path, "rb").read()
    end = data.index(b"end_header") + len(b"end_header")
    end = data.index(b"\n", end) + 1
    head = data[:end].decode("ascii", "replace").splitlines()
    fmt = next((x.split()[1] for x in head if x.startswith("format")), "")
    props, n, in_vertex = [], 0, False
    for line in head:
        w = line.split()
        if not w:
            continue
        if w[:2] == ["element", "vertex"]:
            n, in_vertex = int(w[2]), True
        elif w and w[0] == "element":
            in_vertex = False
        elif in_vertex and w[0] == "property" and w[1] != "list":
            props.append((w[2], w[1]))
    names = [p for p, _ in props]
    if not {"x", "y", "z"} <= set(names):
        raise ValueError("the vertex element has no x, y, z properties")
    types = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1",
             "uint8": "u1", "int": "<i4", "int32": "<i4", "uint": "<u4", "short": "<i2",
             "ushort": "<u2", "char": "i1"}  # fmt: skip
    if fmt == "ascii":
        rows = data[end:].decode().split("\n")[:n]
        arr = np.array([[float(x) for x in r.split()[: len(names)]] for r in rows])
        arr = arr.reshape(len(rows), len(names))  # 0 vertices: [0, k], not [0]
        col = {k: arr[:, i] for i, k in enumerate(names)}
    elif fmt == "binary_little_endian":
        dt = np.dtype([(k, types[t]) for k, t in props])
        rec = np.frombuffer(data, dt, n, end)
        col = {k: rec[k].astype(np.float64) for k in names}
    else:
        raise ValueError(f"unsupported PLY format {fmt!r}")
    pts = np.stack([col["x"], col["y"], col["z"]], 1)
    nrm = np.stack([col["nx"], col["ny"], col["nz"]], 1) if "nx" in col else None
    return pts, nrm
