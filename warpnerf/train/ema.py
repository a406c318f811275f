"""An exponential moving average of a NeRF/VolSDF run's weights (``--ema DECAY``, issue 44): what
evaluation, rendering, meshing, export and the viewer use, and what validation scores, while
training goes on with the raw weights.

The semantics are tiny-cuda-nn's ``EmaOptimizer`` (NVlabs/tiny-cuda-nn,
``include/tiny-cuda-nn/optimizers/ema.h``; instant-ngp's ``configs/nerf/base.json`` wraps its
Adam in it with ``"decay": 0.95``). After optimiser step ``t`` (1-based: tcnn reads the nested
optimiser's step count after the step) the average is the *debiased* EMA

    m_t = d * m_{t-1} + (1 - d) * w_t,   m_0 = 0,        ema_t = m_t / (1 - d^t)

and what is kept is ``ema_t`` itself: tcnn's kernel ``ema_step_full_precision`` re-biases the
stored value and debiases the new one, ``ema_t = (ema_{t-1} * d * (1 - d^(t-1)) + w_t * (1 - d))
/ (1 - d^t)``. That is a linear interpolation towards the new weights,

    ema_t = ema_{t-1} + b_t * (w_t - ema_{t-1}),   b_t = (1 - d) / (1 - d^t),

which is what :meth:`WeightAverage.update` computes (one ``torch._foreach_lerp_`` over the
averaged tensors, the weight a host number: no host sync, no CUDA-graph capture needed). b_1 = 1
(the first average is the weights themselves, whatever was held before), and b_t falls to 1 - d.
The average is kept in the parameters' own precision (float32: tcnn's ``full_precision``).

tcnn's trainer renders with the average (``Trainer::reset_param_pointers``: the inference
parameters are the optimiser's ``custom_weights()``, the EMA; ``serialize`` saves those) and it
never feeds back into training (tcnn's DOCUMENTATION.md). Here the checkpoint keeps both: the raw
weights under ``fields`` (what a resume trains on) and the average under ``ema``
(:data:`KEY`: ``{"<part>.<parameter name>": tensor}``), and :func:`apply_average` copies the
average into a loaded run's model.

What is averaged: the parameters of the run's fields (the coarse and the fine field: hash tables,
MLPs, VolSDF's beta), which is the one network tcnn's EMA wraps in instant-ngp. Not averaged:
the per-image appearance codes and the pose corrections (instant-ngp trains its per-image latents,
``extra_dims_opt``, and camera offsets with optimisers of their own, outside the EMA), and no
buffer (the occupancy grid, the hash levels a schedule has opened).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import torch
from torch import nn

from ..errors import UserError
from ..outputs import load_tensors

__all__ = ["WeightAverage", "averaged_parameters", "apply_average", "saved_average", "KEY"]

KEY = "ema"  # the checkpoint's entry


def averaged_parameters(model) -> dict:
    """``{"<part>.<name>": parameter}`` of a :class:`~warpnerf.fields.model.RadianceModel`'s
    averaged parameters: its field parts' (``parts()``: coarse, fine), without the appearance
    codes (a field's ``appearance`` module) or the pose corrections."""
    out = {}
    for part, module in model.parts().items():
        if module is None or module is model.poses:
            continue
        codes = getattr(module, "appearance", None)
        skip = {id(p) for p in codes.parameters()} if isinstance(codes, nn.Module) else set()
        for name, p in module.named_parameters():
            if id(p) not in skip:
                out[f"{part}.{name}"] = p
    return out


def saved_average(cfg, ckpt: dict, path) -> dict | None:
    """The checkpoint's average (its ``ema`` entry), or None for a run without ``--ema``; a
    :class:`UserError` naming ``path`` when the run's config and its checkpoint disagree."""
    held = ckpt.get(KEY)
    on = float(getattr(cfg, "ema", 0.0) or 0.0) > 0
    if on and held is None:
        raise UserError(
            f"{path}: the run's config.json has --ema {cfg.ema:g} but the checkpoint holds no "
            "averaged weights (was the config edited?)"
        )
    if not on and held is not None:
        raise UserError(
            f"{path}: the checkpoint holds averaged weights (ema) but the run's config.json has "
            "no --ema (was the config edited?)"
        )
    return held


def apply_average(model, cfg, ckpt: dict, path) -> bool:
    """Copies a loaded run's average into ``model``'s parameters (checked as untrusted input:
    exactly the averaged names, each of its parameter's shape and dtype, finite); returns
    whether the run has one."""
    held = saved_average(cfg, ckpt, path)
    if held is None:
        return False
    load_tensors(averaged_parameters(model), held, path, "averaged weights (ema)")
    return True


class WeightAverage:
    """The running average of ``model``'s :func:`averaged_parameters` with decay ``decay`` in
    (0, 1) (see the module's text). Starts as a copy of the weights (step 1 replaces it)."""

    def __init__(self, model, decay: float):
        decay = float(decay)
        if not 0.0 < decay < 1.0:
            raise ValueError(f"decay must be in (0, 1), got {decay}")
        self.decay = decay
        self.params = averaged_parameters(model)
        self.average = [w.clone() for w in self._live]

    @property
    def _live(self) -> list:
        """The parameters' tensors now (views without autograd)."""
        return [p.detach() for p in self.params.values()]

    def weight(self, t: int) -> float:
        """b_t = (1 - d) / (1 - d^t): the new weights' share at optimiser step ``t`` >= 1."""
        d = self.decay
        return (1.0 - d) / (1.0 - d ** max(int(t), 1))

    @torch.no_grad()
    def update(self, step: int) -> None:
        """After the optimiser step of loop step ``step`` (0-based: tcnn's step count is
        ``step + 1``)."""
        torch._foreach_lerp_(self.average, self._live, self.weight(step + 1))

    def state(self) -> dict:
        """The checkpoint's ``ema`` entry (the live tensors; the loop copies them for a
        background write)."""
        return dict(zip(self.params, self.average))

    def load(self, saved, path) -> None:
        """Restores a checkpoint's ``ema`` entry exactly (checked as untrusted input)."""
        load_tensors(dict(zip(self.params, self.average)), saved, Path(path),
                     "averaged weights (ema)")  # fmt: skip

    @contextlib.contextmanager
    def applied(self):
        """The average in the model's parameters while the context is open (validation, the
        live viewer's frames), the raw weights copied back bit for bit after: training goes on
        as without it. Copies in place (a captured step's addresses stay valid)."""
        live = self._live
        with torch.no_grad():
            raw = [w.clone() for w in live]
            try:
                for w, a in zip(live, self.average):
                    w.copy_(a)
                yield
            finally:
                for w, r in zip(live, raw):
                    w.copy_(r)
