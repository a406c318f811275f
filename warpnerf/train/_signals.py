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


def check_finite(step: int, loss, params, run, lr: float | None = None) -> None:
    """:class:`Diverged` unless the loss and every gradient of ``params`` are finite; called after
    ``backward()`` and before the optimiser step, so a diverging step changes nothing and is
    never checkpointed. One fused norm per gradient list and one host sync (the loops
    synchronise every step anyway to log the loss)."""
    import torch

    from ..errors import Diverged

    grads = [p.grad for p in params if p.grad is not None]
    bad_loss = ~torch.isfinite(loss.detach())
    if grads:
        norms = torch.stack([n.float() for n in torch._foreach_norm(grads, float("inf"))])
        bad_grad = ~torch.isfinite(norms).all()
        flags = torch.stack([bad_loss.reshape(()), bad_grad.reshape(())]).tolist()
    else:
        flags = [bool(bad_loss), False]
    if flags[0]:
        raise Diverged(step, f"the loss ({loss.item()})", run, lr)
    if flags[1]:
        raise Diverged(step, "a gradient", run, lr)
