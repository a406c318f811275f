"""Sphere-traced rendering of SDF fields (warpnerf/render.py ``render_sphere_traced``): depth
against closed-form ray/sphere hits (an exact analytic field and a fresh hash SDF, whose
initialisation is the sphere), colour from the field's own head at the hit, misses, rays from
outside the box, rays starting inside the solid or ending before the surface, a field that is
not 1-Lipschitz (step scale + refinement), non-unit directions, non-finite input (INVALID, no
silent NaN), and ``warpnerf eval/render --renderer sphere`` on a tiny hash_sdf run (a NeRF run is
refused)."""

from __future__ import annotations

import json

import pytest
import torch
from torch import nn

from warpnerf.render import render_sphere_traced
from warpnerf.sphere_tracing import HIT, INSIDE, INVALID, MISS

R = 0.75  # world radius of the test sphere
BOX = [-1.5, -1.5, -1.5, 1.5, 1.5, 1.5]


class Sphere(nn.Module):
    """An exact sphere SDF with the field protocol; ``lipschitz`` scales the distance (the zero
    set stays the sphere), colour = a function of position and direction."""

    kind = "sdf"

    def __init__(self, radius=R, lipschitz=1.0):
        super().__init__()
        self.radius, self.lipschitz = radius, lipschitz

    def sdf(self, x):
        return self.lipschitz * (x.norm(dim=-1) - self.radius)

    def normals(self, x):
        return nn.functional.normalize(x, dim=-1)

    def forward(self, x, d):
        rgb = torch.sigmoid(torch.cat([x[:, :2], d[:, :1]], -1) * 2.0)
        return torch.ones_like(x[:, 0]), rgb


def _rays(n=600, dist=4.0, spread=1.2, seed=0, device="cpu"):
    """Rays from a sphere of radius ``dist`` (outside the box) aimed at points within
    ``spread`` of the centre: hits, misses and grazing rays."""
    g = torch.Generator().manual_seed(seed)
    o = nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * dist
    tgt = (torch.rand(n, 3, generator=g) * 2 - 1) * spread
    d = nn.functional.normalize(tgt - o, dim=-1)
    return o.to(device), d.to(device)


def _analytic(o, d, r=R):
    """(t of the first hit of unit rays with the sphere |x| = r, inf on a miss; cos of the
    incidence angle, 0 on a miss)."""
    o, d = o.double(), d.double()
    b = (o * d).sum(-1)
    disc = b * b - ((o * o).sum(-1) - r * r)
    t = torch.where(disc > 0, -b - disc.clamp_min(0).sqrt(), torch.full_like(b, float("inf")))
    cos = torch.where(disc > 0, disc.clamp_min(0).sqrt() / r, torch.zeros_like(b))
    return t, cos


def _hash_sphere():
    """A fresh hash SDF whose last layer is zeroed: exactly |c| - 0.5 box units = |x| - 0.75."""
    from warpnerf.fields.hash_sdf import HashSDFField
    from warpnerf.ops.encoding import HashGrid

    torch.manual_seed(0)
    f = HashSDFField(BOX, HashGrid(n_levels=4, log2_size=8, base_res=4, max_res=32), hidden=16,
                     radius=0.5)  # fmt: skip
    nn.init.zeros_(f.sdf_mlp[-1].weight)
    return f


def test_depth_colour_and_normals_match_the_analytic_sphere(device):
    o, d = _rays(device=device)
    f = Sphere()
    out = render_sphere_traced(f, o, d, 0.0, 10.0, aabb=BOX, background=(0.2, 0.3, 0.4),
                               eps=1e-4)  # fmt: skip
    t, cos = _analytic(o.cpu(), d.cpu())
    sure = (cos > 0.1) | (t.isinf() & (_analytic(o.cpu(), d.cpu(), R + 0.01)[0].isinf()))
    hit = out["opacity"].cpu() > 0
    assert torch.equal(hit[sure], t[sure].isfinite())  # misses and hits, grazing rays aside
    h = hit & (cos > 0.1)
    assert h.sum() > 200 and (hit & t.isinf()).sum() == 0  # (no hit where the ray misses)
    assert (out["depth"].cpu()[h].double() - t[h]).abs().max() < 2e-5
    assert (out["status"].cpu()[h] == HIT).all()
    p = o[h.to(device)] + out["depth"][h.to(device)].unsqueeze(-1) * d[h.to(device)]
    assert torch.allclose(out["normals"][h.to(device)], p / R, atol=1e-4)
    want = f(p, d[h.to(device)])[1]
    assert torch.allclose(out["rgb"][h.to(device)], want, atol=1e-6)
    miss = ~hit.to(device)
    assert (out["opacity"][miss] == 0).all() and (out["depth"][miss] == 0).all()
    bg = torch.tensor([0.2, 0.3, 0.4], device=device)
    assert torch.equal(out["rgb"][miss], bg.expand(int(miss.sum()), 3))
    assert (out["normals"][miss] == 0).all()
    assert out["n_hit"] == int(hit.sum()) and out["n_sdf"] >= int(out["iters"].sum())


