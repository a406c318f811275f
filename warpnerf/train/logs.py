"""Training logs that plotting tools read: TensorBoard event files beside ``history.json``.

:class:`TensorBoardLog` is a :class:`~warpnerf.train.loop.LoopHook`. Every ``log_every`` steps
(default 10, nerfstudio's default) it writes one event holding that step's history entries as
scalars (``train/loss``, ``train/psnr``, ``train/samples_per_ray``, ``train/beta``, ... whatever
the task records), the learning rate (``train/lr``) and the mean training time per step since the
previous record (``train/step_ms``); ``history.json`` keeps every step. After every validation
it writes the figures (``val/val_psnr``) and, when the task kept them, the first validation
image's prediction beside its ground truth (``val/rgb``) and its depth (``val/depth``). Files go
to ``RUN/tensorboard/`` (``tensorboard --logdir RUN``); tensorboardX's background thread writes
them. A resumed run writes a new file that starts with a purge marker at the first step it logs,
so TensorBoard drops what an interrupted run logged past its last checkpoint and the curves
continue without overlap. Cost: about 15 us in the training thread per record plus the writer
thread's pure-Python CRC (about 80 us a record), measured in docs/design/viewer.md (issue 19).
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import numpy as np

from ..errors import UserError
from .loop import LoopHook

__all__ = ["TensorBoardLog", "TENSORBOARD_DIR"]

TENSORBOARD_DIR = "tensorboard"  # RUN/tensorboard/events.out.tfevents.*
_SKIP = ("step", "seconds", "val_step")


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


class TensorBoardLog(LoopHook):
    """Writes a training's curves to ``run/tensorboard`` (see the module's docstring)."""

    def __init__(self, run, log_every: int = 10, flush_secs: float = 10.0):
        try:
            from tensorboardX import SummaryWriter
        except ImportError as e:  # a dependency; a broken install says how to fix it
            raise UserError(f"TensorBoard logs need tensorboardX ({e}); pip install "
                            "tensorboardX, or pass --no-tensorboard") from None  # fmt: skip
        self.dir = Path(run) / TENSORBOARD_DIR
        if self.dir.is_symlink() or (self.dir.exists() and not self.dir.is_dir()):
            raise UserError(f"{self.dir}: exists and is not a folder warpnerf made; move it away "
                            "or pass --no-tensorboard")  # fmt: skip
        if int(log_every) < 1:
            raise UserError(f"--log-every must be a positive number of steps, got {log_every}")
        self._writer_cls = SummaryWriter
        self.writer = None
        self.flush_secs, self.log_every = flush_secs, int(log_every)
        self._last = None  # (step, training seconds) of the last logged step

    def on_start(self, task, step: int) -> None:
        self.dir.mkdir(exist_ok=True)
        # a name no earlier file has (the writer opens its file for writing)
        suffix = f".{os.getpid()}.{time.time_ns()}"
        # purge_step: TensorBoard drops earlier files' events from the first step this file
        # logs (``step`` steps are done) on: a resume after an interruption, a box fit started
        # over in its folder
        self.writer = self._writer_cls(
            str(self.dir), purge_step=step + 1, flush_secs=self.flush_secs, max_queue=1000,
            filename_suffix=suffix,
        )  # fmt: skip

    def on_step(self, step: int, history: dict, lr: float) -> None:
        if step % self.log_every:
            return
        from tensorboardX.proto.summary_pb2 import Summary

        n, vals = len(history["step"]), []
        for k, v in history.items():
            if k in _SKIP or not isinstance(v, list) or len(v) != n or not _finite(v[-1]):
                continue
            vals.append((f"train/{k}", v[-1]))
        vals.append(("train/lr", lr))
        s = history["seconds"][-1]
        if self._last is not None and step > self._last[0]:  # mean over the steps since
            vals.append(("train/step_ms", 1e3 * (s - self._last[1]) / (step - self._last[0])))
        self._last = (step, s)
        # one event per logged step, all scalars in it (a tenth of add_scalar's cost)
        summary = Summary(value=[Summary.Value(tag=t, simple_value=float(v)) for t, v in vals])
        self.writer._get_file_writer().add_summary(summary, step)

    def on_validation(self, step: int, figures: dict, task) -> None:
        for k, v in figures.items():
            if _finite(v):
                self.writer.add_scalar(f"val/{k}", v, step)
        images = getattr(task, "val_images", None) or {}
        for name, img in images.items():  # HxWx3 (or HxW) floats in [0, 1]
            a = np.clip(np.nan_to_num(np.asarray(img, dtype=np.float32)), 0.0, 1.0)
            fmt = "HWC" if a.ndim == 3 else "HW"
            self.writer.add_image(f"val/{name}", a, step, dataformats=fmt)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None
