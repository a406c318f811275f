"""SIGINT/SIGTERM during training: finish the current step, checkpoint, then stop; and the check
every ``--resume`` makes before continuing."""

from __future__ import annotations

import contextlib
import signal
import threading

from ..errors import UserError


@contextlib.contextmanager
def stop_requests():
    """Yields a dict whose "signum" becomes the number of the first SIGINT/SIGTERM received;
    the previous handlers come back on exit. Outside the main thread nothing is installed
    (Python only delivers signals there)."""
    state = {"signum": None}
    if threading.current_thread() is not threading.main_thread():
        yield state
        return

    def handler(signum, frame):
        if state["signum"] is None:
            state["signum"] = signum

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield state
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def check_resume_iters(run, step: int, iters: int) -> None:
    """UserError unless ``iters`` (the total to reach) is beyond the checkpoint's ``step``."""
    if iters <= step:
        raise UserError(
            f"{run}: the checkpoint is at step {step}; --iters must be larger to continue, "
            f"got {iters}"
        )


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