def test_fresh_hash_sdf_is_traced_from_outside_its_box():
    """The hash SDF clamps positions to its box (no distances outside): rays from outside are
    clipped to the box first; the colour is density's features through color()."""
    f = _hash_sphere()
    o, d = _rays(400, seed=1)
    out = render_sphere_traced(f, o, d, 0.0, 10.0, aabb=BOX, eps=1e-4)
    t, cos = _analytic(o, d)
    h = (out["opacity"] > 0) & (cos > 0.1)
    assert h.sum() > 100
    assert (out["depth"][h].double() - t[h]).abs().max() < 1e-4
    p = o[h] + out["depth"][h].unsqueeze(-1) * d[h]
    with torch.no_grad():
        want = f.color(f.density(p)[1], d[h])
    assert torch.allclose(out["rgb"][h], want, atol=1e-5)
    assert ((out["opacity"] > 0) & t.isinf()).sum() == 0
    # rays that miss the box entirely: background, never traced
    o2 = torch.tensor([[0.0, 3.0, 0.0], [2.0, 2.0, 2.0]])
    d2 = torch.tensor([[1.0, 0.0, 0.0], [1.0, 1.0, 1.0]]) / torch.tensor([[1.0], [3**0.5]])
    out2 = render_sphere_traced(f, o2, d2, 0.0, 10.0, aabb=BOX)
    assert (out2["status"] == MISS).all() and (out2["iters"] == 0).all()
    assert (out2["rgb"] == 1.0).all() and (out2["opacity"] == 0).all()


def test_rays_starting_inside_or_ending_before_the_surface():
    f = Sphere()
    o = torch.tensor([[0.0, 0.0, 0.2], [0.0, 0.0, 3.0], [0.0, 0.0, 3.0], [0.0, 0.0, 1.0]])
    d = torch.tensor([[0.0, 0.0, -1.0]]).expand(4, 3)
    near = torch.tensor([0.0, 0.0, 0.0, 0.1])
    far = torch.tensor([5.0, 2.0, 5.0, 0.2])  # ray 1 stops 0.25 short of the surface
    out = render_sphere_traced(f, o, d, near, far, aabb=BOX, eps=1e-5)
    st = out["status"].tolist()
    assert st[0] == INSIDE and out["opacity"][0] == 1 and out["depth"][0] == 0.0
    assert st[1] == MISS and out["opacity"][1] == 0 and out["rgb"][1].eq(1).all()
    assert st[2] == HIT and abs(out["depth"][2].item() - (3.0 - R)) < 1e-5
    assert st[3] == MISS and out["opacity"][3] == 0  # the segment 0.9 .. 0.8 is outside


def test_non_lipschitz_field_needs_the_step_scale_and_the_refinement():
    """A learned SDF overestimates distances somewhere: here |grad| = 1.2 everywhere. The march
    overshoots into the solid (even at step scale 0.9); the refinement on the bracket [last
    step, hit] brings the hits back to the surface."""
    f = Sphere(lipschitz=1.2)
    o, d = _rays(400, seed=2)
    t, cos = _analytic(o, d)
    ok = cos > 0.3

    def err(scale, refine):
        out = render_sphere_traced(f, o, d, 0.0, 10.0, aabb=BOX, eps=1e-4, step_scale=scale,
                                   refine_steps=refine)  # fmt: skip
        h = ok & (out["opacity"] > 0)
        assert h.sum() == ok.sum() > 50
        return (out["depth"][h].double() - t[h]).abs().max().item()

    assert err(1.0, 0) > 0.1 and err(0.9, 0) > 0.05  # overshoot
    assert err(1.0, 4) < 2e-5 and err(0.9, 3) < 2e-5
    assert err(0.8, 1) < 2e-5  # (smaller overshoots: fewer steps)


