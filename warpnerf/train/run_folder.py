"""The run folder around the training loop (:mod:`warpnerf.train.loop`): taking its lock,
claiming a new one or checking a resumed one (the same steps for every task), and writing
checkpoints in a background thread from a host copy training cannot change."""

from __future__ import annotations

import contextlib
from pathlib import Path

import torch

from ..errors import UserError
from ..outputs import adopt, check_foreign, output_lock
from .provenance import RUN_INFO

__all__ = ["to_host", "BackgroundWriter", "lock_run", "resume_checks", "claim_run"]


def to_host(obj):
    """A copy of a checkpoint's state that training cannot change: tensors copied to the host,
    containers rebuilt (numbers and strings are immutable)."""
    if isinstance(obj, torch.Tensor):
        t = obj.detach()
        return t.clone() if t.device.type == "cpu" else t.to("cpu", copy=True)
    if isinstance(obj, dict):
        return {k: to_host(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(to_host(v) for v in obj)
    return obj


class BackgroundWriter:
    """One checkpoint write at a time in a worker thread. ``submit`` waits for the previous one;
    ``wait`` re-raises a failed write's error; leaving the ``with`` block waits for the last
    (its error raised unless another exception is already on its way), so a run that returns,
    stops or fails has every checkpoint it started on disk (each written atomically)."""

    def __init__(self):
        self._pool, self._job = None, None

    def submit(self, fn, *args) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self.wait()
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="warpnerf-ckpt")
        self._job = self._pool.submit(fn, *args)

    def wait(self) -> None:
        job, self._job = self._job, None
        if job is not None:
            job.result()

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        try:
            if exc_type is None:
                self.wait()
            else:  # (the exception on its way wins; the write still completes)
                with contextlib.suppress(BaseException):
                    self.wait()
        finally:
            if self._pool is not None:
                self._pool.shutdown(wait=True)
        return False


def lock_run(run: Path, locks: contextlib.ExitStack) -> None:
    """Takes the run folder's lock for the rest of ``locks`` (before a resume reads the run; a
    missing folder is left to the run's loader to report)."""
    if run.is_dir():
        locks.enter_context(output_lock(run, "run folder"))


def check_resume_iters(run, step: int, iters: int) -> None:
    """UserError unless ``iters`` (the total to reach) is beyond the checkpoint's ``step``."""
    if iters <= step:
        raise UserError(
            f"{run}: the checkpoint is at step {step}; --iters must be larger to continue, "
            f"got {iters}"
        )


def resume_checks(run: Path, step: int, iters: int, outputs) -> None:
    """Before continuing a run at checkpoint ``step``: ``iters`` must go beyond it, and the
    run's files (from before the manifest existed, or copied) become the run's own."""
    check_resume_iters(run, step, iters)
    adopt(run, (*outputs, RUN_INFO))


def claim_run(run: Path, locks: contextlib.ExitStack, outputs, checkpoint: str) -> None:
    """For a new run, once its data has loaded: locks the folder, refuses it if a run started
    there meanwhile (another process), and refuses to replace files warpnerf did not write."""
    locks.enter_context(output_lock(run, "run folder"))
    if (run / checkpoint).exists():
        raise UserError(f"{run}: already holds a run; choose another --out")
    check_foreign([run / n for n in (*outputs, RUN_INFO)])
