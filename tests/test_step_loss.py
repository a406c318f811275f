"""The step's loss assembled once (warpnerf/train/step_loss.py): one step of the eager path
(NeRFTask.loss) and of the static-shape body a CUDA graph holds (GraphStep without capture) give
the same loss, terms and gradients, recipe by recipe; the terms the captured step cannot compute
are named by unsupported() and refused, never dropped."""

from __future__ import annotations

import pytest
import torch

from tests.test_graph_step import _params, _task, _train
from warpnerf.train.graph_step import GraphStep, unsupported
from warpnerf.train.step_loss import LossSettings, step_loss, unsupported_terms

FORCE = (4096, 1 << 16, 1 << 15)  # room for every sample: the static body drops nothing
SPP_FORCE = (256, 1 << 18, 1 << 17)  # --train-spp 4: four rays (and their samples) a pixel
CASES = {
    "plain": {},
    "random_background": dict(random_background="on"),
    "mask": dict(random_background="on", mask_loss=0.5),  # (the built-in scene's alpha)
    "distortion": dict(distortion_loss=0.01),
    "near": dict(near_loss=0.1, distortion_loss=0.01, distortion_space="mipnerf360"),
    "hash_sdf": dict(field="hash_sdf", target_samples=0, beta_final=0.02, beta_anneal_steps=8),
    "train_spp": dict(train_spp=4),
    "pixel_jitter": dict(pixel_jitter=True),
}
FORCES = {"train_spp": SPP_FORCE}  # (the cases whose samples outgrow FORCE)
EXTRA = {"mask": ("mask",), "distortion": ("distortion",), "near": ("near", "distortion"),
         "hash_sdf": ("beta",)}  # fmt: skip
TERMS = {"psnr", "mask", "distortion", "near", "beta"}


class _Keep:
    """An optimiser that keeps the step's gradients (no update) for the comparison."""

    def __init__(self, params):
        self.params = params

    def zero_grad(self, set_to_none=True):
        for p in self.params:
            p.grad = None

    def step(self):
        pass


def _pair(kw, force=FORCE):
    """Two tasks after the same eager first step; the second with the static-shape body (its
    capacities ``force``)."""
    tasks = []
    for static in (False, True):
        task = _task("cpu", **kw)
        if task.random_bg and not task.mask_w:  # a random alpha for the built-in pixels
            task.flat_alpha = torch.rand(task.flat.shape[0],
                                         generator=torch.Generator().manual_seed(5))  # fmt: skip
        if static:
            task.graph = GraphStep(task, capture=False)
            task.graph.force = force
        _train(task, 1)  # (step 0: eager on both, it sizes the static buffers)
        tasks.append(task)
    return tasks


def step_both(eager, static) -> tuple:
    """Step 1 of a :func:`_pair`: the eager step's loss and its backward, then the static
    body's whole step (no flag raised, no sample dropped). Returns (loss_e, terms_e, loss_s,
    terms_s); the gradients stay on the tasks' parameters (:func:`assert_same_gradients`)."""
    params_e, params_s = eager.parameters(), static.parameters()
    loss_e, terms_e = eager.loss(1)
    _Keep(params_e).zero_grad()
    loss_e.backward()
    loss_s, terms_s, flags = static.train_step(1, _Keep(params_s), params_s)
    assert not flags.any() and int(terms_s["dropped_samples"]) == 0
    return loss_e, terms_e, loss_s, terms_s


def assert_same_gradients(eager, static, what="") -> None:
    """Each parameter's gradient of the two tasks within 1e-5 of the eager one's largest entry
    (no gradient: zeros)."""
    for pe, ps in zip(eager.parameters(), static.parameters()):
        ge = torch.zeros_like(pe) if pe.grad is None else pe.grad
        gs = torch.zeros_like(ps) if ps.grad is None else ps.grad
        scale = float(ge.abs().max()) + 1e-12
        assert float((ge - gs).abs().max()) <= 1e-5 * scale, (what, tuple(pe.shape))


def assert_static_trains_as_eager(steps: int, force=FORCE, **kw) -> None:
    """``steps`` steps of two tasks with the config changes ``kw`` (the first eager on both, it
    sizes the buffers): the static-shape step gives the eager step's batches, losses and
    parameters, dropping no sample; and ``kw`` changes the training (a plain task's first loss
    differs)."""
    eager, static = _task("cpu", **kw), _task("cpu", **kw)
    la, ha, _ = _train(eager, steps)
    lb, hb, _ = _train(static, steps, static=True, force=force)
    assert static.graph.shapes and ha["batch"] == hb["batch"]
    assert hb["dropped_samples"] == [0] * steps
    assert lb == pytest.approx(la, rel=1e-5)
    assert (_params(eager) - _params(static)).abs().max() < 1e-6
    lc, _, _ = _train(_task("cpu"), 1)
    assert lc[0] != pytest.approx(la[0], rel=1e-6)


@pytest.mark.parametrize("name", list(CASES))
def test_eager_and_static_step_have_the_same_loss_terms_and_gradients(name):
    eager, static = _pair(CASES[name], FORCES.get(name, FORCE))
    loss_e, terms_e, loss_s, terms_s = step_both(eager, static)
    # (the static body's masked means sum in another order: float32 round-off)
    assert loss_s.item() == pytest.approx(loss_e.item(), rel=1e-6)
    want = TERMS & set(terms_e)
    assert want == TERMS & set(terms_s)
    assert want == {"psnr", *EXTRA.get(name, ())}
    for k in want:
        assert float(terms_s[k]) == pytest.approx(float(terms_e[k]), rel=1e-6), k
    assert terms_s["batch"] == terms_e["batch"]
    assert float(terms_s["samples_per_ray"]) == pytest.approx(terms_e["samples_per_ray"])
    assert_same_gradients(eager, static, name)


def test_terms_the_captured_step_cannot_compute_are_named_and_refused():
    assert unsupported_terms(LossSettings()) is None
    assert "--depth-loss" in unsupported_terms(LossSettings(depth_w=0.1))
    assert "fine pass" in unsupported_terms(LossSettings(fine=True))
    assert "data-parallel" in unsupported_terms(LossSettings(), dist=object())
    out = {"rgb": torch.rand(4, 3), "opacity": torch.rand(4)}
    target, mask, n = torch.rand(4, 3), torch.ones(4), torch.tensor(4.0)
    with pytest.raises(ValueError, match="depth-loss"):
        step_loss(LossSettings(depth_w=0.1), None, out, target, None, mask=mask, n=n,
                  depth=torch.tensor(1.0))  # fmt: skip
    with pytest.raises(ValueError, match="depth term"):  # (eager: the term must be given)
        step_loss(LossSettings(depth_w=0.1), None, out, target, None)
    loss, terms = step_loss(LossSettings(depth_w=0.5), None, out, target, None,
                            depth=torch.tensor(2.0))  # fmt: skip
    assert float(terms["depth"]) == 2.0
    assert float(loss) == pytest.approx(float(((out["rgb"] - target) ** 2).mean()) + 1.0)
    # a run's settings: a fine pass (no grid: refused for that first), an SDF's eikonal term
    task = _task("cpu", field="hash", grid_res=0, n_fine=8)
    assert "fine pass" in unsupported_terms(task.loss_settings, task.model)
    assert "grid" in unsupported(task.cfg, task.model, task)
    sdf = _task("cpu", field="hash_sdf").loss_settings
    assert sdf.sdf and sdf.eikonal_w > 0 and unsupported_terms(sdf) is None
