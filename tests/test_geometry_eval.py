"""Geometry evaluation's depth error (train/geometry_eval.py): the analytic first hits of the
materials scene and of spheres, and the rendered depth of a constructed hash_sdf model (which
starts as a sphere) against them. No dataset needed; the CLI path is in test_hash_sdf.py."""

from __future__ import annotations

import math

import pytest
import torch

from warpnerf.data.materials_truth import (
    MATERIALS_SPHERES,
    materials_depth,
    materials_reference,
    sphere_depth,
)
from warpnerf.train.geometry_eval import depth_error


def test_materials_depth_hits_the_spheres_and_the_disk():
    x0, y0, z0 = MATERIALS_SPHERES[0]  # (-1.05, -0.4, 0.32), radius 0.32
    o = torch.tensor([
        [x0, y0, 3.0],  # straight down onto the sphere's top
        [0.0, 0.0, 3.0],  # down between the spheres: the disk
        [2.0, 0.0, 3.0],  # down outside the disk (radius 1.6)
        [-3.0, y0, z0],  # along +x through the row of spheres
        [-3.0, 0.0, 5.0],  # parallel to the disk, above everything
        [-3.0, 0.0, 0.0],  # in the disk's plane
        [0.0, 0.0, -1.0],  # from below, looking down
    ], dtype=torch.float64)  # fmt: skip
    d = torch.tensor([[0, 0, -1], [0, 0, -1], [0, 0, -1], [1, 0, 0], [1, 0, 0], [1, 0, 0],
                      [0, 0, -1]], dtype=torch.float64)  # fmt: skip
    t = materials_depth(o, d)
    want = [3.0 - 0.64, 3.0, math.inf, 3.0 + x0 - 0.32, math.inf, math.inf, math.inf]
    assert t.tolist() == pytest.approx(want, abs=1e-12)
    # the reference points lie on the surfaces the rays hit
    ref = torch.as_tensor(materials_reference(2000), dtype=torch.float64)
    down = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).expand_as(ref)
    top = ref[:, 2] > 0.32 + 0.3  # the spheres' caps: nothing above them
    t = materials_depth(ref[top] + 2.0 * down[top].neg(), down[top])
    assert torch.allclose(t, torch.full_like(t, 2.0), atol=1e-5)


def test_sphere_depth():
    o = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, 3.0], [0.0, 2.0, 3.0], [0.0, 0.0, 0.0]])
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    t = sphere_depth(o, d, [[0, 0, 0], [0, 0, -2.5]], 0.5)
    assert t.tolist() == [2.5, math.inf, math.inf, math.inf]  # (from inside: no first hit)
    t = sphere_depth(o[:1], d[:1], [[0, 0, -2.5]], 0.5)
    assert t.tolist() == [5.0]


@pytest.fixture(scope="module")
def sphere_model():
    """A fresh hash_sdf model (its SDF starts as a sphere of radius 0.5 box units) with a sharp,
    fixed beta, and two 16x16 views from distance 2.5."""
    from warpnerf.data import intrinsics_from_fov, orbit_views
    from warpnerf.data.dataset import Dataset
    from warpnerf.fields.model import build_model
    from warpnerf.train.nerf_config import NeRFConfig

    cfg = NeRFConfig(field="hash_sdf", data="builtin", aabb=1.0, beta=0.005, learn_beta=False,
                     grid_res=0, hash_levels=3, hash_log2_size=8, hash_max_res=16, near=1.0,
                     far=4.0)  # fmt: skip
    model = build_model(cfg).eval()
    ds = Dataset(images=torch.zeros(2, 16, 16, 3), c2w=orbit_views(2, radius=2.5),
                 intrinsics=intrinsics_from_fov(16, 16, 0.7).expand(2, 4))  # fmt: skip
    return cfg, model, ds, model.field.radius * model.field.half


