"""tiny-cuda-nn's Adam for hash fields (issue 44): hash-table entries without a gradient this step
are left alone, and an L2 penalty on the MLP weight matrices only.

What tiny-cuda-nn does (``include/tiny-cuda-nn/optimizers/adam.h``, ``adam_step`` kernel;
instant-ngp's NeRF settings in ``configs/nerf/base.json``: beta1 0.9, beta2 0.99, epsilon 1e-15,
l2_reg 1e-6):

- one thread per parameter element; the network's *matrix* weights come first, the rest (the
  encoding's parameters: the hash tables) after them;
- a non-matrix element whose gradient is exactly zero is skipped:
  ``if (i >= n_matrix_weights) { if (... || gradient == 0) return; }`` -- its weight, both
  moments and its step counter stay as they are;
- L2 on the matrix weights only: ``if (i < n_matrix_weights) gradient += l2_reg * weight_fp``
  ("No L2 reg for non-matrix params"), before the moments: L2 into the gradient, which is what
  ``torch.optim.Adam``'s ``weight_decay`` does (not AdamW's decoupled decay);
- a step counter per element for the bias correction ("Since some parameters might see fewer
  steps than others, they each need their own step counter"):
  ``current_step = ++param_steps[i]; lr *= sqrt(1 - beta2^t) / (1 - beta1^t)``, then
  ``w -= lr / (sqrt(v) + eps) * m``.

What this module does (``--sparse-adam``, ``--mlp-weight-decay W``; ``train.nerf._optimizer``
builds the groups with :func:`split_groups`):

- the hash tables (every :class:`~warpnerf.fields.encoding.HashEncoding`'s ``table``
  ``[rows, features]``) are a ``lazy`` group of :class:`LazyAdam`: an element whose gradient is
  exactly zero (``g == 0``, so -0.0 too, as tiny-cuda-nn's test) keeps its value, both moments
  and its step count bit-identical; every other element takes ``torch.optim.Adam``'s update
  (same ops, same order) with the bias correction of its own step count. The test is per
  element, as tiny-cuda-nn's, not per table row: the state keeps its parameter's shape (the
  checkpoint loader checks that of every state tensor), and the F features of a touched row get
  their gradients together in practice (each a sum over the samples of an interpolation weight
  times the MLP's input gradient; hash_sdf's levels closed by the coarse-to-fine schedule give
  exact zeros to all the features of their rows alike). Memory: one float32 counter per table
  element besides Adam's two moments (tiny-cuda-nn: a uint32). Counters are float32 like
  PyTorch's (exact up to 2^24 steps of an element).
- The update is computed for the whole table and selected with ``torch.where``: no host sync,
  no data-dependent shape, the learning rate read from the group's device tensor when the
  optimiser is capturable, so the step is captured in a CUDA graph like the fused Adam it sits
  beside. Its cost: 19 elementwise passes over the table per step instead of the fused
  kernel's one: 0.73 ms a step against fused Adam's 0.13 ms for the default table (6,098,944
  rows x 2 features) plus a small MLP, captured, on an H200 (torch 2.11); a hash step is ~9 ms.
  One fused kernel, as tiny-cuda-nn's, would take that back.
- The other parameters (MLPs, biases, appearance codes, beta, pose corrections) keep PyTorch's
  Adam (fused on CUDA). With ``--mlp-weight-decay W`` the ``nn.Linear`` weights of the fields
  (the MLPs' matrices, tiny-cuda-nn's matrix weights) are a group with ``weight_decay=W``:
  ``g + W * w`` into the moments, as tiny-cuda-nn's ``l2_reg``; biases (tiny-cuda-nn's fully
  fused MLPs have none), tables, appearance codes and pose corrections get no L2.

Differences from tiny-cuda-nn, chosen so that the touched elements follow ``torch.optim.Adam``
(the update every other warpnerf run uses):

- epsilon is added to the debiased ``sqrt(v / (1 - beta2^t))`` (PyTorch), not to the raw
  ``sqrt(v)`` (tiny-cuda-nn: its eps is PyTorch's ``eps / sqrt(1 - beta2^t)``, at most 10x
  larger for beta2 0.99; with eps 1e-15 the two differ only where ``sqrt(v)`` is below ~1e-14);
- only the hash tables skip zero gradients; tiny-cuda-nn skips every non-matrix parameter, but
  warpnerf's other non-matrix parameters (biases, codes, beta) are small and dense;
- no loss scale (tiny-cuda-nn divides by it: its half-precision training), no AdaBound clamps
  (off in instant-ngp), no relative/absolute decay or clipping (0 in instant-ngp).
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["LazyAdam", "hash_tables", "mlp_weights", "split_groups"]


def hash_tables(module: nn.Module) -> list:
    """The hash-grid tables ``[rows, features]`` of every hash encoding in ``module``."""
    from ..fields.encoding import HashEncoding

    return [m.table for m in module.modules() if isinstance(m, HashEncoding)]


def mlp_weights(module: nn.Module, skip: nn.Module | None = None) -> list:
    """The weight matrices of every ``nn.Linear`` in ``module`` (not their biases), leaving out
    those inside ``skip`` (e.g. the pose corrections)."""
    left_out = {id(m) for m in skip.modules()} if skip is not None else set()
    return [m.weight for m in module.modules()
            if isinstance(m, nn.Linear) and id(m) not in left_out]  # fmt: skip


def split_groups(groups, tables=(), decayed=(), weight_decay: float = 0.0) -> list:
    """``groups`` (tensors, or dicts of parameter groups) with each group's ``tables`` moved to a
    group of their own marked ``lazy`` (:class:`LazyAdam`) and its ``decayed`` tensors to one
    with ``weight_decay``; each new group keeps its origin's other settings (``lr_scale``).
    Order: each group's other tensors, then its decayed ones, then its tables (empty groups
    left out)."""
    groups = list(groups)
    if groups and not isinstance(groups[0], dict):
        groups = [{"params": groups}]
    lazy, decay = {id(p) for p in tables}, {id(p) for p in decayed}
    out = []
    for g in groups:
        rest = {k: v for k, v in g.items() if k != "params"}
        params = list(g["params"])
        parts = (
            ([p for p in params if id(p) not in lazy and id(p) not in decay], {}),
            ([p for p in params if id(p) in decay and id(p) not in lazy],
             {"weight_decay": float(weight_decay)}),
            ([p for p in params if id(p) in lazy], {"lazy": True}),
        )  # fmt: skip
        out += [{"params": ps, **rest, **extra} for ps, extra in parts if ps]
    return out


class LazyAdam(torch.optim.Adam):
    """``torch.optim.Adam`` whose groups marked ``lazy`` (the hash tables) leave every element
    without a gradient this step untouched (value, moments, step count), with a step count per
    element for the bias correction (tiny-cuda-nn's Adam; see the module's text). Other groups
    are PyTorch's Adam as built (fused, capturable). The state dict has Adam's layout: a lazy
    parameter's ``step`` has the parameter's shape."""

    def __init__(self, params, **kw):
        super().__init__(params, **kw)
        for g in self.param_groups:
            self._check_lazy(g)

    @staticmethod
    def _check_lazy(group: dict) -> None:
        if not group.get("lazy"):
            return
        flags = ("amsgrad", "maximize", "differentiable", "decoupled_weight_decay", "weight_decay")
        bad = [k for k in flags if group.get(k)]
        if bad:
            raise ValueError(f"a lazy (hash table) group takes none of {', '.join(bad)}")

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        groups = self.param_groups
        dense = [g for g in groups if not g.get("lazy")]
        if dense:  # PyTorch's Adam on the other groups (its step walks self.param_groups)
            self.param_groups = dense
            try:
                super().step()
            finally:
                self.param_groups = groups
        for g in groups:
            if g.get("lazy"):
                self._lazy_step(g)
        return loss

    def _lazy_step(self, group: dict) -> None:
        beta1, beta2 = group["betas"]
        lr, eps = group["lr"], group["eps"]
        for p in group["params"]:
            grad = p.grad
            if grad is None:
                continue
            if grad.is_sparse:
                raise RuntimeError("LazyAdam takes dense gradients (zeros where untouched)")
            state = self.state[p]
            if len(state) == 0:
                state["step"] = torch.zeros_like(p, dtype=torch.float32,
                                                 memory_format=torch.preserve_format)  # fmt: skip
                state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            step, exp_avg, exp_avg_sq = state["step"], state["exp_avg"], state["exp_avg_sq"]
            seen = grad != 0  # tiny-cuda-nn's test, per element
            step.add_(seen)
            t = step.to(p.dtype)  # (the counts themselves for a float32 table: no copy)
            # torch.optim.Adam's update, per element, with the values of its non-capturable
            # single-tensor step: the moments (lerp, mul/addcmul), -lr / (1 - beta1^t) as
            # lr / (beta1^t - 1) (the same number, one pass fewer), sqrt(1 - beta2^t),
            # sqrt(v) / that + eps, p + (m * -step_size) / denom. Entries never seen (t = 0)
            # give inf/nan here, discarded by the selection below.
            m = torch.lerp(exp_avg, grad, 1 - beta1)
            v = (exp_avg_sq * beta2).addcmul_(grad, grad, value=1 - beta2)
            # (a tensor numerator: a true division; a number over a tensor is computed as the
            # tensor's reciprocal times the number)
            rate = lr if isinstance(lr, torch.Tensor) else torch.tensor(lr, dtype=p.dtype)
            step_size_neg = torch.div(rate, torch.pow(beta1, t).sub_(1))
            bias_correction2_sqrt = torch.rsub(torch.pow(beta2, t), 1).sqrt_()
            denom = v.sqrt().div_(bias_correction2_sqrt).add_(eps)
            new = p.addcdiv(m * step_size_neg, denom)
            torch.where(seen, m, exp_avg, out=exp_avg)
            torch.where(seen, v, exp_avg_sq, out=exp_avg_sq)
            torch.where(seen, new, p, out=p)

    def load_state_dict(self, state_dict) -> None:
        """Adam's load; the groups keep this optimiser's ``lazy`` marks (the run's config decides
        them, as the implementation flags), and a lazy parameter's step counts land on its
        device as float32 (a dense Adam's single count becomes every element's)."""
        marks = [bool(g.get("lazy")) for g in self.param_groups]
        super().load_state_dict(state_dict)
        for g, lazy in zip(self.param_groups, marks):
            g["lazy"] = lazy
            self._check_lazy(g)
            for p in g["params"]:
                state = self.state.get(p)
                if not state or "step" not in state:
                    continue
                s = state["step"]
                if lazy:
                    if s.dim() == 0:
                        s = torch.full_like(p, float(s), dtype=torch.float32)
                    state["step"] = s.to(device=p.device, dtype=torch.float32)
                elif s.dim() > 0:
                    raise ValueError("the saved optimiser state has per-element step counts "
                                     "(--sparse-adam) for a parameter this run's Adam treats "
                                     "as dense")  # fmt: skip
