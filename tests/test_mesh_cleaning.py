"""Meshes that are the surface, without VTK (warpnerf/mesh.py: merge_vertices, face_components,
clean_mesh, seen_faces, cull_unseen; `warpnerf mesh` of a run culls (by the training rays'
weights, unless --no-weight-cull, and by the training cameras) and cleans by default,
`--keep-all` keeps the raw level set): connected components against a plain union-find, faces
hidden from every camera culled, and the built-in scene's surface with an object inside another
and a small floater: the default cleaning keeps exactly the visible surface."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from warpnerf.cli import main
from warpnerf.data.cameras import intrinsics_from_fov, orbit_views
from warpnerf.fields.sdf_volume import sdf_box, sdf_sphere
from warpnerf.mesh import (
    clean_mesh,
    cull_unseen,
    extract_mesh,
    face_components,
    merge_vertices,
    seen_faces,
)  # fmt: skip


def _union_find(faces, n):
    parent = list(range(n))

    def root(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, b, c in faces:
        for x, y in ((a, b), (b, c)):
            parent[root(x)] = root(y)
    return [root(int(f[0])) for f in faces]


@pytest.mark.parametrize("seed", range(6))
def test_components_match_a_union_find(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 60))
    faces = rng.integers(0, n, (int(rng.integers(1, 40)), 3))
    labels, k = face_components(faces, n)
    want = _union_find(faces, n)
    assert k == len(set(want))
    # the same partition of the faces (labels may be numbered differently)
    pairs = {(int(a), b) for a, b in zip(labels, want)}
    assert len(pairs) == k == len({a for a, _ in pairs}) == len({b for _, b in pairs})


def test_merge_and_components_of_a_long_chain():
    """A strip of 2,000 triangles is one component (labels travel the whole chain), and a mesh
    with a vertex per triangle is merged before connectivity."""
    n = 2000
    x = np.arange(n + 2, dtype=np.float32)
    v = np.stack([x, (np.arange(n + 2) % 2).astype(np.float32), np.zeros(n + 2, np.float32)], 1)
    f = np.stack([np.arange(n), np.arange(n) + 1, np.arange(n) + 2], 1)
    assert face_components(f[::-1].copy(), len(v))[1] == 1
    # vertex numbers in an order that runs against the strip: still one component, in few rounds
    perm = np.random.default_rng(0).permutation(n + 2)
    assert face_components(perm[f], n + 2)[1] == 1
    rev = (n + 1 - np.arange(n + 2))[f]  # the least label at the far end
    assert face_components(rev, n + 2)[1] == 1
    vs, fs = v[f].reshape(-1, 3), np.arange(3 * n).reshape(-1, 3)
    vm, fm = merge_vertices(vs, fs)
    assert len(vm) == n + 2 and face_components(fm, len(vm))[1] == 1


def test_non_finite_vertices_are_seen_by_no_camera():
    c2w, k, size = _cameras(8, 32)
    v = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [np.nan, 0, 0]], np.float32)
    seen = seen_faces(v, [[0, 1, 2], [3, 1, 2]], c2w, k, size, size)
    assert seen.tolist() == [True, False]


def _cameras(n=12, size=64, upper=False):
    """Cameras around the built-in scene (its orbit, looking at the origin); ``upper``: those
    above the z = 0.7 plane only (16 degrees of elevation and more: at grazing angles a floor's
    own depth spans many pixels' width and the depth test cannot tell what lies under it)."""
    c2w = orbit_views(n, radius=2.5, seed=0)
    if upper:
        c2w = c2w[c2w[:, 2, 3] > 0.7]
    return c2w, intrinsics_from_fov(size, size, 0.7).expand(len(c2w), 4), size


def _grid(z0, half=1.0, m=24):
    """A square [-half, half]^2 at height z0 of 2 m^2 triangles, facing +z."""
    t = np.linspace(-half, half, m + 1, dtype=np.float32)
    xx, yy = np.meshgrid(t, t, indexing="ij")
    v = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, z0, np.float32)], 1)
    i = np.arange(m)[:, None] * (m + 1) + np.arange(m)[None, :]
    i = i.ravel()
    f = np.concatenate(
        [np.stack([i, i + m + 1, i + 1], 1), np.stack([i + 1, i + m + 1, i + m + 2], 1)]
    )
    return v, f


def test_faces_hidden_from_every_camera_are_culled():
    c2w, k, size = _cameras(24, 64, upper=True)  # looking down: a floor at z = 0 hides z < 0
    assert len(c2w) >= 8
    floor_v, floor_f = _grid(0.0, 1.5, 40)
    under_v, under_f = _grid(-0.4, 0.5, 8)  # under the floor: no camera sees it
    v = np.concatenate([floor_v, under_v])
    f = np.concatenate([floor_f, under_f + len(floor_v)])
    seen = seen_faces(v, f, c2w, k, size, size)
    # (corners of the 3 x 3 floor fall outside every view at this distance)
    assert seen[: len(floor_f)].mean() > 0.9 and not seen[len(floor_f) :].any()
    v2, f2, info = cull_unseen(v, f, c2w, k, size, size)
    assert v2[:, 2].min() == 0.0 and info["faces_unseen"] >= len(under_f)
    # behind every camera: not in front of any of them
    far = c2w[:, :3, 3].mean(0).numpy() * 3
    assert not seen_faces(far + np.eye(3, dtype=np.float32), [[0, 1, 2]], c2w, k, size, size)[0]


