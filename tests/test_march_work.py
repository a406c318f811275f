"""What the marcher skips must not change what it emits (kernels/occupancy.py): each ray cut to
the box of the occupied cells (``occupied_cells``) gives the same bits as the uncut march, for
grids from empty to full, one corner cell, a small cluster; packed, in rounds (``k_begin`` and
``max_samples``), into a fixed capacity that cuts rays short, with hard rays (axis-parallel,
grazing, inside, missing) included."""

from __future__ import annotations

import pytest
import torch

from warpnerf.occupancy import OccupancyGrid
from warpnerf.ops import occupancy as O
from warpnerf.reference import occupancy as R

from ._twin import assert_matches_twin
from .test_occupancy import BOX, hard_rays


def _same(a, b):
    sa, ka = a[0], a[1]
    sb, kb = b[0], b[1]
    for name in ("t_starts", "t_ends", "ray_indices", "packed_info"):
        x, y = getattr(sa, name), getattr(sb, name)
        assert x.shape == y.shape and torch.equal(x, y), name
    assert torch.equal(ka, kb)
    if len(a) > 2:  # the fixed-capacity path's stats
        assert torch.equal(a[2], b[2])


def _grids(res, device):
    """Bitfields: empty, full, sparse random, one corner cell, one inner cell, a small cluster."""
    n = res**3
    out = {"empty": torch.zeros(n), "full": torch.ones(n)}
    g = torch.Generator().manual_seed(7)
    out["sparse"] = (torch.rand(n, generator=g) < 0.02).float()
    one = torch.zeros(res, res, res)
    one[res - 1, 0, res - 1] = 1.0
    out["corner"] = one.reshape(-1).clone()
    one.zero_()
    one[res // 2, res // 2 - 1, 1] = 1.0
    out["inner"] = one.reshape(-1).clone()
    one.zero_()
    one[2:4, 3:6, 4:5] = 1.0
    out["cluster"] = one.reshape(-1)
    return {k: O.grid_pack_bits(v.to(device), 0.5) for k, v in out.items()}


def _brute_occupied(bits, res):
    idx = torch.nonzero(O.unpack_bits(bits).reshape(res, res, res))
    if not len(idx):
        return None
    return idx.amin(0).tolist() + (idx.amax(0) + 1).tolist()


@pytest.mark.parametrize("res", [2, 8, 16])
def test_occupied_cells_is_the_box_of_the_occupied_cells(device, res):
    for name, bits in _grids(res, device).items():
        occ = O.occupied_cells(bits, res)
        assert occ.dtype == torch.int32 and occ.shape == (6,) and occ.device == bits.device
        want = _brute_occupied(bits, res)
        if want is None:
            assert bool((occ[:3] >= occ[3:]).all()), name
        else:
            assert occ.tolist() == want, name
    with pytest.raises(ValueError):
        O.occupied_cells(bits, res + 2)


@pytest.mark.parametrize("res", [8, 16])
def test_march_cut_to_the_occupied_box_is_the_same(device, res):
    o, d = hard_rays(160, device, seed=6)
    jit = torch.rand(160, device=device)
    kb = torch.randint(-1, 60, (160,), device=device, dtype=torch.int32)
    for name, bits in _grids(res, device).items():
        occ = O.occupied_cells(bits, res)
        for dt in (0.013, 0.3):  # steps far below a cell and longer than one
            for kw in ({"jitter": jit}, {"max_samples": 4, "k_begin": kb}, {"capacity": 300}):
                want = O.march_rays(o, d, 0.5, 9.0, bits, res, BOX, dt, **kw)
                got = O.march_rays(o, d, 0.5, 9.0, bits, res, BOX, dt, occupied=occ, **kw)
                _same(got, want)
        if name == "cluster":  # the cut march against the float64 brute force too
            assert_matches_twin(
                lambda o, d, b=bits, c=occ: O.march_rays(
                    o, d, 0.5, 9.0, b, res, BOX, 0.013, occupied=c
                ),
                lambda o, d, b=bits: R.march_rays(o, d, 0.5, 9.0, b, res, BOX, 0.013),
                {"o": o, "d": d},
                names=("samples", "k"),
                tol={"rtol": 0.0, "atol": 2e-6},
            )


def test_march_cut_in_rounds_is_the_same(device):
    res = 16
    bits = _grids(res, device)["cluster"]
    occ = O.occupied_cells(bits, res)
    o, d = hard_rays(64, device, seed=2)
    k = k_cut = None
    for _ in range(100):
        s, k = O.march_rays(o, d, 0.0, 9.0, bits, res, BOX, 0.01, k_begin=k, max_samples=3)
        s_cut, k_cut = O.march_rays(o, d, 0.0, 9.0, bits, res, BOX, 0.01, k_begin=k_cut,
                                    max_samples=3, occupied=occ)  # fmt: skip
        _same((s_cut, k_cut), (s, k))
        if bool((k < 0).all()):
            break
    assert bool((k < 0).all())


def test_grid_keeps_its_occupied_box_with_its_bits(device):
    g = OccupancyGrid(BOX, 8, dt=0.05).to(device)
    assert g.occupied.tolist() == [0, 0, 0, 8, 8, 8]  # everything counts as occupied at first
    assert "occupied" not in g.state_dict()  # derived: never saved

    def ball(x):
        return (x.norm(dim=-1) < 0.3).float() * 100.0

    g.update(ball)
    assert g.occupied.tolist() == _brute_occupied(g.bits, 8)
    assert g.occupied.tolist() != [0, 0, 0, 8, 8, 8]
    h = OccupancyGrid(BOX, 8, dt=0.05).to(device)
    h.load_state_dict(g.state_dict())
    assert h.occupied.tolist() == g.occupied.tolist()
    # the grid's march (cut) equals the uncut march of its bits
    o, d = hard_rays(80, device, seed=3)
    want = O.march_rays(o, d, 0.0, 9.0, g.bits, 8, BOX, 0.05)
    _same(g.march(o, d, 0.0, 9.0), want)
