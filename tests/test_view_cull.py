"""View culling of the occupancy grid (--view-cull, issue 44): the cells no training camera sees
are empty from the start and stay empty. The vectorised rule equals its cell-by-cell twin (a
bounded, a contracted and an NDC grid; cameras looking in, one looking away, an axis-parallel one,
one inside the box); no point of a culled cell is on any camera's ray (rays through the image's
pixels and edges, every distance); the grid keeps culled cells empty through its updates; the
mask is saved, restored on resume, and an older grid without it loads (nothing culled)."""

from __future__ import annotations

import json
import math

import pytest
import torch

from warpnerf.cli import main
from warpnerf.data.cameras import frustum_bounds, look_at, ndc_rays
from warpnerf.occupancy import OccupancyGrid, seen_cells
from warpnerf.ops import occupancy as O
from warpnerf.reference import view_cull as R
from warpnerf.reference.rays import generate_rays

from .test_capture import _colmap_capture, _object_cameras

A = 1.0  # the bounded box's half-size, a contracted grid's inner half-size
W, H = 32, 24
NDC = [40.0, 40.0, 32.0, 24.0]  # the NDC camera (fx, fy, W, H)
KINDS = {  # grid box and seen_cells' keywords
    "box": ([-A] * 3 + [A] * 3, {}),
    "contract": ([-2 * A] * 3 + [2 * A] * 3, {"contract": A}),
    "ndc": ([-1.5, -1.5, -1.0, 1.5, 1.5, 1.0], {"ndc": NDC}),
}


def _cameras(kind: str):
    """c2w [N, 4, 4], intrinsics [N, 4]: two narrow cameras looking at the box from outside, one
    looking away from it, one axis-parallel (an exact identity rotation, looking down -z) and
    one inside the box whose axes are a permutation of the world's (NDC: a forward-facing set
    in front of the scene, one of them turned away)."""
    if kind == "ndc":
        cams = []
        for i, yaw in enumerate((0.0, 0.15, -0.1, math.pi)):
            m = torch.eye(4, dtype=torch.float64)
            c, s = math.cos(yaw), math.sin(yaw)
            m[:3, :3] = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)
            m[:3, 3] = torch.tensor([0.3 * i - 0.4, 0.1 * i, 0.05 * i])
            cams.append(m)
    else:
        cams = [look_at((3.1, 0.4, 1.2), (0.1, 0.0, 0.0), dtype=torch.float64),
                look_at((-0.7, -2.9, 0.8), (0.0, 0.2, 0.1), dtype=torch.float64),
                look_at((0.2, 0.1, 2.5), (0.5, 0.3, 6.0), dtype=torch.float64)]  # fmt: skip
        axis = torch.eye(4, dtype=torch.float64)
        axis[:3, 3] = torch.tensor([0.31, -0.23, 2.7])
        inside = torch.eye(4, dtype=torch.float64)[[1, 2, 0, 3]]
        inside[:3, 3] = torch.tensor([-0.13, 0.27, 0.19])
        cams += [axis, inside]
    c2w = torch.stack(cams)
    k = torch.tensor([[70.0, 64.0, 15.3, 12.4]], dtype=torch.float64).repeat(len(cams), 1)
    if kind == "ndc":
        k[:, :2] = 40.0
    return c2w, k


@pytest.mark.parametrize("res", [8, 10])
@pytest.mark.parametrize("kind", ["box", "contract", "ndc"])
def test_seen_cells_equal_the_twin(device, kind, res):
    """The vectorised rule (closed-form plane tests, cameras in groups, chunks of cells) marks
    exactly the cells of the cell-by-cell twin; some cells are culled and some kept."""
    box, kw = KINDS[kind]
    c2w, k = _cameras(kind)
    bounds = frustum_bounds(k, W, H)
    want = R.seen_cells(res, box, c2w, bounds, **kw)
    got = seen_cells(res, box, c2w.to(device), bounds.to(device), chunk=4000, **kw)
    assert got.device.type == device.type
    assert torch.equal(got.cpu(), want)
    assert 0.05 < float(want.float().mean()) < 0.95  # both kinds of cell are there
    each = [R.seen_cells(res, box, c2w[i : i + 1], bounds[i : i + 1], **kw)
            for i in range(len(c2w))]  # fmt: skip
    assert torch.equal(want, torch.stack(each).any(0))  # seen: seen by some camera
    if kind != "contract":  # the camera looking away from the scene sees none of it
        assert not bool(each[2 if kind == "box" else 3].any())


