"""The softplus kernels (kernels/activations.py) against their twin (warpnerf.reference) in
float64, torch's op in float32, gradcheck, the hard cases; the module switch; hash_sdf's
network gives the same values under either implementation."""

import pytest
import torch

from warpnerf import reference
from warpnerf.ops import softplus
from warpnerf.ops.activations import Softplus, activation_kernels


def _points(n, dtype, device, scale=0.1):
    g = torch.Generator().manual_seed(3)
    x = torch.randn(n, generator=g, dtype=torch.float64) * scale
    # the hard cases: the threshold's two sides, zero, huge values of both signs, tiny ones
    hard = torch.tensor([0.0, 0.2, 0.2 + 1e-9, 0.19999, -0.2, 1e30, -1e30, 3e38, -3e38,
                         1e-30, -1e-30, 0.05, -0.05, -0.3, -1.0], dtype=torch.float64)  # fmt: skip
    return torch.cat([x, hard]).to(dtype).to(device)


def test_float64_matches_the_twin_values_and_gradients(device):
    x = _points(4096, torch.float64, device).reshape(-1, 1).requires_grad_(True)
    xr = x.detach().clone().requires_grad_(True)
    y, yr = softplus(x, 100.0, 20.0), reference.softplus(xr, 100.0, 20.0)
    assert torch.allclose(y, yr, rtol=1e-13, atol=1e-300)
    w = torch.randn(y.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    (y * w.to(device)).sum().backward()
    (yr * w.to(device)).sum().backward()
    assert torch.allclose(x.grad, xr.grad, rtol=1e-13, atol=1e-300)
    assert torch.isfinite(y).all() and torch.isfinite(x.grad).all()


def test_float32_matches_torchs_op(device):
    x = _points(1 << 16, torch.float32, device)
    x = x[: x.numel() // 64 * 64].reshape(-1, 64).requires_grad_(True)
    xt = x.detach().clone().requires_grad_(True)
    y = softplus(x, 100.0)
    yt = torch.nn.functional.softplus(xt, 100.0)
    assert y.shape == x.shape
    assert torch.allclose(y, yt, rtol=2e-6, atol=1e-9)
    g = torch.rand(y.shape, generator=torch.Generator().manual_seed(2)).to(device)
    (y * g).sum().backward()
    (yt * g).sum().backward()
    assert torch.allclose(x.grad, xt.grad, rtol=2e-6, atol=1e-9)


def test_gradcheck():
    x = torch.tensor([-0.3, -0.02, 0.0, 0.013, 0.15, 0.3], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: softplus(v, 100.0, 20.0), (x,))
    assert torch.autograd.gradcheck(lambda v: softplus(v, 1.0, 20.0), (x * 10,))


def test_nan_and_inf_inputs_do_not_pass_silently():
    x = torch.tensor([float("nan"), float("inf"), -float("inf"), 0.0], requires_grad=True)
    y = softplus(x, 100.0)
    assert torch.isnan(y[0]) and y[1] == float("inf") and y[2] == 0.0
    assert y[3].item() == pytest.approx(torch.log(torch.tensor(2.0)).item() / 100.0)
    y.sum().backward()
    assert torch.isnan(x.grad[0]) and x.grad[1] == 1.0 and x.grad[2] == 0.0


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="beta"):
        softplus(torch.zeros(3), 0.0)
    with pytest.raises(ValueError, match="float32 or float64"):
        softplus(torch.zeros(3, dtype=torch.int32))
    with pytest.raises(ValueError, match="softplus"):
        with activation_kernels("fast"):
            pass


def test_empty_input():
    y = softplus(torch.zeros(0, 64), 100.0)
    assert y.shape == (0, 64)


def test_the_module_switch_and_the_sdf_network(device):
    from warpnerf.fields.hash_sdf import HashSDFField
    from warpnerf.ops.encoding import HashGrid

    m = Softplus(beta=100)
    assert not list(m.parameters()) and not m.state_dict()
    x = torch.randn(8, 4, requires_grad=True)  # (which implementation ran: the autograd node)
    assert "Softplus" in type(m(x).grad_fn).__name__ and "_Softplus" not in str(m(x).grad_fn)
    with activation_kernels("warp"):
        assert "_SoftplusBackward" in type(m(x).grad_fn).__name__
    torch.manual_seed(0)
    field = HashSDFField([-1.5] * 3 + [1.5] * 3, HashGrid(n_levels=4, log2_size=10, max_res=32))
    field = field.to(device)
    with torch.no_grad():  # (the geometric init leaves the hash columns at zero: perturb them)
        for lin in (mod for mod in field.sdf_mlp if isinstance(mod, torch.nn.Linear)):
            lin.weight.add_(0.05 * torch.randn_like(lin.weight))
    p = (torch.rand(2000, 3) * 3 - 1.5).to(device)
    d0 = field.sdf(p)
    params = [*field.sdf_mlp.parameters(), *field.encoding.parameters()]
    g0 = torch.autograd.grad(d0.sum(), params)
    with activation_kernels("warp"):
        d1 = field.sdf(p)
        g1 = torch.autograd.grad(d1.sum(), params)
    assert torch.allclose(d0, d1, rtol=1e-5, atol=1e-6)
    for a, b in zip(g0, g1):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-6)
