"""--sampler proposal (issue 48): nerfacto's proposal networks in place of the occupancy grid on a
contracted scene. The networks' forward, the renderer's fixed shapes and sorted samples, a short
training run on the tiny built-in scene contracted (loss down, interlevel term logged, eval and
render of the saved run), exact resume (networks, anneal, optimiser and jitter stream), and the
flags' checks."""

from __future__ import annotations

import json
import math

import pytest
import torch

from warpnerf.errors import UserError
from warpnerf.fields.proposal import ProposalDensity, ProposalSampler, parse_levels
from warpnerf.ops.encoding import HashGrid
from warpnerf.render_proposal import render_proposal, uniform_edges
from warpnerf.train import evaluate_run, render_run, train_nerf
from warpnerf.train.nerf import load_run

from .test_nerf import GRID, tiny

QUIET = dict(progress=False, log=lambda *a: 0)
# the tiny built-in scene, contracted, with small proposal levels (CPU Warp is single-threaded)
PROPOSAL = dict(GRID, contract="on", target_samples=0, sampler="proposal",
                proposal_samples="16,8", proposal_final=8, proposal_anneal=10)  # fmt: skip


def test_proposal_density_forward():
    """Densities >= 0 of every point of space (the contraction keeps far points in the cube),
    differentiable in the hash table and the MLP; zero only outside the contracted cube."""
    torch.manual_seed(0)
    net = ProposalDensity(1.5, HashGrid(n_levels=5, log2_size=10, base_res=4, max_res=32))
    p = torch.cat([torch.randn(50, 3), torch.randn(5, 3) * 1e4])
    sig = net(p)
    assert sig.shape == (55,) and (sig > 0).all() and torch.isfinite(sig).all()
    sig.sum().backward()
    assert net.encoding.table.grad.abs().sum() > 0 and net.mlp[0].weight.grad is not None
    with pytest.raises(ValueError, match="contracted"):
        ProposalDensity(0.0, HashGrid(n_levels=2))


def test_anneal_schedule_and_levels():
    s = ProposalSampler(1.0, (16, 8), 8, anneal_steps=1000)
    s.set_step(0)
    assert float(s.anneal) == 0.0
    s.set_step(100)  # nerfacto: 10 f / (9 f + 1) at f = 0.1
    assert float(s.anneal) == pytest.approx(1.0 / 1.9, rel=1e-6)
    s.set_step(5000)
    assert float(s.anneal) == 1.0 and s.n_draws == 3
    assert parse_levels("256,96") == (256, 96)
    for bad in ("", "0", "1,2,3,4,5", "a,b", "96,5000"):
        with pytest.raises(ValueError):
            parse_levels(bad)
    # s = t / (t + a) and its inverse
    t = torch.tensor([0.0, 0.5, 1.0, 100.0], dtype=torch.float64)
    assert torch.allclose(s.t_of_s(s.s_of_t(t)), t)
    e = uniform_edges(4, 6, torch.rand(4, generator=torch.Generator().manual_seed(0)), "cpu",
                      torch.float64)  # fmt: skip
    assert (e[:, 1:] >= e[:, :-1]).all() and (e >= 0).all() and (e <= 1).all()


def test_render_proposal_shapes_and_losses():
    """Fixed samples per ray, outputs per ray, interlevel (and distortion) only with gradients;
    evaluation is deterministic without jitter."""
    from warpnerf.fields.hash_nerf import HashNeRFField

    torch.manual_seed(0)
    a = 1.0
    sampler = ProposalSampler(a, (12, 6), 5)
    field = HashNeRFField([-2 * a] * 3 + [2 * a] * 3,
                          HashGrid(n_levels=3, log2_size=8, base_res=4, max_res=16), hidden=8,
                          contract=a)  # fmt: skip
    o = torch.randn(7, 3) * 0.3
    d = torch.nn.functional.normalize(torch.randn(7, 3), dim=-1)
    out = render_proposal(sampler, field, o, d, 0.05, 1000.0, perturb=True,
                          generator=torch.Generator().manual_seed(1), distortion=True)  # fmt: skip
    assert out["rgb"].shape == (7, 3) and out["interlevel"].shape == (7,)
    assert out["distortion"].shape == (7,) and torch.isfinite(out["interlevel"]).all()
    (out["rgb"].sum() + out["interlevel"].sum()).backward()
    assert sampler.nets[0].encoding.table.grad is not None
    with torch.no_grad():
        e1 = render_proposal(sampler, field, o, d, 0.05, 1000.0)
        e2 = render_proposal(sampler, field, o, d, 0.05, 1000.0)
    assert "interlevel" not in e1 and torch.equal(e1["rgb"], e2["rgb"])
    assert ((e1["opacity"] >= 0) & (e1["opacity"] <= 1 + 1e-6)).all()