def _cell_of(points, res: int, box) -> torch.Tensor:
    lo, hi = torch.tensor(box[:3]).double(), torch.tensor(box[3:]).double()
    ijk = ((points - lo) / (hi - lo) * res).floor().long().clamp(0, res - 1)
    return (ijk[:, 0] * res + ijk[:, 1]) * res + ijk[:, 2]


@pytest.mark.parametrize("kind", ["box", "contract", "ndc"])
def test_no_culled_cell_holds_a_point_a_camera_sees(kind):
    """Points along every camera's rays (through the image's corners, edges and a lattice of
    pixels, from the camera to far beyond the scene) lie only in kept cells; and each kept cell
    of a bounded grid touches a cell that such a point lies in (the rule's slack is at most a
    cell along the frustums' sides)."""
    res = 10
    box, kw = KINDS[kind]
    c2w, k = _cameras(kind)
    seen = R.seen_cells(res, box, c2w, frustum_bounds(k, W, H), **kw)
    n = 17
    f64 = torch.float64
    px, py = torch.meshgrid(torch.linspace(0, W, n, dtype=f64), torch.linspace(0, H, n, dtype=f64),
                            indexing="ij")  # fmt: skip
    cam = torch.arange(len(c2w)).repeat_interleave(n * n)
    o, d = generate_rays(c2w, k, cam_idx=cam, px=px.reshape(-1).repeat(len(c2w)),
                         py=py.reshape(-1).repeat(len(c2w)))  # fmt: skip
    if kind == "ndc":
        front = d[:, 2] < -1e-3  # (rays that never reach the NDC slab have no NDC ray)
        o, d = ndc_rays(o[front].float(), d[front].float(), NDC)
        o, d = o.double(), d.double()
        t = torch.linspace(0, 4, 1000, dtype=torch.float64)
    elif kind == "contract":
        t = torch.logspace(-4, 7, 1000, dtype=torch.float64)
    else:
        t = torch.linspace(0, 8, 1000, dtype=torch.float64)
    x = (o[:, None] + t[:, None] * d[:, None]).reshape(-1, 3)
    if kind == "contract":
        x = O.contract_points(x, A)
    lo, hi = torch.tensor(box[:3]).double(), torch.tensor(box[3:]).double()
    x = x[((x >= lo) & (x <= hi)).all(-1)]
    hit = torch.zeros(res**3, dtype=torch.bool)
    hit[_cell_of(x, res, box)] = True
    assert bool(hit.any())
    assert bool(seen[hit].all())  # sound: what a ray passes through is never culled
    if kind == "box":  # tight: a kept cell lies next to a cell that a ray passes through
        near = torch.nn.functional.max_pool3d(hit.reshape(1, res, res, res).float(), 3, 1, 1)
        assert bool(near.reshape(-1).bool()[seen].all())


class _Everywhere(torch.nn.Module):
    """A density of 5 everywhere."""

    def forward(self, x):
        return torch.full_like(x[:, 0], 5.0)


