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
