"""SIGINT/SIGTERM during training: finish the current step, checkpoint, then stop."""

from __future__ import annotations

import contextlib
import signal
import threading


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
