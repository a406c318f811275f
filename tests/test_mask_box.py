"""The scene box RGBA images ask for (warpnerf/data/mask_box.py, nerf_run.box_from_alpha): the
smallest cube a ray enters, exact against a dense search and in closed form for axis-parallel rays;
the box of a cube's masks is the cube; a new Blender-format run's box grows to hold what its
opaque pixels show (the materials scene's disk reaches 1.6, past the convention's 1.5) and stays
1.5 otherwise (lego), as given with --aabb, for RGB images and for fields without a box."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from warpnerf.data import look_at
from warpnerf.data.cameras import camera_rays
from warpnerf.data.mask_box import opaque_reach, ray_reach
from warpnerf.errors import UserError
from warpnerf.train.nerf import NeRFConfig, load_data, settle_new_run
from warpnerf.train.nerf_run import BOX_MARGIN, box_from_alpha

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
FOV = 0.8


def test_ray_reach_matches_a_dense_search():
    g = torch.Generator().manual_seed(0)
    o = 4.0 * torch.nn.functional.normalize(torch.randn(200, 3, generator=g, dtype=torch.float64))
    d = torch.nn.functional.normalize(
        -o + 1.5 * torch.randn(200, 3, generator=g, dtype=torch.float64)
    )
    got = ray_reach(o, d, 2.0, 6.0)
    t = torch.linspace(2.0, 6.0, 40001, dtype=torch.float64)
    dense = (o[:, None] + t[None, :, None] * d[:, None]).abs().amax(-1).min(-1).values
    assert torch.all(got <= dense + 1e-9)  # (the exact minimum is below any sample's)
    assert torch.all(dense - got < 1e-3)  # (and the samples, 1e-4 apart, come close to it)


def test_ray_reach_hard_cases():
    o = torch.tensor([[-5.0, 0.3, -0.2], [0.0, 0.0, 5.0], [3.0, 3.0, 3.0], [-5.0, 0.3, -0.2]],
                     dtype=torch.float64)  # fmt: skip
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]],
                     dtype=torch.float64)  # fmt: skip
    near = torch.tensor([2.0, 2.0, 2.0, 1.0])
    got = ray_reach(o[:3], d[:3], 2.0, 6.0)
    # axis-parallel through the cube: |y| = 0.3 once x passes 0; down the z axis: z = 0 at t = 5;
    # a ray moving away from the origin: its nearest point is at t = near
    assert got.tolist() == pytest.approx([0.3, 0.0, 5.0], abs=1e-9)
    # a depth range that ends before the ray reaches the cube: the range's end (x = -5 + 1.5)
    assert float(ray_reach(o[3:], d[3:], float(near[3]), 1.5)) == pytest.approx(3.5, abs=1e-9)
    assert torch.isfinite(got).all()


def _cube_views(s: float, n: int = 8, size: int = 40, dist: float = 5.0):
    """(c2w [n, 4, 4], intrinsics [n, 4], alpha [n, size, size] float) of an opaque cube
    [-s, s]^3 seen from n cameras around it (exact slab test per pixel centre)."""
    angles = np.linspace(0, 2 * math.pi, n, endpoint=False)
    c2w = torch.stack([look_at((dist * math.cos(a), dist * math.sin(a), 0.4 * dist * (k % 3 - 1)))
                       for k, a in enumerate(angles)])  # fmt: skip
    f = 0.5 * size / math.tan(0.5 * FOV)
    intr = torch.tensor([[f, f, size / 2, size / 2]] * n, dtype=torch.float32)
    o, d = camera_rays(c2w, intr, size, size)
    o, d = o.double(), d.double()
    inv = 1.0 / torch.where(d == 0, torch.full_like(d, 1e-30), d)
    t0, t1 = (-s - o) * inv, (s - o) * inv
    tn, tf = torch.minimum(t0, t1).amax(-1), torch.maximum(t0, t1).amin(-1)
    hit = (tn <= tf) & (tf > 0)
    return c2w.float(), intr, hit.reshape(n, size, size).float()


@pytest.mark.parametrize("s", [1.0, 1.8])
def test_the_box_of_a_cubes_masks_is_the_cube(s):
    c2w, intr, alpha = _cube_views(s)
    got = opaque_reach(c2w, intr, alpha, 2.0, 8.0, 1.5)
    if s < 1.5:
        assert got == 1.5  # (nothing asks for more than the convention's box)
    else:
        assert s - 0.06 < got <= s + 1e-6  # (the rays through the silhouette's pixels)
    u8 = (alpha * 255).to(torch.uint8)
    assert opaque_reach(c2w, intr, u8, 2.0, 8.0, 1.5) == got  # (uint8 alpha: the same)
    half = alpha * 0.49  # (pixels below half coverage show nothing)
    assert opaque_reach(c2w, intr, half, 2.0, 8.0, 1.5) == 1.5
    with pytest.raises(ValueError):
        opaque_reach(c2w, intr[:3], alpha, 2.0, 8.0, 1.5)


def _blender_cube(root: Path, s: float, rgba: bool = True, n: int = 8, size: int = 24) -> Path:
    import imageio.v3 as iio

    c2w, _, alpha = _cube_views(s, n, size)
    frames = []
    for i in range(n):
        img = np.zeros((size, size, 4 if rgba else 3), np.uint8)
        img[..., 1] = 200
        if rgba:
            img[..., 3] = (255 * alpha[i].numpy()).astype(np.uint8)
        (root / "train").mkdir(parents=True, exist_ok=True)
        iio.imwrite(root / "train" / f"r_{i}.png", img)
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": c2w[i].double().tolist()})
    (root / "transforms_train.json").write_text(
        json.dumps({"camera_angle_x": FOV, "frames": frames})
    )
    return root


def test_a_new_runs_box_holds_its_opaque_pixels(tmp_path):
    big = _blender_cube(tmp_path / "big", 1.8)
    cfg, _ = settle_new_run(NeRFConfig(data=str(big), field="hash", device="cpu", far=8.0))
    train = load_data(cfg, "train", alpha=True)
    reach = opaque_reach(train.c2w, train.intrinsics, train.alpha, cfg.near, cfg.far, 1.5)
    assert 1.7 < reach <= 1.8
    assert cfg.aabb == math.ceil(reach * BOX_MARGIN * 1000) / 1000  # saved in config.json
    need = math.ceil(2 * math.sqrt(3) * cfg.aabb / cfg.march_step * (1 - 1e-6))
    assert need == 1024  # (the march step follows the box: 1,024 steps across its diagonal)
    # what keeps the convention's box: --aabb given, an object inside it, RGB images
    given, _ = settle_new_run(NeRFConfig(data=str(big), field="hash", device="cpu", far=8.0,
                                         aabb=1.5))  # fmt: skip
    assert given.aabb == 1.5
    small = _blender_cube(tmp_path / "small", 1.0)
    assert settle_new_run(NeRFConfig(data=str(small), field="hash", device="cpu"))[0].aabb == 1.5
    rgb = _blender_cube(tmp_path / "rgb", 1.8, rgba=False)
    cfg_rgb, train_rgb = settle_new_run(NeRFConfig(data=str(rgb), field="hash", device="cpu"))
    assert train_rgb.alpha is None and cfg_rgb.aabb == 1.5
    # a field without a box (the paper's MLP samples near..far): nothing to grow
    mlp = NeRFConfig(data=str(big), field="mlp", device="cpu")
    assert box_from_alpha(mlp, train) is None
    assert box_from_alpha(NeRFConfig(data=str(big), field="hash", aabb=1.5), train) is None
    assert box_from_alpha(NeRFConfig(data="builtin", field="hash"), train) is None
    opaque = dataclasses.replace(train, alpha=torch.ones_like(train.alpha))  # (no silhouette)
    assert box_from_alpha(NeRFConfig(data=str(big), field="hash", far=8.0), opaque) is None
    assert box_from_alpha(NeRFConfig(data=str(big), field="hash", far=8.0), train) == cfg.aabb
    # cameras a million units out (bounded at load): one line naming the data, no box
    far_away = dataclasses.replace(train, c2w=train.c2w.clone())
    far_away.c2w[:, :3, 3] *= 9e5
    with pytest.raises(UserError, match="scene box"):
        box_from_alpha(NeRFConfig(data=str(big), field="hash", far=8.0), far_away)


@pytest.mark.skipif(not (SHARED / "materials").is_dir(), reason="needs ../shared/data")
def test_the_materials_disk_asks_for_a_larger_box_and_lego_does_not():
    mat, _ = settle_new_run(NeRFConfig(data=str(SHARED / "materials"), field="hash", device="cpu"))
    assert 1.6 <= mat.aabb <= 1.7  # (the ground disk's radius is 1.6)
    lego, _ = settle_new_run(NeRFConfig(data=str(SHARED / "lego"), field="hash", device="cpu"))
    assert lego.aabb == 1.5
