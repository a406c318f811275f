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

``keep=True`` (``train ... --viewer`` at a terminal): the loop's end leaves the server up; the
command then serves the finished run (:meth:`LiveViewer.serve_finished`: frames render in a
background thread, as ``warpnerf view``'s) until Ctrl-C, or closes it
(:meth:`LiveViewer.shutdown`) when the training failed or stopped.
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
    """Serves the training model on ``host:port`` from the first step to the end (with
    ``keep``, on after it: :meth:`serve_finished`)."""

    def __init__(self, run, host: str = "127.0.0.1", port: int = 7007, log=print,
                 keep: bool = False, **viewer_kw):  # fmt: skip
        self.run, self.host, self.port, self.log = run, host, port, log
        self.keep = keep  # the loop's end leaves the server up (serve_finished / shutdown)
        self.viewer_kw = viewer_kw
        self.viewer = None
        self.url = None
        self._task = None
        self._step, self._history = None, None
        self._shown_at, self._last_val = 0.0, ""

    def on_start(self, task, step: int) -> None:
        from .server import Viewer

        self._task = task
        scene = scene_of_task(task, f"{self.run} (training)")
        kw = {"refine_seconds": 8.0, **self.viewer_kw}  # (frames hold the training up)
        self.viewer = Viewer(scene, host=self.host, port=self.port, run=self.run, live=True,
                             log=self.log, **kw)  # fmt: skip
        self.url = self.viewer.url
        self.log(f"viewer: {self.viewer.url} (live; frames render between training steps)")

    def on_step(self, step: int, history: dict, lr: float) -> None:
        self._step, self._history = step, history
        v = self.viewer
        v.weights_changed()
        if v.watched():
            now = time.perf_counter()
            if now - self._shown_at >= 1.0:  # the panel's training line, once a second
                self._shown_at = now
                v.set_training_text(training_text(step, history))
            v.tick(self._task.eval_weights)  # (--ema: the averaged weights, as a saved run's)

    def on_validation(self, step: int, figures: dict, task) -> None:
        if self.viewer is not None:
            self._last_val = ", ".join(f"{k} {v:.2f}" for k, v in figures.items()
                                       if isinstance(v, (int, float)))  # fmt: skip
            self.viewer.set_training_text(self._last_val)

    def close(self) -> None:
        """The loop's end: the server closes, unless ``keep`` (then :meth:`serve_finished` or
        :meth:`shutdown` does, whoever made the hook)."""
        if self.keep and self.viewer is not None:
            return
        self.shutdown()

    def shutdown(self) -> None:
        """Closes the server (about 2 s at most; nothing if it is closed)."""
        if self.viewer is not None:
            self.viewer.close()
            self.viewer = None

    def serve_finished(self, exit_after: float | None = None) -> str:
        """After the training: serves the finished model (the saved run's weights: ``--ema``'s
        average) until Ctrl-C or SIGTERM (or ``exit_after`` seconds), frames rendering in a
        background thread; then closes the server. Returns why it stopped ("signal",
        "timeout"), or "closed" when there was no server to keep."""
        v = self.viewer
        if v is None:
            return "closed"
        done = f"finished at {training_text(self._step, self._history)}" if self._step else (
            "finished")  # fmt: skip
        v.set_training_text(done + (f"; {self._last_val}" if self._last_val else ""))
        v._bump()  # (every browser's frame is redrawn once, with the final weights)
        try:
            with self._task.eval_weights():
                return v.serve_until_stopped(exit_after)
        finally:
            self.viewer = None