def test_non_unit_directions_give_depth_in_their_own_t():
    f = Sphere()
    o, d = _rays(100, seed=3)
    a = render_sphere_traced(f, o, d, 0.0, 10.0, aabb=BOX)
    b = render_sphere_traced(f, o, 2.5 * d, 0.0, 4.0, aabb=BOX)
    assert torch.equal(a["opacity"], b["opacity"])
    assert torch.allclose(b["depth"] * 2.5, a["depth"], atol=1e-5)


def test_non_finite_input_is_invalid_not_silent_nan():
    f = Sphere()
    o, d = _rays(8, seed=4)
    o, d = o.clone(), d.clone()
    o[1, 0] = float("nan")
    d[2, 1] = float("inf")
    d[3] = 0.0
    near = torch.zeros(8)
    near[4] = float("nan")
    far = torch.full((8,), 10.0)
    far[5] = float("inf")
    out = render_sphere_traced(f, o, d, near, far, aabb=BOX)
    bad = torch.zeros(8, dtype=torch.bool)
    bad[1:6] = True
    assert (out["status"][bad] == INVALID).all() and (out["status"][~bad] != INVALID).all()
    assert out["depth"][bad].isnan().all() and (out["opacity"][bad] == 0).all()
    for k in ("rgb", "normals", "opacity"):
        assert out[k].isfinite().all(), k
    assert out["depth"][~bad].isfinite().all()
    good = render_sphere_traced(f, o[~bad], d[~bad], 0.0, 10.0, aabb=BOX)
    assert torch.equal(good["depth"], out["depth"][~bad])
    with pytest.raises(ValueError, match="step_scale"):
        render_sphere_traced(f, o, d, 0.0, 1.0, step_scale=1.5)


def test_cli_eval_and_render_with_the_sphere_renderer(tmp_path, capsys):
    from warpnerf.cli.parser import main

    from .test_datasets import make_blender

    data = make_blender(tmp_path / "bl", n=2, w=12, h=12)
    make_blender(data, n=1, w=12, h=12, split="val")
    run = tmp_path / "r"
    common = ["--hash-levels", "3", "--hash-log2-size", "8", "--hash-max-res", "16"]
    assert main(["train", "volsdf", "--data", str(data), "--field", "hash_sdf", "--out", str(run),
                 "--iters", "2", "--batch", "64", "--grid-res", "8", "--val-images", "0",
                 "--quiet", *common]) == 0  # fmt: skip
    capsys.readouterr()
    assert main(["eval", str(run), "--max-images", "1", "--renderer", "sphere"]) == 0
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert line["renderer"] == "sphere" and line["psnr"] > 0
    m = json.loads((run / "eval_val_sphere" / "metrics.json").read_text())
    assert m["renderer"] == "sphere" and 0 < m["sphere_hits"] <= 1 and m["sphere_iters"] > 0
    assert (run / "eval_val_sphere" / "val_000.png").is_file()
    assert main(["eval", str(run), "--max-images", "1"]) == 0  # volume: its own folder
    assert json.loads((run / "eval_val" / "metrics.json").read_text())["renderer"] == "volume"
    capsys.readouterr()
    assert main(["render", str(run), "--frames", "1", "--size", "8x8", "--renderer",
                 "sphere"]) == 0  # fmt: skip
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["renderer"] == "sphere"
    assert (run / "render_spiral_sphere" / "rgb_000.png").is_file()
    with pytest.raises(SystemExit):  # argparse's choices
        main(["eval", str(run), "--renderer", "marching"])

    nerf = tmp_path / "n"
    tn = ["--iters", "1", "--batch", "16", "--samples", "4", "--layers", "2", "--width", "8",
          "--pos-freqs", "1", "--dir-freqs", "1", "--val-images", "0", "--quiet"]  # fmt: skip
    assert main(["train", "nerf", "--data", str(data), "--out", str(nerf), *tn]) == 0
    capsys.readouterr()
    assert main(["eval", str(nerf), "--renderer", "sphere"]) == 2
    assert "needs an SDF run" in capsys.readouterr().err
    assert main(["render", str(nerf), "--frames", "1", "--renderer", "sphere"]) == 2
