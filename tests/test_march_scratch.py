"""The marcher's scratch (kernels/occupancy.py): the count pass keeps each ray's first S intervals
and the fill pass copies them instead of marching again. Whatever S is (none, smaller than most
rays' counts, larger than all), the outputs are the same bits: packed, in rounds (``k_begin`` and
``max_samples``), into a fixed capacity that cuts rays short, bounded and contracted, hard rays
(axis-parallel, grazing, inside, missing) included."""

from __future__ import annotations

import pytest
import torch

from warpnerf.ops import occupancy as O

from .test_occupancy import BOX, hard_rays, random_bits

SIZES = (0, 1, 3, 16, 4096)


def _same(a, b):
    sa, ka = a[0], a[1]
    sb, kb = b[0], b[1]
    for name in ("t_starts", "t_ends", "ray_indices", "packed_info"):
        x, y = getattr(sa, name), getattr(sb, name)
        assert x.shape == y.shape and torch.equal(x, y), name
    assert torch.equal(ka, kb)
    if len(a) > 2:  # the fixed-capacity path's stats
        assert torch.equal(a[2], b[2])


def _with_scratch(monkeypatch, s, fn):
    monkeypatch.setattr(O, "MARCH_SCRATCH", s)
    return fn()


@pytest.mark.parametrize("frac", [0.1, 0.6])
def test_bounded_march_is_the_same_with_any_scratch(device, monkeypatch, frac):
    res = 8
    bits = random_bits(res, frac, device, seed=2)
    o, d = hard_rays(120, device, seed=4)
    jit = torch.rand(120, device=device)
    kb = torch.randint(-1, 40, (120,), device=device, dtype=torch.int32)
    cases = [
        lambda: O.march_rays(o, d, 0.5, 9.0, bits, res, BOX, 0.013, jitter=jit),
        lambda: O.march_rays(o, d, 0.5, 9.0, bits, res, BOX, 0.013, max_samples=7),
        # rounds: resume where the last call stopped
        lambda: O.march_rays(o, d, 0.5, 9.0, bits, res, BOX, 0.013, max_samples=5, k_begin=kb),
        # a fixed capacity smaller than the samples: later rays lose theirs
        lambda: O.march_rays(o, d, 0.5, 9.0, bits, res, BOX, 0.013, capacity=500),
    ]
    for case in cases:
        want = _with_scratch(monkeypatch, 0, case)  # (the fill pass marches every ray again)
        counts = want[0].packed_info[:, 1]
        assert int(counts.max()) > 3  # some rays overflow the small scratches
        for s in SIZES[1:]:
            _same(_with_scratch(monkeypatch, s, case), want)


def test_contracted_march_is_the_same_with_any_scratch(device, monkeypatch):
    res, a, dt, cone = 16, 1.0, 0.01, 0.004
    g = torch.Generator().manual_seed(5)
    dens = torch.rand(res**3, generator=g) * (torch.rand(res**3, generator=g) < 0.3)
    bits = O.grid_pack_bits(dens.to(device), 0.0)
    o = (torch.randn(64, 3, generator=g) * 0.5).to(device)
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=g), dim=-1).to(device)

    def case():
        return O.march_rays_contracted(o, d, 0.05, 500.0, bits, res, a, dt, cone, max_samples=64)

    want = _with_scratch(monkeypatch, 0, case)
    assert int(want[0].packed_info[:, 1].max()) > 16
    for s in SIZES[1:]:
        _same(_with_scratch(monkeypatch, s, case), want)


def test_scratch_is_bounded_by_the_launch():
    """A launch's scratch stays within MARCH_SCRATCH_SLOTS (so ray * S fits int32) and shrinks
    to none for the largest launches."""
    assert O.march_scratch(1000, 16) == 16
    big = O.MARCH_SCRATCH_SLOTS // 4
    assert O.march_scratch(big, 16) == 4
    assert O.march_scratch(O.MARCH_SCRATCH_SLOTS + 1, 16) == 0
    assert O.march_scratch(0, 16) == 16
    assert O.march_scratch(10, per_ray=0) == 0
    assert O.march_scratch(10) == O.MARCH_SCRATCH
    for n in (1, 7, 10**6, 2**31 - 1):
        assert n * O.march_scratch(n, 16) <= O.MARCH_SCRATCH_SLOTS < 2**31
