"""NeuS's unbiased density for hash_sdf (``--sdf-density neus``, warpnerf/fields/hash_sdf.py):
its closed form against NeuS's definition, the unbiased outline of a sphere (where the Laplace
and logistic densities render it wider), gradients by gradcheck, hard cases, the field's
contract (directions needed, the gradient handed to the colour head) and the renderers."""

from __future__ import annotations

import math

import pytest
import torch

from warpnerf.fields.hash_sdf import HashSDFField, logistic_density, neus_density, sdf_density
from warpnerf.ops.encoding import HashGrid

F64 = torch.float64
BOX = [-1.5, -1.5, -1.5, 1.5, 1.5, 1.5]


def field(**kw) -> HashSDFField:
    torch.manual_seed(0)
    grid = HashGrid(n_levels=4, log2_size=10, base_res=4, max_res=32)
    return HashSDFField(BOX, grid, hidden=16, **kw)


def _sphere_ray(b: float, radius: float, n: int = 200001):
    """Samples of a ray along x passing the sphere's centre at distance b: (t, sdf, gradient,
    direction), the exact SDF |p| - r."""
    t = torch.linspace(-1.0, 1.0, n, dtype=F64)
    p = torch.stack([t, torch.full_like(t, b), torch.zeros_like(t)], -1)
    d = p.norm(dim=-1) - radius
    g = p / p.norm(dim=-1, keepdim=True)
    v = torch.tensor([[1.0, 0.0, 0.0]], dtype=F64).expand_as(p)
    return t, d, g, v


def _opacity(sigma: torch.Tensor, t: torch.Tensor) -> float:
    tau = (0.5 * (sigma[1:] + sigma[:-1]) * (t[1:] - t[:-1])).sum()
    return 1.0 - math.exp(-float(tau))


def test_matches_neus_definition_on_any_ray():
    """rho = max(-d/dt Phi_s(d(t)), 0) / Phi_s(d(t)) (NeuS eq. 13) by autograd in float64, on a
    ray that grazes a sphere (it approaches, then leaves): equal everywhere, zero on the way out."""
    r, beta = 0.32, torch.tensor(0.02, dtype=F64)
    t = torch.linspace(-0.8, 0.8, 4001, dtype=F64, requires_grad=True)
    p = torch.stack([t, torch.full_like(t, 0.3), torch.zeros_like(t)], -1)
    d = p.norm(dim=-1) - r
    phi = torch.sigmoid(d / beta)
    (dphi,) = torch.autograd.grad(phi.sum(), t)
    want = torch.relu(-dphi) / phi.detach()
    g = (p / p.norm(dim=-1, keepdim=True)).detach()
    v = torch.tensor([[1.0, 0.0, 0.0]], dtype=F64).expand_as(g)
    got = neus_density(d.detach(), g, v, beta)
    assert torch.allclose(got, want, rtol=1e-9, atol=1e-12)
    assert (got[t.detach() > 0] == 0).all()  # leaving the surface: no density
    # head-on (c = -1) it is the logistic density; the bound sdf_density("neus") gives
    d0 = torch.linspace(-0.2, 0.2, 101, dtype=F64)
    g0 = torch.tensor([[-1.0, 0.0, 0.0]], dtype=F64).expand(101, 3)
    v0 = torch.tensor([[1.0, 0.0, 0.0]], dtype=F64).expand(101, 3)
    assert torch.equal(neus_density(d0, g0, v0, beta), logistic_density(d0, beta))
    assert torch.equal(sdf_density("neus", d0, beta), logistic_density(d0, beta))


