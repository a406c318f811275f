"""hash_sdf's forward differences (``--sdf-gradient forward``, warpnerf/fields/hash_sdf.py): the
gradient (d(x + h e_i) - d(x)) / h from the sample's own SDF value, which the density computed:
exact on linear functions, first order on smooth ones, differentiable through both terms; the
colour head's features carry that value, so density() then color() needs 3 more evaluations;
a half-precision value is recomputed."""

from __future__ import annotations

import pytest
import torch

from .test_hash_sdf import field
from .test_hash_sdf import inside as points


def smooth(p):
    p = p.double()
    return torch.sin(p[:, 0]) * p[:, 1] + 0.5 * p[:, 2] ** 2


def test_forward_difference_is_exact_on_linear_and_first_order_on_smooth(monkeypatch):
    f = field(gradient="forward")
    x = points().double()
    a = torch.tensor([0.3, -1.2, 0.7], dtype=torch.float64)
    monkeypatch.setattr(f, "sdf", lambda p: p.double() @ a)
    g = f.forward_gradient(x)
    assert g.dtype == torch.float64 and torch.allclose(g, a.expand_as(g), atol=1e-9)
    monkeypatch.setattr(f, "sdf", smooth)
    xr = x.clone().requires_grad_(True)
    (want,) = torch.autograd.grad(smooth(xr).sum(), xr)
    h = f.fd_step
    fwd = (f.forward_gradient(x) - want).abs()
    central = (f.gradient(x).double() - want).abs().max().item()
    # first order: the error is h/2 times the second derivative along the axis, + O(h^2)
    second = (torch.sin(x[:, 0]) * x[:, 1]).abs()  # |d2f/dx0^2|; f is linear in x1
    assert (fwd[:, 0] - 0.5 * h * second).abs().max() <= 0.25 * h * h
    assert fwd[:, 1].max() < 1e-12
    assert torch.allclose(fwd[:, 2], torch.full_like(fwd[:, 2], 0.5 * h), rtol=1e-6)
    assert fwd.max().item() > 10 * central  # (central: second order)
    # the value given is the one used: the same gradient as computing it here
    assert torch.equal(f.forward_gradient(x, smooth(x)), f.forward_gradient(x))