def test_depth_error_of_a_sphere(sphere_model):
    """The rendered surface depth of the sphere matches its analytic hits to a fraction of the
    sample spacing; a reference sphere 0.1 larger is off by about 0.1 (more at grazing rays)."""
    cfg, model, ds, r = sphere_model
    assert r == pytest.approx(0.5)
    right = depth_error(model, cfg, ds, lambda o, d: sphere_depth(o, d, [[0, 0, 0]], r), views=0)
    assert right["depth_views"] == 2 and right["depth_pixels"] > 100
    assert right["depth_error_mean"] < 0.02 and right["depth_error_median"] < 0.015
    wrong = depth_error(model, cfg, ds, lambda o, d: sphere_depth(o, d, [[0, 0, 0]], r + 0.1),
                        views=1)  # fmt: skip
    assert wrong["depth_views"] == 1 and 0.09 < wrong["depth_error_median"] < 0.2
    none = depth_error(model, cfg, ds, lambda o, d: sphere_depth(o, d, [[0, 0, 9]], r), views=1)
    assert none["depth_pixels"] == 0 and none["depth_error_mean"] is None


def test_depth_error_by_shape(sphere_model):
    """Per shape: the pixels of each shape add up to all of them, and a reference sphere 0.1
    larger than the field's puts the rendered surface about 0.1 behind it (signed median > 0)
    on the shape that holds the hits, the other shape named has none."""
    import numpy as np

    cfg, model, ds, r = sphere_model
    ref = lambda o, d: sphere_depth(o, d, [[0, 0, 0]], r + 0.1)  # noqa: E731

    def ids(p):  # upper half: shape 0, lower: shape 1; "none" never
        return np.where(p[:, 2] >= 0, 0, 1)

    res = depth_error(model, cfg, ds, ref, views=0, shapes=(("upper", "lower", "none"), ids))
    per = res["depth_by_shape"]
    assert set(per) <= {"upper", "lower"} and per
    assert sum(v["pixels"] for v in per.values()) == res["depth_pixels"]
    for v in per.values():
        assert 0.05 < v["signed_median"] < 0.2
        assert v["median"] == pytest.approx(abs(v["signed_median"]), abs=0.05)
    plain = depth_error(model, cfg, ds, ref, views=0)
    assert "depth_by_shape" not in plain
    assert plain["depth_error_mean"] == pytest.approx(res["depth_error_mean"])


def test_materials_visibility_and_shapes():
    """The analytic observation mask: a sphere's top and the open disk are seen from above, the
    contact point under a sphere and a sphere's underside are not, points outside the image are
    not; each point is assigned to its own shape."""
    import numpy as np

    from warpnerf.data.cameras import look_at
    from warpnerf.data.materials_truth import (
        MATERIALS_NAMES,
        MATERIALS_SPHERES,
        materials_shape_ids,
        materials_visible,
    )

    (x, y, z) = MATERIALS_SPHERES[6]  # the glass sphere
    pts = np.array([
        [x, y, z + 0.32],  # its top
        [x, y, 0.0],  # its contact point with the disk
        [x, y, z - 0.32 + 1e-3],  # (just above) its bottom
        [0.0, 1.3, 0.0],  # open disk
        [0.0, -1.3, 0.0],  # open disk, outside the camera's image
    ])  # fmt: skip
    cam = look_at((0.0, 3.0, 4.0), (0.0, 0.8, 0.0)).unsqueeze(0)
    wide = torch.tensor([[100.0, 100.0, 100.0, 100.0]])  # 200x200, 90 degrees
    narrow = torch.tensor([[400.0, 400.0, 100.0, 100.0]])  # 28 degrees
    seen = materials_visible(pts, cam, narrow, 200, 200)
    assert seen.tolist() == [True, False, False, True, False]
    below = look_at((0.0, 0.0, -4.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)).unsqueeze(0)
    assert not materials_visible(pts[:1], below, wide, 200, 200).any()  # the disk hides it
    ids = materials_shape_ids(pts)
    assert [MATERIALS_NAMES[i] for i in ids[[0, 3]]] == ["glass", "disk"]