@pytest.mark.parametrize("beta", [0.01, 0.003])
def test_the_outline_of_a_sphere_is_its_zero_level(beta):
    """A ray that passes the sphere exactly at its radius has opacity 1/2 with NeuS's density
    (transmittance sigmoid(s m) at distance m); the Laplace and logistic densities put the
    outline ~2.4 / 3 beta outside (experiments/surfaces/silhouette_bias.py)."""
    r = 0.32
    t, d, g, v = _sphere_ray(r, r)
    b = torch.tensor(beta, dtype=F64)
    assert _opacity(neus_density(d, g, v, b), t) == pytest.approx(0.5, abs=2e-3)
    # and at distance m outside, 1 - sigmoid(m / beta)
    t, d, g, v = _sphere_ray(r + beta, r)
    want = 1.0 - 1.0 / (1.0 + math.exp(-1.0))
    assert _opacity(neus_density(d, g, v, b), t) == pytest.approx(want, abs=2e-3)
    for kind in ("laplace", "logistic"):
        t, d, g, v = _sphere_ray(r + 2 * beta, r)
        assert _opacity(sdf_density(kind, d, b), t) > 0.5  # their outline lies farther out


def test_gradcheck():
    """Gradients in d, the SDF's gradient and the direction, away from the relu's kink."""
    torch.manual_seed(1)
    d = (torch.randn(12, dtype=F64) * 0.05).requires_grad_()
    g = torch.nn.functional.normalize(torch.randn(12, 3, dtype=F64), dim=-1)
    v = torch.nn.functional.normalize(torch.randn(12, 3, dtype=F64), dim=-1)
    keep = (g * v).sum(-1).abs() > 0.05
    g = g[keep].requires_grad_()
    v = v[keep].requires_grad_()
    d = d.detach()[keep].requires_grad_()
    beta = torch.tensor(0.03, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(neus_density, (d, g, v, beta))


@pytest.mark.parametrize("beta", [1e-4, 1e-2, 1.0])
def test_hard_cases_stay_finite(beta):
    """Tiny beta, points far outside the box and on its faces, axis-parallel and random
    directions: finite densities, colours, eikonal term and parameter gradients."""
    f = field(beta=beta, beta_min=min(beta, 1e-4), density="neus")
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(40, 3, generator=g) * 2 - 1) * 1.4
    x = torch.cat([x, torch.tensor([[100.0, 0, 0], [-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]])])
    d = torch.nn.functional.normalize(torch.randn(len(x), 3, generator=g), dim=-1)
    d[:3] = torch.eye(3)  # axis-parallel rays
    sigma, rgb = f(x, d)
    loss = sigma.mean() * 1e-4 + rgb.mean() + f.aux_losses()["eikonal"]
    loss.backward()
    assert torch.isfinite(sigma).all() and torch.isfinite(rgb).all() and (sigma >= 0).all()
    for p in f.parameters():
        assert p.grad is None or torch.isfinite(p.grad).all()
    with torch.no_grad():  # the density is the closed form of the field's own SDF and gradient
        want = neus_density(f.sdf(x), f.gradient(x), d, f.beta)
    assert torch.allclose(sigma.detach(), want, rtol=1e-5, atol=1e-30)


def test_the_field_needs_directions_and_hands_its_gradient_on():
    """density() without directions fails loudly; with them its features carry the gradient
    the density used, which the colour head and the eikonal term reuse (no second difference)."""
    f = field(density="neus")
    assert f.density_needs_directions and not field().density_needs_directions
    x = torch.tensor([[0.3, 0.1, -0.2], [0.9, 0.0, 0.4]])
    d = torch.nn.functional.normalize(torch.tensor([[1.0, 0.2, 0.0], [0.0, -1.0, 0.3]]), dim=-1)
    with pytest.raises(ValueError, match="direction"):
        f.density(x)
    sigma, h = f.density(x, d)
    plain = field()
    assert h.shape[1] == plain.density(x)[1].shape[1] + 3
    assert torch.allclose(h[:, 3:6], f.gradient(x))
    calls = []
    orig = f.gradient
    f.gradient = lambda p: calls.append(1) or orig(p)
    rgb = f.color(h, d)
    assert calls == [] and rgb.shape == (2, 3) and "eikonal" in f.aux_losses()
    from warpnerf.field_protocol import density

    with pytest.raises(ValueError, match="directions"):
        density(f, x)
    assert torch.equal(density(f, x, lambda: d)[0], sigma)
    assert torch.equal(density(plain, x, lambda: 1 / 0)[0], plain.density(x)[0])  # not called


