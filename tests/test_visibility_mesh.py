"""The delivered mesh keeps what training rays put weight on (issue 49): cull_unweighted exact on
a hand-made mesh and grid; the visibility grid of an opaque analytic ball (both renderers: MLP
stratified samples and occupancy-grid marching) marks the cells where rays hit it and nothing in
front of it, inside it or behind it; surface_mesh culls an inner surface and the far side by
it; `train sdf` writes mesh.ply cleaned of small components."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from warpnerf.data.cameras import intrinsics_from_fov
from warpnerf.fields.model import RadianceModel
from warpnerf.fields.sdf_volume import sdf_sphere
from warpnerf.mesh import cull_unweighted, extract_mesh, read_ply, surface_mesh
from warpnerf.occupancy import OccupancyGrid
from warpnerf.train.nerf_config import NeRFConfig
from warpnerf.train.visibility import training_weight_grid, weight_grid

R_BALL = 0.5
BOX = ([-1.0] * 3, [1.0] * 3)


def test_cull_unweighted_is_exact():
    """Five separate triangles over a 4^3 grid of [0, 1]^3: kept exactly those whose centroid's
    cell is marked (one on the box's upper corner counts in the last cell, one outside the box
    is dropped); vertices renumbered, the figures exact."""
    grid = np.zeros((4, 4, 4), bool)
    grid[0, 0, 0] = grid[3, 3, 3] = grid[1, 2, 3] = True
    tri = np.array([[0, 0, 0], [0.09, 0, 0], [0, 0.09, 0]], np.float32)  # area 0.00405
    at = [
        (0.05, 0.05, 0.05),  # cell (0, 0, 0): marked
        (0.3, 0.55, 0.8),  # cell (1, 2, 3): marked
        (0.55, 0.3, 0.8),  # cell (2, 1, 3): not marked
        (0.97, 0.97, 0.97),  # centroid at the upper corner (1, 1, 1): cell (3, 3, 3), marked
        (1.2, 0.5, 0.5),  # outside the box: dropped
    ]
    v = np.concatenate([tri - tri.mean(0) + np.float32(c) for c in at])
    v[9:12] += np.float32(1.0) - v[9:12].mean(0)  # exactly on the corner
    f = np.arange(15).reshape(5, 3)
    v2, f2, info = cull_unweighted(v, f, grid, [0, 0, 0], [1, 1, 1])
    assert info == {"faces_unweighted": 2, "area_unweighted_fraction": pytest.approx(0.4)}
    assert f2.dtype == np.int32 and len(f2) == 3 and len(v2) == 9
    kept = np.sort(v2[f2].mean(1), axis=0)
    want = np.sort(np.asarray([at[0], at[1], [1.0, 1.0, 1.0]], np.float32), axis=0)
    np.testing.assert_allclose(kept, want, atol=1e-6)
    # torch grids work alike; an all-marked grid keeps every face inside the box
    _, f3, i3 = cull_unweighted(v, f, torch.ones(4, 4, 4, dtype=torch.bool), [0] * 3, [1] * 3)
    assert len(f3) == 4 and i3["faces_unweighted"] == 1
    _, f4, i4 = cull_unweighted(v, f[:0], grid, [0] * 3, [1] * 3)
    assert len(f4) == 0 and i4 == {"faces_unweighted": 0, "area_unweighted_fraction": 0.0}
    with pytest.raises(ValueError):
        cull_unweighted(v, f, grid, [0] * 3, [1, 0, 1])


class _Ball(torch.nn.Module):
    """An opaque ball (density ``sigma`` inside radius R_BALL about the origin, 0 outside): both
    interfaces, ``density``/``color`` (marched) and ``forward`` (MLP renderer)."""

    kind = "density"

    def __init__(self, sigma=1e4):
        super().__init__()
        self.sigma = sigma

    def density(self, p):
        return torch.where(p.norm(dim=-1) < R_BALL, self.sigma, 0.0), p

    def color(self, feats, d, **kw):
        return torch.full_like(d, 0.5)

    def forward(self, p, d):
        return self.density(p)[0], torch.full_like(p, 0.5)


def _model(kind, sigma=1e4):
    ball = _Ball(sigma)
    if kind == "mlp":  # stratified samples (128 over [1, 5]: 0.03125 apart)
        return RadianceModel(ball), NeRFConfig(near=1.0, far=5.0, n_coarse=128), 1 / 32
    dt = 2 * math.sqrt(3) / 256
    grid = OccupancyGrid([-1, -1, -1, 1, 1, 1], 16, dt=dt)  # new: every cell occupied
    return RadianceModel(ball, None, grid), NeRFConfig(near=1.0, far=5.0), dt


def _camera(size=48):
    """One camera on +z at distance 3, looking at the origin (down -z)."""
    c2w = torch.eye(4)[None].clone()
    c2w[0, 2, 3] = 3.0
    k = intrinsics_from_fov(size, size, 0.5)[None]
    return SimpleNamespace(c2w=c2w, intrinsics=k, width=size, height=size, distortion=None)


def _cell_centres(res):
    c = (torch.arange(res) + 0.5) * (2.0 / res) - 1.0
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    return torch.stack([x, y, z], -1)


@pytest.mark.parametrize("kind", ["mlp", "marched"])
def test_grid_marks_where_rays_stop_and_nothing_behind(kind):
    """Every pixel's ray of one camera: cells are marked (before dilation) only on the ball's
    surface that faces the camera (within a cell's half-diagonal and a sample's step), never
    in front of it, deep inside it or on its far side; the cell where each ray hits the ball
    is marked once dilated, and dilation reaches no further than one cell."""
    from warpnerf.data.cameras import camera_rays

    model, cfg, dt = _model(kind)
    cam = _camera()
    o, d = camera_rays(cam.c2w, cam.intrinsics, cam.width, cam.height)
    res, cell = 16, 2.0 / 16
    g0, marked = weight_grid(model, cfg, o, d, *BOX, res, dilate=0, chunk=700)
    assert g0.shape == (res,) * 3 and g0.dtype == torch.bool and int(g0.sum()) == marked > 20
    c = _cell_centres(res)
    r = c.norm(dim=-1)
    half_diag = cell * math.sqrt(3) / 2
    near_surface = (r - R_BALL).abs() <= half_diag + dt
    assert bool(near_surface[g0].all())  # nothing in front of the ball, nothing deep inside
    assert bool((c[..., 2][g0] >= -half_diag).all())  # nothing on the far side
    # the analytic first hits of the rays that meet the ball (not grazing it)
    b = (o * d).sum(-1)
    disc = b**2 - ((o * o).sum(-1) - R_BALL**2)
    hit = disc > 0.01
    t = -b[hit] - disc[hit].sqrt()
    p = o[hit] + t[:, None] * d[hit]
    assert hit.sum() > 100
    g1, _ = weight_grid(model, cfg, o, d, *BOX, res, dilate=1)
    idx = ((p + 1) / cell).floor().long().clamp(0, res - 1)
    assert bool(g1[idx[:, 0], idx[:, 1], idx[:, 2]].all())  # each hit's cell is marked
    # dilated: one cell more, no further (the far side and the core stay unmarked)
    assert bool((c[..., 2][g1] >= -half_diag - cell).all())
    assert not bool(g1[r < R_BALL - half_diag - dt - math.sqrt(3) * cell].any())
    assert bool(g1[g0].all())


def test_training_grid_culls_what_no_ray_reaches():
    """training_weight_grid over one camera's pixels (stride 2), then surface_mesh: of the ball's
    sphere plus a sphere inside it, the inner sphere and the far hemisphere go, the side facing
    the camera stays; with an empty field there is no grid (and a reason)."""
    model, cfg, _ = _model("marched")
    cam = _camera(64)
    wg, why = training_weight_grid(model, cfg, cam, *BOX, resolution=32, stride=2)
    assert why is None and wg.grid.shape == (wg.info["resolution"],) * 3
    assert wg.info["rays"] == 32 * 32 and wg.info["stride"] == 2 and wg.info["threshold"] == 0.005
    assert 8 <= wg.info["resolution"] <= 32 and 0 < wg.info["cells_marked_fraction"] < 0.2
    vo, fo = extract_mesh(lambda p: sdf_sphere(p, torch.zeros(3), R_BALL), *BOX, 40)
    vi, fi = extract_mesh(lambda p: sdf_sphere(p, torch.zeros(3), 0.2), *BOX, 40)
    v, f = np.concatenate([vo, vi]), np.concatenate([fo, fi + len(vo)])
    v2, f2, info = surface_mesh(v, f, None, 0.01, weight_grid=wg)
    assert info["culled_by_weights"] is True and info["culled_by_views"] is False
    cent = v2[f2].mean(1)
    assert (np.linalg.norm(cent, axis=1) > 0.45).all()  # the inner sphere is gone
    cell = 2.0 / wg.info["resolution"]
    assert cent[:, 2].min() > -2 * cell  # nothing of the far hemisphere beyond the dilation
    front = vo[fo].mean(1)[:, 2] > 0.2
    assert (cent[:, 2] > 0.2).sum() == front.sum()  # the side facing the camera is all kept
    assert 0.4 < info["area_unweighted_fraction"] < 0.8 and info["components"] == 1
    # no weight anywhere: nothing to cull by
    empty, _, _ = _model("marched", sigma=0.0)
    none, why = training_weight_grid(empty, cfg, cam, *BOX, resolution=32, stride=4)
    assert none is None and "no sample" in why


def test_train_sdf_writes_a_cleaned_mesh(tmp_path, monkeypatch):
    """`train sdf`'s mesh.ply goes through clean_mesh: a small floater added to the marched
    level set is not in the file; metrics say what was dropped, and the faces counted are the
    file's."""
    import warpnerf.mesh as M
    from warpnerf.train.sdf import SDFConfig, load_sdf_run, train_sdf

    march = M.extract_mesh

    def with_floater(fn, lower, upper, resolution, *a, **kw):
        v, f = march(fn, lower, upper, resolution, *a, **kw)
        blob = lambda p: sdf_sphere(p, torch.tensor([0.9, 0.9, 0.9]), 0.06)  # noqa: E731
        vb, fb = march(blob, [0.7] * 3, [1.0] * 3, 12)
        return np.concatenate([v, vb]), np.concatenate([f, fb + len(v)])

    monkeypatch.setattr(M, "extract_mesh", with_floater)
    lines = []
    cfg = SDFConfig(iters=2, batch=32, n_random=32, resolution=16, width=16, n_layers=2, skip=1,
                    pos_freqs=1)  # fmt: skip
    m = train_sdf(cfg, tmp_path / "r", progress=False, log=lines.append)
    mc = m["mesh_clean"]
    assert mc["clean"] == 0.01 and mc["components_removed"] >= 1 and mc["components"] >= 2
    assert mc["faces_extracted"] > m["faces"] > 0
    assert any("mesh.ply" in s and "components dropped" in s for s in lines)
    v, f = read_ply(tmp_path / "r" / "mesh.ply")
    assert len(f) == m["faces"] and len(v) == m["vertices"]
    saved = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert saved["mesh_clean"] == mc
    # the floater's vertices (at 0.9 in the normalised frame) are gone, in the data's units
    _, _, ck = load_sdf_run(tmp_path / "r")
    c, s = np.asarray(ck["normalisation"]["center"]), ck["normalisation"]["scale"]
    assert (np.linalg.norm((v - c) * s - 0.9, axis=1) > 0.1).all()
