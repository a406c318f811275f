"""``warpnerf train ... --viewer``: the web viewer live during training (every task: NeRF and
VolSDF, neural SDFs from points, the box fit), as a :class:`~warpnerf.train.loop.LoopHook`.

Frames are rendered in the training thread, between steps (:meth:`Viewer.tick`): training waits
while a frame renders, so a frame never sees a half-updated model or occupancy grid, and the
training itself is unchanged (no random numbers drawn, no state touched: a run trained with the
viewer equals one trained without). With nobody connected a step costs one check; with a browser
watching, frames are spaced so that rendering takes at most about a fifth of the wall time, and
the loop does not count that time as training time (as for validation). Ctrl-C or SIGTERM
while a frame renders stops the frame at its next block (about 0.2 s) and reaches the training
loop's own handler, which finishes the step, checkpoints and stops; closing the viewer then
takes about 2 s at most.
"""

from __future__ import annotations

import time

from ..train.loop import LoopHook

__all__ = ["LiveViewer"]


def scene_of_task(task, title: str = ""):
    """The :class:`~warpnerf.viewer.scene.RunScene` of a training task's live model (its
    method's ``open_task``: a NeRF/VolSDF task, a neural SDF fitted to points, a box fit)."""
    from ..train.methods import method_of_task
    from .scene import scene_of

    method = method_of_task(task)
    opened = method.open_task(task)
    opened.title = title
    return scene_of(method, opened)


def training_text(step: int, history: dict) -> str:
    """The panel's line about a training: step, training seconds, loss and PSNR (if any)."""
    parts = [f"step {step}", f"{history['seconds'][-1]:.0f} s", f"loss {history['loss'][-1]:.4g}"]
    if history.get("psnr"):
        parts.append(f"psnr {history['psnr'][-1]:.2f}")
    return ", ".join(parts)


class LiveViewer(LoopHook):
    """Serves the training model on ``host:port`` from the first step to the end."""

    def __init__(self, run, host: str = "127.0.0.1", port: int = 7007, log=print, **viewer_kw):
        self.run, self.host, self.port, self.log = run, host, port, log
        self.viewer_kw = viewer_kw
        self.viewer = None
        self._shown_at, self._last_val = 0.0, ""

    def on_start(self, task, step: int) -> None:
        from .server import Viewer

        scene = scene_of_task(task, f"{self.run} (training)")
        kw = {"refine_seconds": 8.0, **self.viewer_kw}  # (frames hold the training up)
        self.viewer = Viewer(scene, host=self.host, port=self.port, run=self.run, live=True,
                             log=self.log, **kw)  # fmt: skip
        self.log(f"viewer: {self.viewer.url} (live; frames render between training steps)")

    def on_step(self, step: int, history: dict, lr: float) -> None:
        v = self.viewer
        v.weights_changed()
        if v.watched():
            now = time.perf_counter()
            if now - self._shown_at >= 1.0:  # the panel's training line, once a second
                self._shown_at = now
                v.set_training_text(training_text(step, history))
            v.tick()

    def on_validation(self, step: int, figures: dict, task) -> None:
        if self.viewer is not None:
            self._last_val = ", ".join(f"{k} {v:.2f}" for k, v in figures.items()
                                       if isinstance(v, (int, float)))  # fmt: skip
            self.viewer.set_training_text(self._last_val)

    def close(self) -> None:
        if self.viewer is not None:
            self.viewer.close()
            self.viewer = None
