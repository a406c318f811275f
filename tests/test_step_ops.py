"""Less work per static-shape step (issue 47 item 2): the kernels that replace torch's per-sample
gathers (sample_points; live_samples_fixed's compaction with the kept points and directions)
equal their twins bitwise, the fused ReLU backward equals the comparison-and-where it replaced,
and --mlp-precision bf16/fp16 trains inside the static body, close to float32."""

from __future__ import annotations

import pytest
import torch

from tests.test_graph_step import _params, _task, _train
from warpnerf.errors import UserError
from warpnerf.fields.mlp import _LinearReLU, mlp_precision
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


def test_sh_concat_equals_the_twin_and_the_fields_torch_path(device):
    """[features | SH(d)] in one kernel: the twin's values (bitwise on CPU) for every degree,
    the features' gradient passed through, directions with a gradient refused; the hash
    field's colours are the same by either path (directions with a gradient take torch's)."""
    from warpnerf.fields.hash_nerf import HashNeRFField
    from warpnerf.ops.encoding import HashGrid, sh_concat
    from warpnerf.reference.encoding import sh_concat as twin

    g = torch.Generator().manual_seed(1)
    d = torch.nn.functional.normalize(torch.randn(5000, 3, generator=g), dim=-1).to(device)
    d[0] = torch.tensor([0.0, 0.0, 1.0])  # (poles and axes)
    d[1] = torch.tensor([-1.0, 0.0, 0.0])
    h = torch.randn(5000, 16, generator=g).to(device)
    for degree in (1, 2, 3, 4):
        got, want = sh_concat(h, d, degree), twin(h, d, degree)
        assert got.shape == (5000, 16 + degree * degree)
        if device.type == "cpu":
            assert torch.equal(got, want)
        else:  # (the kernel may fuse multiply-adds)
            torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)
    hg = h.clone().requires_grad_(True)
    v = torch.randn(5000, 32, generator=g).to(device)
    (sh_concat(hg, d) * v).sum().backward()
    assert torch.equal(hg.grad, v[:, :16])
    with pytest.raises(ValueError, match="no gradient"):
        sh_concat(h, d.clone().requires_grad_(True))
    field = HashNeRFField([-1.0] * 3 + [1.0] * 3, HashGrid(n_levels=2, log2_size=8),
                          hidden=16).to(device)  # fmt: skip
    feats = torch.randn(64, 16, generator=g).to(device)
    fast = field.color(feats, d[:64])
    slow = field.color(feats, d[:64].clone().requires_grad_(True))
    torch.testing.assert_close(fast, slow, rtol=0, atol=0 if device.type == "cpu" else 1e-6)


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


@pytest.mark.parametrize("precision", ["bf16", "fp16"])
def test_half_precision_mlps_train_in_the_static_body_close_to_float32(precision):
    """--mlp-precision: the hash field's MLPs under autocast in the training step (eager and
    the static body alike), float32 again outside it; a few steps stay close to float32's."""
    base = _task("cpu")
    lf, _, _ = _train(base, 6, static=True, force=(4096, 1 << 16, 1 << 15))
    eager, static = _task("cpu", mlp_precision=precision), _task("cpu", mlp_precision=precision)
    le, _, _ = _train(eager, 6)
    ls, _, _ = _train(static, 6, static=True, force=(4096, 1 << 16, 1 << 15))
    assert static.model.coarse.mlp_dtype is None  # (only inside the step)
    assert ls == pytest.approx(le, rel=1e-4)
    assert ls == pytest.approx(lf, rel=2e-3) and ls != lf  # (it did run in half precision)
    # (Adam with eps 1e-15 moves a parameter by ~lr whatever its gradient's size: a tiny
    # gradient whose sign half precision flips moves it the other way; the bulk stays close)
    diff = (_params(static) - _params(base)).abs()
    assert float(diff.mean()) < 5e-4  # (measured: bf16 6e-5, fp16 7e-6)


def test_fp16_mlp_gradients_do_not_flush_to_zero(monkeypatch):
    """Gradients below fp16's smallest normal number (a step's, ~1e-6 at the MLP's output)
    come through the fp16 MLP scaled inside it and unscaled exactly: within 0.5% of float32's,
    where without the scale they are ~10% off (subnormal in fp16)."""
    import warpnerf.fields.mlp as M

    torch.manual_seed(0)
    mlp = torch.nn.Sequential(torch.nn.Linear(32, 64), torch.nn.ReLU(), torch.nn.Linear(64, 16))
    x = torch.randn(256, 32) * 1e-2

    def grads(dtype):
        xi = x.clone().requires_grad_(True)
        mlp.zero_grad()
        (M.run_mlp(mlp, xi, dtype).sum() * 1e-6).backward()
        return xi.grad, mlp[0].weight.grad.clone()

    def error(got, want):
        return max(float((a - b).abs().max() / b.abs().max()) for a, b in zip(got, want))

    want = grads(None)
    scaled = error(grads(torch.float16), want)
    monkeypatch.setattr(M, "FP16_GRAD_SCALE", 1.0)
    unscaled = error(grads(torch.float16), want)
    assert scaled < 5e-3 and unscaled > 10 * scaled, (scaled, unscaled)


def test_mlp_precision_is_refused_where_the_field_has_none():
    with pytest.raises(UserError, match="--mlp-precision bf16 needs --field hash"):
        _task("cpu", field="hash_sdf", mlp_precision="bf16")
    field = torch.nn.Linear(2, 2)
    with mlp_precision(field, "fp32"):  # (float32: nothing to switch)
        pass
    with pytest.raises(ValueError, match="no half-precision"), mlp_precision(field, "bf16"):
        pass
    with pytest.raises(ValueError, match="one of"), mlp_precision(field, "fp8"):
        pass
