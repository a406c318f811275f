"""Divergence checks of a training step: the loss and every gradient finite, read without a host
sync (:func:`nonfinite_flags`, then :func:`raise_if_diverged` at a sync the loop makes) or at
once (:func:`check_finite`); :class:`~warpnerf.errors.Diverged` names the step."""

from __future__ import annotations


def nonfinite_flags(loss, params):
    """A [2] bool tensor on the loss's device: (loss not finite, some gradient of ``params`` not
    finite). No host sync: one fused max-norm over the gradient list; read it with
    :func:`raise_if_diverged` at a sync the loop makes anyway."""
    import torch

    grads = [p.grad for p in params if p.grad is not None]
    bad_loss = (~torch.isfinite(loss.detach())).reshape(())
    if not grads:
        return torch.stack([bad_loss, torch.zeros_like(bad_loss)])
    norms = torch.stack([n.float() for n in torch._foreach_norm(grads, float("inf"))])
    return torch.stack([bad_loss, ~torch.isfinite(norms).all().to(bad_loss.device)])


def raise_if_diverged(flags, step: int, loss_value, run, lr: float | None = None) -> None:
    """:class:`Diverged` naming the step if ``flags`` (host values of :func:`nonfinite_flags`)
    say the loss or a gradient was not finite."""
    from ..errors import Diverged

    if flags[0]:
        raise Diverged(step, f"the loss ({loss_value})", run, lr)
    if flags[1]:
        raise Diverged(step, "a gradient", run, lr)


def check_finite(step: int, loss, params, run, lr: float | None = None) -> None:
    """:class:`Diverged` unless the loss and every gradient of ``params`` are finite; called after
    ``backward()`` and before the optimiser step, so a diverging step changes nothing and is
    never checkpointed (one host sync; the NeRF loop instead reads :func:`nonfinite_flags` at the
    sync it makes after the step, and never saves a step that diverged)."""
    flags = nonfinite_flags(loss, params).tolist()
    raise_if_diverged(flags, step, float(loss.detach()) if flags[0] else None, run, lr)