def test_training_reduces_the_loss_and_the_run_evaluates(tmp_path):
    """20 steps on the tiny contracted scene: the loss falls, the interlevel term is logged
    every step, the checkpoint holds the proposal networks and no grid, and the saved run
    evaluates and renders with the same sampler."""
    cfg = tiny(iters=20, val_every=20, ckpt_every=20, **PROPOSAL)
    h = train_nerf(cfg, tmp_path / "r", **QUIET)
    assert len(h["interlevel"]) == 20 and all(math.isfinite(v) and v >= 0 for v in h["interlevel"])
    first, last = sum(h["loss"][:5]) / 5, sum(h["loss"][-5:]) / 5
    assert last < 0.95 * first, (first, last)
    assert "samples_per_ray" not in h  # (the grid's adaptive batch is not used)
    assert "batch" not in h
    ckpt = torch.load(tmp_path / "r" / "checkpoint.pt", weights_only=True)
    assert ckpt["fields"]["grid"] is None and "nets.1.encoding.table" in ckpt["fields"]["proposal"]
    assert float(ckpt["fields"]["proposal"]["anneal"][0]) == 1.0  # (10 anneal steps, all done)
    saved = json.loads((tmp_path / "r" / "config.json").read_text())
    assert saved["sampler"] == "proposal" and saved["contract"] == "on"
    _, model, _ = load_run(tmp_path / "r")
    assert model.grid is None and model.proposal is not None
    m = evaluate_run(tmp_path / "r", max_images=1)
    assert math.isfinite(m["psnr"]) and m["psnr"] > 5
    with pytest.raises(UserError, match="occupancy grid"):  # grid-only settings are refused
        evaluate_run(tmp_path / "r", max_images=1, march_step=0.1)
    r = render_run(tmp_path / "r", "orbit", frames=2, size=(8, 6))
    assert r["frames"] == 2 and (tmp_path / "r" / "render_orbit" / "rgb_001.png").stat().st_size


def test_resume_continues_exactly(tmp_path):
    straight = train_nerf(tiny(**PROPOSAL), tmp_path / "a", **QUIET)
    train_nerf(tiny(iters=3, lr_decay_steps=6, **PROPOSAL), tmp_path / "b", **QUIET)
    resumed = train_nerf(tiny(iters=6), tmp_path / "b", resume=True, **QUIET)
    assert resumed["loss"] == straight["loss"]
    assert resumed["interlevel"] == straight["interlevel"]
    a = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=True)
    b = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=True)
    for part in ("coarse", "proposal"):
        for k, v in a["fields"][part].items():
            assert torch.equal(v, b["fields"][part][k]), (part, k)


def test_the_flags_are_checked(tmp_path):
    """--sampler proposal needs the hash field on a contracted scene and refuses --view-cull;
    distortion works with it; the static-shape step says why it is not captured."""
    bads = (
        (dict(sampler="proposal"), "sampler"),  # the MLP field
        (dict(GRID, field="hash_sdf", contract="on", sampler="proposal"), "sampler"),
        (dict(GRID, sampler="proposal", contract="off"), "contract"),
        (dict(PROPOSAL, view_cull=True), "view-cull"),
        (dict(PROPOSAL, proposal_samples="16,x"), "proposal-samples"),
        (dict(PROPOSAL, interlevel_loss=float("nan")), "interlevel-loss"),
        (dict(PROPOSAL, sampler="nope"), "sampler"),
    )
    for bad, match in bads:
        with pytest.raises(UserError, match=match):
            train_nerf(tiny(**bad), tmp_path / "bad", **QUIET)
    assert not (tmp_path / "bad").exists()
    # (--target-samples, set by --preset gpu, leaves the batch at --batch)
    h = train_nerf(tiny(iters=2, distortion_loss=0.1, **dict(PROPOSAL, target_samples=500)),
                   tmp_path / "d", **QUIET)  # fmt: skip
    assert len(h["distortion"]) == 2 and all(v > 0 for v in h["distortion"])
    from warpnerf.train.graph_step import unsupported

    cfg, model, _ = load_run(tmp_path / "d")
    why = unsupported(cfg, model, None)
    assert why is not None and "--sampler proposal" in why