def test_grid_keeps_culled_cells_empty(device):
    """cull() marks the unseen cells empty at once (bits off, density 0); every update, the
    warm-up's over all cells and the later random subsets, leaves them so (a field with
    density everywhere occupies exactly the seen cells); the culled fraction is returned."""
    res = 8
    box, _ = KINDS["box"]
    c2w, k = _cameras("box")
    grid = OccupancyGrid(box, res, dt=0.01, warmup=1).to(device)
    culled = grid.cull(c2w.float(), k.float(), W, H)
    want = R.seen_cells(res, box, c2w, frustum_bounds(k, W, H))
    assert torch.equal(grid.seen.cpu(), want)
    assert culled == pytest.approx(1 - float(want.float().mean()))
    assert torch.equal(O.unpack_bits(grid.bits).cpu(), want)  # empty from the start
    gen = torch.Generator(device=device).manual_seed(0)
    for _ in range(4):
        grid.update(_Everywhere(), gen)
        assert torch.equal(O.unpack_bits(grid.bits).cpu(), want)
        assert not bool(grid.density[~grid.seen].any())
        assert bool((grid.density[grid.seen] > 0).any())
    bits = grid.bits.clone()
    grid.cull(c2w[:1].float(), k[:1].float(), W, H)  # culling again narrows the mask further
    assert torch.equal(grid.seen.cpu(), want & R.seen_cells(res, box, c2w[:1], frustum_bounds(
        k[:1], W, H)))  # fmt: skip
    assert torch.equal(grid.bits, bits & O.grid_pack_bits(grid.seen.float(), 0.5))


def test_mask_is_saved_and_older_grids_load():
    """The mask is a buffer of the grid's state: saved, and restored by a strict load; a state
    saved before it existed loads with every cell seen, while other missing entries still
    fail."""
    box, _ = KINDS["box"]
    c2w, k = _cameras("box")
    grid = OccupancyGrid(box, 8, dt=0.01)
    grid.cull(c2w.float(), k.float(), W, H)
    state = grid.state_dict()
    assert "seen" in state and not bool(state["seen"].all())
    fresh = OccupancyGrid(box, 8, dt=0.01)
    fresh.load_state_dict(state)
    assert torch.equal(fresh.seen, grid.seen) and torch.equal(fresh.bits, grid.bits)
    old = {key: v for key, v in state.items() if key != "seen"}
    fresh.load_state_dict(old)  # strict: no error
    assert bool(fresh.seen.all())
    with pytest.raises(RuntimeError, match="density"):
        fresh.load_state_dict({key: v for key, v in old.items() if key != "density"})


def test_distorted_cameras_widen_their_frustum():
    """Barrel distortion: the undistorted rays through the border reach further than the
    pinhole's; the bounds hold every undistorted border ray (and equal the pinhole's without
    distortion)."""
    from warpnerf.data.cameras import undistort_points

    k = torch.tensor([[20.0, 21.0, 12.3, 7.8]], dtype=torch.float64)
    plain = frustum_bounds(k, 24, 16)
    assert torch.equal(plain, frustum_bounds(k, 24, 16, torch.zeros(1, 4)))
    torch.testing.assert_close(plain[0], torch.tensor([-12.3 / 20, 11.7 / 20, -8.2 / 21,
                                                       7.8 / 21], dtype=torch.float64))  # fmt: skip
    dist = torch.tensor([[-0.1, 0.02, 0.005, -0.004]])
    b = frustum_bounds(k, 24, 16, dist)[0]
    assert bool((b[[1, 3]] > plain[0, [1, 3]]).all() & (b[[0, 2]] < plain[0, [0, 2]]).all())
    t = torch.rand(2000, dtype=torch.float64)
    side = torch.randint(4, (2000,))
    px = torch.where(side < 2, t * 24, (side == 3) * 24.0)
    py = torch.where(side < 2, (side == 1) * 16.0, t * 16)
    x, y = undistort_points((px - 12.3) / 20, (py - 7.8) / 21, dist[0])
    assert bool(((x >= b[0]) & (x <= b[1]) & (-y >= b[2]) & (-y <= b[3])).all())