def test_forward_difference_gradcheck(monkeypatch):
    """Differentiable through the neighbours' values and the sample's own: gradcheck in float64
    with an SDF of learnable parameters."""
    f = field(gradient="forward")
    x = points(30).double()

    def run(theta):
        monkeypatch.setattr(f, "sdf", lambda p: torch.sin(p.double() @ theta[:3]) + theta[3])
        d0 = torch.sin(x @ theta[:3]) + theta[3]
        return f.forward_gradient(x, d0)

    theta = torch.tensor([0.4, -0.9, 1.3, 0.2], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(run, (theta,))


def test_density_then_color_use_the_samples_value():
    """The features carry the SDF value at each sample (the density's own, with its gradient),
    so color() differences from it; its normals are the forward differences', within h / (2 r)
    of the central ones on the initial sphere; the eikonal term is recorded; the parameters get
    gradients through the colour and the value alike."""
    f, c = field(gradient="forward", radius=0.5), field(radius=0.5)
    x = points(300)
    dirs = torch.nn.functional.normalize(torch.randn(x.shape[0], 3), dim=-1)
    sigma, h = f.density(x, dirs)
    assert h.shape[1] == c.density(x, dirs)[1].shape[1] + 1  # [x, d, feat]
    assert torch.allclose(h[:, 3], f.sdf(x)) and h.requires_grad
    rgb = f.color(h, dirs, valid=torch.ones(x.shape[0], dtype=torch.bool))
    assert rgb.shape == (x.shape[0], 3) and torch.isfinite(rgb).all()
    aux = f.aux_losses()
    assert set(aux) == {"eikonal"} and torch.isfinite(aux["eikonal"])
    (rgb.sum() + sigma.sum() + aux["eikonal"]).backward()
    first = [m for m in f.sdf_mlp if isinstance(m, torch.nn.Linear)][0]
    assert first.weight.grad is not None and first.weight.grad.abs().sum() > 0
    # normals: forward against central on the initial sphere (radius 0.75 world units)
    nf = torch.nn.functional.normalize(f.forward_gradient(x).detach(), dim=-1)
    nc = torch.nn.functional.normalize(c.gradient(x).detach(), dim=-1)
    cos = (nf * nc).sum(-1)  # (the sphere's level set through x has radius |x|)
    assert (cos > 1 - (f.fd_step / x.norm(dim=-1)) ** 2).all()  # angle <= about h / (2 |x|)
    assert cos.min() < 1 - 1e-6  # (not the same scheme)


def test_a_half_precision_value_is_recomputed():
    """Under fp16 autocast the features (and the value) are rounded: color() recomputes the value
    in float32 at the rounded positions instead of differencing against the rounded one."""
    f = field(gradient="forward")
    x = points(100)
    with torch.no_grad():
        _, h = f.density(x)
        h16 = h.half()
        g = f.forward_gradient(h16[:, :3], h16[:, 3])
        want = f.forward_gradient(h16[:, :3].float())
    assert g.dtype == torch.float32 and torch.equal(g, want)
    # (differencing against the rounded value would be off by its rounding error / h)
    with torch.no_grad():
        xs = h16[:, :3].float()
        e = torch.eye(3) * f.fd_step
        dp = torch.stack([f.sdf(xs + e[i]) for i in range(3)], -1)
        naive = (dp - h16[:, 3:4].float()) / f.fd_step
    assert (naive - want).abs().max() > 0.01


@pytest.mark.parametrize("beta", [1e-4, 0.01, 1.0])
def test_neus_with_forward_differences_hard_cases(beta):
    """NeuS's density from the forward gradient: finite for tiny and large beta, far points,
    axis-parallel directions; its features carry that gradient."""
    f = field(gradient="forward", density="neus", beta=max(beta, 1e-4), beta_min=1e-4,
              learn_beta=False)  # fmt: skip
    x = torch.cat([points(50), torch.tensor([[1e3, 0.0, 0.0], [0.0, 0.0, 1.49]])])
    dirs = torch.zeros(x.shape[0], 3)
    dirs[:, 2] = -1.0  # axis-parallel
    sigma, h = f.density(x, dirs)
    assert torch.isfinite(sigma).all() and (sigma >= 0).all()
    with torch.no_grad():
        d = f.sdf(x)
    assert torch.allclose(h[:, 3:6], f.forward_gradient(x, d), atol=1e-6)


def test_an_unknown_scheme_is_refused():
    """(The CLI flag: tests/test_hash_sdf.py::test_hash_sdf_flags.)"""
    with pytest.raises(ValueError, match="gradient"):
        field(gradient="tetrahedral")


def test_forward_is_hash_sdfs_default_and_older_runs_keep_central():
    """Forward differences are hash_sdf's default since 2026-12-03 (on an H200: 0.72x the step,
    lego 33.32 against 33.13 dB at 300 s, the same materials mesh; docs/design/surfaces.md);
    the MLP SDF field keeps central ones; a config.json written before the option existed
    (no ``sdf_gradient`` key) loads as the central differences it trained with."""
    from warpnerf.train.nerf_config import VolSDFConfig

    assert VolSDFConfig(field="hash_sdf", data="builtin").resolve().sdf_gradient == "forward"
    assert VolSDFConfig(field="volsdf", data="builtin").resolve().sdf_gradient == "central"
    saved = VolSDFConfig(field="hash_sdf", data="builtin").resolve().to_dict()
    assert VolSDFConfig.from_dict(saved).sdf_gradient == "forward"
    del saved["sdf_gradient"]
    assert VolSDFConfig.from_dict(saved).resolve().sdf_gradient == "central"


def test_huber_is_hash_sdfs_default_and_older_runs_keep_mse():
    """Huber is hash_sdf's colour loss since 2026-12-03 (on an H200: lego 34.63 against 33.32
    dB after 300 s, the materials mesh 0.0194 against 0.0208; docs/design/nerf.md "Issue 44,
    eleventh round"); the other fields keep mse; a flag given wins; a config.json without the
    key (written before the field's default changed) loads as the mse it trained with."""
    from warpnerf.train.nerf_config import NeRFConfig, VolSDFConfig

    assert VolSDFConfig(field="hash_sdf", data="builtin").resolve().photometric_loss == "huber"
    assert VolSDFConfig(field="volsdf", data="builtin").resolve().photometric_loss == "mse"
    for f in ("hash", "mlp"):
        assert NeRFConfig(field=f, data="builtin").resolve().photometric_loss == "mse"
    mse = VolSDFConfig(field="hash_sdf", data="builtin", photometric_loss="mse").resolve()
    assert mse.photometric_loss == "mse"
    saved = VolSDFConfig(field="hash_sdf", data="builtin").resolve().to_dict()
    assert VolSDFConfig.from_dict(saved).photometric_loss == "huber"
    del saved["photometric_loss"]
    assert VolSDFConfig.from_dict(saved).resolve().photometric_loss == "mse"


def test_resume_compares_a_missing_key_with_the_value_it_trained_with():
    """`--resume --photometric-loss mse` (or `--sdf-gradient central`) on a run whose
    config.json predates the key compares with what it trained with, not with None."""
    from warpnerf.cli.train import _saved_value
    from warpnerf.train.nerf_config import VolSDFConfig

    saved = VolSDFConfig(field="hash_sdf", data="builtin").resolve().to_dict()
    assert _saved_value("photometric_loss", saved, VolSDFConfig) == "huber"
    for key, before in (("photometric_loss", "mse"), ("sdf_gradient", "central")):
        old = {k: v for k, v in saved.items() if k != key}
        assert _saved_value(key, old, VolSDFConfig) == before
