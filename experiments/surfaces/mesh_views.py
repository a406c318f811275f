"""Images of a materials mesh from the side and from below, coloured by each vertex's distance to
the scene's analytic surface (the eight spheres and the ground disk): issue 49's "what is left"
views of the delivered mesh. CPU only (pyvista off-screen).

    python experiments/surfaces/mesh_views.py MESH.ply --out docs/x.png [--clim 0.05]

One PNG of three panels (side, below, above at an angle); the title gives the mean and 95th
percentile of the error and the mesh's lowest z.
"""

from __future__ import annotations

import argparse

import numpy as np


def surface_distance(v: np.ndarray) -> np.ndarray:
    """Unsigned distance [n] from points [n, 3] to the materials spheres and disk."""
    from warpnerf.data.materials_truth import materials_signed_distances

    return np.abs(materials_signed_distances(v)).min(1)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("mesh")
    p.add_argument("--out", required=True)
    p.add_argument("--clim", type=float, default=0.05)
    p.add_argument("--title", default="")
    a = p.parse_args(argv)
    import pyvista as pv

    from warpnerf.ply import read_ply

    v, f = read_ply(a.mesh)[:2]
    v, f = np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)
    err = surface_distance(v)
    faces = np.hstack([np.full((f.shape[0], 1), 3), f]).ravel()
    mesh = pv.PolyData(v, faces)
    mesh["error"] = err
    pv.OFF_SCREEN = True
    pl = pv.Plotter(shape=(1, 3), off_screen=True, window_size=(1800, 620))
    views = (
        ("side (from -y)", (0, -6, 0.4), (0, 0, 1)),
        ("below (from -z)", (0, 0, -6), (0, 1, 0)),
        ("above, at an angle", (3.5, -4.5, 3.5), (0, 0, 1)),
    )
    for i, (name, pos, up) in enumerate(views):
        pl.subplot(0, i)
        bar = {"title": "distance to truth"}
        pl.add_mesh(mesh.copy(), scalars="error", clim=(0, a.clim), cmap="viridis",
                    show_scalar_bar=i == 2, scalar_bar_args=bar)  # fmt: skip
        pl.add_text(name, font_size=11)
        pl.camera_position = [pos, (0, 0, 0.1), up]
    title = (f"{a.title}  error mean {err.mean():.4f}, p95 {np.percentile(err, 95):.4f}, "
             f"lowest z {v[:, 2].min():.3f}")  # fmt: skip
    pl.subplot(0, 0)
    pl.add_text(title, position="lower_left", font_size=9)
    pl.screenshot(a.out)
    print(title)


if __name__ == "__main__":
    main()
