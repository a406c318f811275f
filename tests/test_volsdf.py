"""VolSDF: the Laplace density is finite with finite gradients for beta from 1 down to 1e-4 and
signed distances up to +-1e6; the field's forward, eikonal term and backward stay finite for tiny
beta; rendering through the Warp compositing kernel stays finite; beta is learned above its
floor; a tiny run resumes exactly (see test_nerf for the shared trainer)."""

from __future__ import annotations

import pytest
import torch

from warpnerf.fields.sdf_volume import laplace_cdf
from warpnerf.fields.volsdf import VolSDFField
from warpnerf.render import render_nerf

BETAS = [1.0, 0.1, 1e-2, 1e-3, 1e-4]


@pytest.mark.parametrize("beta", BETAS)
def test_laplace_density_finite_for_extreme_sdf_and_small_beta(beta):
    d = torch.tensor([-1e6, -10.0, -1e-3, -1e-8, 0.0, 1e-8, 1e-3, 10.0, 1e6], dtype=torch.float64)
    d.requires_grad_(True)
    b = torch.tensor(beta, dtype=torch.float64, requires_grad=True)
    sigma = laplace_cdf(-d, b) / b
    assert torch.isfinite(sigma).all() and (sigma >= 0).all()
    assert abs(sigma[0].item() - 1 / beta) < 1e-9 / beta and sigma[-1].item() < 1e-300 + 1e-12
    assert abs(sigma[4].item() - 0.5 / beta) < 1e-9 / beta  # half density on the surface
    gd, gb = torch.autograd.grad(sigma.sum(), (d, b))
    assert torch.isfinite(gd).all() and torch.isfinite(gb)
    for dt in (torch.float32,):
        s32 = laplace_cdf(-d.detach().to(dt), torch.tensor(beta, dtype=dt)) / beta
        assert torch.isfinite(s32).all()


@pytest.mark.parametrize("beta", [1.0, 1e-2, 1e-4])
def test_field_and_render_finite_for_small_beta(device, beta):
    torch.manual_seed(0)
    f = VolSDFField(1.0, n_layers=3, width=48, skip=1, pos_freqs=4, dir_freqs=2, n_features=8,
                    color_width=32, beta=beta, beta_min=1e-4).to(device)  # fmt: skip
    o = torch.tensor([[0.0, 0.0, 3.0]], device=device).repeat(64, 1)
    toward = torch.tensor([0.0, 0.0, -1.0], device=device)
    d = torch.nn.functional.normalize(torch.randn(64, 3, device=device) * 0.2 + toward, dim=-1)
    out = render_nerf(f, o, d, 1.0, 5.0, fine=f, n_coarse=32, n_fine=32,
                      perturb=True, aabb=[-1, -1, -1, 1, 1, 1])  # fmt: skip
    loss = (
        out["rgb"].square().mean()
        + f.aux_losses()["eikonal"]
        + f.eikonal(torch.rand(128, 3, device=device))
    )
    loss.backward()
    assert all(torch.isfinite(v).all() for v in out.values())
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in f.parameters())
    assert f.beta_param.grad is not None and torch.isfinite(f.beta_param.grad)
    assert float(f.beta.detach()) >= 1e-4


def test_beta_floor_and_fixed_beta():
    f = VolSDFField(1.0, 2, 32, 1, 2, 1, n_features=4, color_width=16, beta=0.05, beta_min=0.01)
    with torch.no_grad():
        f.beta_param.fill_(-5.0)
    assert abs(float(f.beta.detach()) - 5.01) < 1e-6  # |b| + floor: never below the floor
    g = VolSDFField(1.0, 2, 32, 1, 2, 1, n_features=4, color_width=16, beta=0.05, learn_beta=False)
    assert g.beta_param is None and abs(float(g.beta) - 0.05) < 1e-7
    assert all("beta" not in n for n, _ in g.named_parameters())