def test_contracted_capture_trains_with_view_culling_and_resumes(tmp_path):
    """A few steps on an inward-facing capture (contracted grid) with --view-cull: the saved
    grid holds the mask (some cells culled, none of them occupied); a resume keeps it as saved;
    the run's checkpoint without the mask (as written before it) still loads and resumes,
    nothing culled."""
    from warpnerf.train.nerf import load_run

    _colmap_capture(tmp_path / "obj", _object_cameras(8))
    args = ["train", "nerf", "--data", str(tmp_path / "obj"), "--field", "hash",
            "--batch", "24", "--val-every", "3", "--val-images", "1", "--hash-levels", "4",
            "--hash-log2-size", "10", "--grid-res", "8", "--grid-every", "2",
            "--grid-warmup", "2", "--max-samples", "256", "--quiet", "--view-cull",
            "--iters", "4", "--out", str(tmp_path / "a")]  # fmt: skip
    assert main(args) == 0
    cfg = json.loads((tmp_path / "a" / "config.json").read_text())
    assert cfg["contract"] == "on" and cfg["view_cull"] is True
    path = tmp_path / "a" / "checkpoint.pt"
    grid = torch.load(path, weights_only=True)["fields"]["grid"]
    seen = grid["seen"]
    assert 0 < float((~seen).float().mean()) < 1
    assert not bool(O.unpack_bits(grid["bits"])[~seen].any())
    assert not bool(grid["density"][~seen].any())
    assert main(["train", "nerf", "--out", str(tmp_path / "a"), "--resume", "--iters", "6",
                 "--quiet"]) == 0  # fmt: skip
    again = torch.load(path, weights_only=True)
    assert again["step"] == 6 and torch.equal(again["fields"]["grid"]["seen"], seen)
    assert not bool(O.unpack_bits(again["fields"]["grid"]["bits"])[~seen].any())
    del again["fields"]["grid"]["seen"]  # as saved before the mask existed
    torch.save(again, path)
    _, model, _ = load_run(tmp_path / "a")
    assert bool(model.grid.seen.all())
    assert main(["train", "nerf", "--out", str(tmp_path / "a"), "--resume", "--iters", "8",
                 "--quiet"]) == 0  # fmt: skip
    assert bool(torch.load(path, weights_only=True)["fields"]["grid"]["seen"].all())


def test_resume_with_view_culling_continues_exactly(tmp_path):
    """Three training images of the built-in scene leave cells unseen: a run stopped and resumed
    trains exactly as one that went straight through, with the same mask."""
    from warpnerf.train.nerf import train_nerf

    from .test_nerf import GRID, tiny

    kw = dict(GRID, view_cull=True, max_images=3)
    quiet = dict(progress=False, log=lambda *a: 0)
    straight = train_nerf(tiny(**kw), tmp_path / "a", **quiet)
    train_nerf(tiny(iters=3, lr_decay_steps=6, **kw), tmp_path / "b", **quiet)
    resumed = train_nerf(tiny(iters=6), tmp_path / "b", resume=True, **quiet)
    assert resumed["loss"] == straight["loss"]
    a, b = (torch.load(tmp_path / r / "checkpoint.pt", weights_only=True)["fields"]["grid"]
            for r in "ab")  # fmt: skip
    assert not bool(a["seen"].all()) and bool(a["seen"].any())
    for key, v in a.items():
        assert torch.equal(v, b[key]), key


def test_forward_facing_capture_trains_with_view_culling(tmp_path):
    """An NDC run (forward-facing LLFF capture) culls in NDC space and trains."""
    from .test_capture import _forward_cameras, _llff_capture

    _llff_capture(tmp_path / "ff", _forward_cameras(9), 20.0, [10.0, 40.0])
    args = ["train", "nerf", "--data", str(tmp_path / "ff"), "--field", "hash", "--batch", "24",
            "--val-images", "0", "--hash-levels", "4", "--hash-log2-size", "10",
            "--grid-res", "8", "--grid-every", "2", "--grid-warmup", "2", "--quiet",
            "--view-cull", "--iters", "2", "--out", str(tmp_path / "r")]  # fmt: skip
    assert main(args) == 0
    cfg = json.loads((tmp_path / "r" / "config.json").read_text())
    assert cfg["scene"]["ndc"] is not None and cfg["view_cull"] is True
    grid = torch.load(tmp_path / "r" / "checkpoint.pt", weights_only=True)["fields"]["grid"]
    assert bool(grid["seen"].any()) and not bool(grid["seen"].all())  # NDC x, y beyond the views
    assert not bool(O.unpack_bits(grid["bits"])[~grid["seen"]].any())