@pytest.mark.parametrize("density,gradient", [("neus", "central"), ("neus", "forward"),
                                              ("laplace", "forward")])  # fmt: skip
@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_renderers_give_the_same_image(device, density, gradient):
    """The marcher's paths (gradients, fixed capacity, rounds, tracer) render a neus field alike
    on a few rays (each passes the samples' directions), and a field with forward differences
    (its features carry the samples' SDF values)."""
    if device == "cuda" and not torch.cuda.is_available():
        pytest.skip("CUDA not available (torch.cuda.is_available() is False): cuda variant skipped")
    from warpnerf.occupancy import OccupancyGrid
    from warpnerf.render import render_marched, render_marched_fixed

    f = field(density=density, beta=0.05, gradient=gradient).to(device)
    grid = OccupancyGrid(BOX, 8, dt=0.01).to(device)
    torch.manual_seed(3)
    o = torch.tensor([[0.0, 0.0, -3.0]]).expand(6, 3).contiguous()
    d = torch.randn(6, 3) * 0.2 + torch.tensor([0.0, 0.0, 1.0])
    o, d = o.to(device), torch.nn.functional.normalize(d, dim=-1).to(device)
    with torch.no_grad():
        # (the rounds path with the tracer's colour rule: the default's light samples take
        # their ray's mean colour, a difference up to 3e-3 on these near-miss rays)
        rounds = render_marched(grid, f, o, d, 0.5, 6.0, tracer="rounds", color_eps=1e-5,
                                color_fill="black")  # fmt: skip
        traced = render_marched(grid, f, o, d, 0.5, 6.0, tracer="traced")
    grad = render_marched(grid, f, o, d, 0.5, 6.0)
    fixed = render_marched_fixed(grid, f, o, d, 0.5, 6.0, marched=6 * 1024, kept=6 * 1024)
    for out in (traced, grad, fixed):
        assert torch.allclose(out["rgb"].detach(), rounds["rgb"], atol=2e-4)
        assert torch.allclose(out["opacity"].detach(), rounds["opacity"], atol=2e-4)
    op = rounds["opacity"]
    assert op.max() > 0.99 and op.min() < 0.01  # rays that meet the initial sphere, and miss it


def test_the_workflow_with_neus(tmp_path):
    """train volsdf --field hash_sdf --sdf-density neus, then eval (images, the weight cull of
    the delivered mesh), render and mesh run end to end on a tiny run of the built-in scene."""
    from warpnerf.cli.parser import main
    from warpnerf.train.nerf import load_run

    run = tmp_path / "r"
    tiny = ["--hash-levels", "3", "--hash-log2-size", "8", "--hash-max-res", "16"]
    assert main(["train", "volsdf", "--data", "builtin", "--field", "hash_sdf", "--out", str(run),
                 "--iters", "3", "--batch", "64", "--grid-res", "8", "--builtin-size", "16",
                 "--val-images", "1", "--quiet", "--no-tensorboard", "--sdf-density", "neus",
                 *tiny]) == 0  # fmt: skip
    cfg, model, _ = load_run(run)
    assert cfg.sdf_density == "neus" and model.field.density_needs_directions
    assert main(["eval", str(run), "--max-images", "1", "--out", str(tmp_path / "e")]) == 0
    assert main(["render", str(run), "--frames", "1", "--size", "12x12"]) == 0
    assert main(["mesh", str(run), "--out", str(tmp_path / "m.ply"), "--resolution", "16"]) == 0
    assert (tmp_path / "m.ply").is_file()
