import torch

from warpnerf import SDFVolume, laplace_cdf
from warpnerf.fields import sdf_box, sdf_sphere, sdf_torus

from ._twin import gradcheck_op


def test_laplace_cdf_closed_form_and_symmetry():
    s = torch.linspace(-1, 1, 101, dtype=torch.float64)
    beta = 0.1
    want = torch.where(s <= 0, 0.5 * torch.exp(s / beta), 1 - 0.5 * torch.exp(-s / beta))
    assert torch.allclose(laplace_cdf(s, beta), want, atol=0, rtol=1e-15)
    assert torch.allclose(laplace_cdf(s, beta) + laplace_cdf(-s, beta), torch.ones_like(s))


def test_laplace_cdf_tiny_beta_no_overflow_no_nan_grad():
    s = torch.tensor(
        [-1e3, -1.0, -1e-9, 0.0, 1e-9, 1.0, 1e3], dtype=torch.float64, requires_grad=True
    )
    for beta in (1e-2, 1e-6, 1e-12):
        y = laplace_cdf(s, beta)
        (g,) = torch.autograd.grad(y.sum(), s)
        assert torch.isfinite(y).all() and torch.isfinite(g).all()
        assert float(y[0].detach()) == 0.0 and float(y[-1].detach()) == 1.0
        # Derivative at 0 is the Laplace density at 0: 1 / (2 beta).
        assert abs(float(g[3]) - 0.5 / beta) <= 1e-9 * 0.5 / beta


def test_laplace_cdf_gradcheck():
    s = torch.tensor([-0.3, -0.01, 0.02, 0.4], dtype=torch.float64)
    gradcheck_op(lambda s: laplace_cdf(s, 0.1), {"s": s}, ["s"])


def test_sdfs_exact_values():
    p = torch.tensor(
        [[2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.25, 0, 0]], dtype=torch.float64
    )
    c = torch.zeros(3, dtype=torch.float64)
    box = sdf_box(p, c, torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64))
    assert torch.allclose(box, torch.tensor([1.5, -0.5, 2**0.5 / 2, -0.25], dtype=torch.float64))
    assert torch.allclose(sdf_sphere(p, c, 0.5), p.norm(dim=-1) - 0.5)
    torus = sdf_torus(
        torch.tensor([[0.6, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64), c, 0.6, 0.25
    )
    assert torch.allclose(torus, torch.tensor([-0.25, 0.35], dtype=torch.float64))


def test_opacity_values_and_gradients_finite_for_small_beta():
    vol = SDFVolume("box", beta=1e-5, dtype=torch.float64)
    p = torch.randn(1000, 3, dtype=torch.float64) * 2
    o = vol.opacity(p)
    (o.sum() + vol.color(p).sum()).backward()
    assert torch.isfinite(o).all() and (o >= 0).all() and (o <= 1).all()
    assert torch.isfinite(vol.center.grad).all() and torch.isfinite(vol.side_lengths.grad).all()


def test_opacity_is_half_alpha_on_surface():
    vol = SDFVolume("sphere", radius=0.5, alpha=0.8, dtype=torch.float64)
    p = torch.tensor([[0.5, 0, 0], [0, -0.5, 0]], dtype=torch.float64)
    assert torch.allclose(vol.opacity(p), torch.full((2,), 0.4, dtype=torch.float64))


def test_rainbow_color_clamped():
    vol = SDFVolume("box", center=(0.1, 0.2, 0.3))
    p = torch.tensor([[0.1, 0.2, 0.3], [5.0, 5.0, 5.0]])
    c = vol.color(p)
    assert torch.allclose(c[0], torch.full((3,), 0.02)) and torch.allclose(
        c[1], torch.full((3,), 0.98)
    )
