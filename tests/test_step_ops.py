"""Less work per static-shape step (issue 47 item 2): the kernels that replace torch's per-sample
gathers (sample_points; live_samples_fixed's compaction with the kept points and directions)
equal their twins bitwise, and the fused ReLU backward equals the comparison-and-where it
replaced."""

from __future__ import annotations

import pytest
import torch

from warpnerf.fields.mlp import _LinearReLU
from warpnerf.ops import occupancy as O
from warpnerf.reference import occupancy as R

BOX = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]


def _marched(device, capacity: int):
    """Fixed-capacity samples of 48 rays through a random grid (some rays miss the box, one is
    an unused slot with far = near), their densities (a transparent and an opaque ray)."""
    g = torch.Generator().manual_seed(2)
    n = 48
    o = (torch.rand(n, 3, generator=g) * 2 - 1) * 0.5 + torch.tensor([0.0, 0.0, -3.0])
    d = torch.nn.functional.normalize(torch.rand(n, 3, generator=g) - 0.5 + torch.tensor(
        [0.0, 0.0, 1.0]), dim=-1)  # fmt: skip
    d[:4] = torch.tensor([1.0, 0.0, 0.0])  # (these miss the box)
    res = 16
    occ = torch.rand(res**3, generator=g) < 0.5
    bits = (occ.reshape(-1, 8).to(torch.uint8) << torch.arange(8, dtype=torch.uint8)).sum(-1)
    bits = bits.to(torch.uint8).to(device)
    o, d = o.to(device), d.to(device)
    far = torch.full((n,), 6.0, device=device)
    far[5] = 0.5  # an unused slot: no samples
    jitter = torch.rand(n, generator=g).to(device)
    smp, _, _ = O.march_rays(o, d, 0.5, far, bits, res, BOX, 0.05, jitter=jitter,
                             capacity=capacity)  # fmt: skip
    sig = torch.exp(torch.rand(capacity, generator=g) * 6 - 3).to(device)
    ri = smp.ray_indices.long()
    sig[ri == 7] = 0.0  # a transparent ray
    sig[ri == 8] = 1e8  # an opaque one
    return smp, sig, o, d


def test_sample_points_equal_the_twin(device):
    smp, _, o, d = _marched(device, 4096)
    got = O.sample_points(smp, o, d)
    want = R.sample_points(smp, o, d)
    if device.type == "cpu":
        assert torch.equal(got, want)
    else:  # (the kernel may fuse the multiply-add)
        torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)
    # unused slots (t = 0 on ray 0) hold ray 0's origin
    n_marched = int(smp.packed_info[:, 1].sum())
    assert torch.equal(got[n_marched:], o[:1].expand(4096 - n_marched, 3))


@pytest.mark.parametrize("capacity", [4096, 300, 7])
def test_live_compaction_equals_the_twin_bitwise(device, capacity):
    """Room for everything, a full buffer (rays past it keep fewer or none) and a tiny one: the
    kept slots, their sources, counts and the gathered points and directions are the twin's."""
    smp, sig, o, d = _marched(device, 4096)
    pos = O.sample_points(smp, o, d)
    got = O.live_samples_fixed(smp, sig, 1e-4, capacity, positions=pos, directions=d)
    want = R.live_samples_fixed(smp, sig, 1e-4, capacity, positions=pos, directions=d)
    kept, src, stats, kp, kd = got
    for a, b in zip((*kept, src, stats, kp, kd), (*want[0], *want[1:])):
        assert a.dtype == b.dtype and torch.equal(a, b)
    assert kp.shape == (capacity, 3) and kd.shape == (capacity, 3)
    live = int(stats[0])
    assert (int(stats[1]) > 0) == (live > capacity)
    # without positions: the same slots, no gathers
    bare = O.live_samples_fixed(smp, sig, 1e-4, capacity)
    assert all(torch.equal(a, b) for a, b in zip((*bare[0], bare[1]), (*kept, src)))
    assert bare[3] is None and bare[4] is None


def test_fused_relu_backward_equals_the_mask_and_where():
    g = torch.Generator().manual_seed(0)
    for dt in (torch.float32, torch.float64):
        x = torch.randn(500, 32, generator=g, dtype=dt, requires_grad=True)
        w = torch.randn(64, 32, generator=g, dtype=dt, requires_grad=True)
        b = torch.randn(64, generator=g, dtype=dt, requires_grad=True)
        y = _LinearReLU.apply(x, w, b)
        v = torch.randn(y.shape, generator=g, dtype=dt)
        y.backward(v)
        mask = torch.where(y > 0, v, torch.zeros_like(v)).detach()  # (the replaced formula)
        assert torch.equal(x.grad, mask @ w.detach())
        assert torch.equal(w.grad, mask.t() @ x.detach())
        assert torch.equal(b.grad, mask.sum(0))