def _builtin_sdf(p):
    box = sdf_box(p, torch.tensor([-0.4, -0.1, 0.0]), torch.tensor([0.55, 0.55, 0.55]))  # (sides)
    return torch.minimum(box, sdf_sphere(p, torch.tensor([0.4, 0.15, 0.05]), 0.38))


def test_builtin_scene_keeps_only_its_visible_surface():
    """The built-in scene's level set plus a piece inside the box (a cavity no camera sees: the
    inside of a solid, as an SDF's raw level set can hold) and
    a small floater in free space: culling by the training cameras and dropping small
    components leave vertices on the true surface only, inside its box + 0.05."""
    v, f = extract_mesh(_builtin_sdf, [-1.0] * 3, [1.0] * 3, 64)
    inner = lambda p: sdf_sphere(p, torch.tensor([-0.4, -0.1, 0.0]), 0.1)  # noqa: E731
    vi, fi = extract_mesh(inner, [-1.0] * 3, [1.0] * 3, 64)
    floater = lambda p: sdf_sphere(p, torch.tensor([0.0, -0.7, 0.8]), 0.05)  # noqa: E731
    vf, ff = extract_mesh(floater, [-1.0] * 3, [1.0] * 3, 64)
    vv = np.concatenate([v, vi, vf])
    ff_all = np.concatenate([f, fi + len(v), ff + len(v) + len(vi)])
    sdf = lambda x: _builtin_sdf(torch.as_tensor(x)).abs().numpy()  # noqa: E731
    assert sdf(vv).max() > 0.25  # the raw mesh has pieces off the surface
    c2w, k, size = _cameras(24, 96)
    vc, fc, info = cull_unseen(vv, ff_all, c2w, k, size, size)
    vc, fc, info2 = clean_mesh(vc, fc, 0.01)
    assert info["faces_unseen"] >= len(fi) and info2["components_removed"] >= 1
    assert sdf(vc).max() < 0.03  # on the surface (marching cubes at 2/63 spacing)
    # the box (sides 0.55 about (-0.4, -0.1, 0)) and the sphere (0.38 about (0.4, 0.15, 0.05))
    lo = np.minimum([-0.675, -0.375, -0.275], [0.02, -0.23, -0.33]) - 0.05
    hi = np.maximum([-0.125, 0.175, 0.275], [0.78, 0.53, 0.43]) + 0.05
    assert (vc.min(0) >= lo).all() and (vc.max(0) <= hi).all()
    assert len(fc) > 0.5 * len(f)  # most of the true surface is seen and kept


def test_mesh_of_a_run_culls_and_cleans_unless_keep_all(tmp_path, capsys):
    run = tmp_path / "r"
    assert main(["train", "nerf", "--data", "builtin", "--builtin-size", "12", "--iters", "3",
                 "--batch", "32", "--samples", "8", "--layers", "2", "--width", "16",
                 "--pos-freqs", "1", "--dir-freqs", "1", "--val-images", "0", "--quiet",
                 "--no-tensorboard", "--out", str(run)]) == 0  # fmt: skip
    capsys.readouterr()

    def mesh(name, *extra):
        return main(["mesh", str(run), "--resolution", "16", "--no-screenshot", "--out",
                     str(tmp_path / name), *extra])  # fmt: skip

    level = []
    if mesh("m.ply") != 0:  # an untrained field: the density level it suggests
        import re

        level = ["--level", re.search(r"try --level ([0-9.e+-]+)", capsys.readouterr().err)[1]]
        assert mesh("m.ply", *level) == 0
    default = json.loads(capsys.readouterr().out)
    assert mesh("raw.ply", *level, "--keep-all") == 0
    raw = json.loads(capsys.readouterr().out)
    assert default["culled_by_views"] is True and default["clean"] == 0.01
    assert "culled_by_views" not in raw and "clean" not in raw
    assert default["faces_extracted"] == raw["faces"] >= default["faces"]
    # culled by the training rays' weights first (issue 49), unless --no-weight-cull
    assert default["culled_by_weights"] is True and default["weight_grid"]["rays"] > 0
    assert "faces_unweighted" in default and "culled_by_weights" not in raw
    assert mesh("w.ply", *level, "--no-weight-cull") == 0
    off = json.loads(capsys.readouterr().out)
    assert off["culled_by_weights"] is False and "faces_unweighted" not in off
    assert off["culled_by_views"] is True and "--no-weight-cull" in off["weights_note"]
    assert off["faces"] >= default["faces"]
