"""``warpnerf train ... --viewer``: the web viewer live during training, as a
:class:`~warpnerf.train.loop.LoopHook`.

Frames are rendered in the training thread, between steps (:meth:`Viewer.tick`): training waits
while a frame renders, so a frame never sees a half-updated model or occupancy grid, and the
training itself is unchanged (no random numbers drawn, no state touched: a run trained with the
viewer equals one trained without). With nobody connected a step costs one check; with a browser
watching, frames are spaced so that rendering takes at most about a fifth of the wall time, and
the loop does not count that time as training time (as for validation).
"""

from __future__ import annotations

from ..train.loop import LoopHook

__all__ = ["LiveViewer"]


class LiveViewer(LoopHook):
    """Serves the training model on ``host:port`` from the first step to the end."""

    def __init__(self, run, host: str = "127.0.0.1", port: int = 7007, log=print, **viewer_kw):
        self.run, self.host, self.port, self.log = run, host, port, log
        self.viewer_kw = viewer_kw
        self.viewer = None

    def on_start(self, task, step: int) -> None:
        from .scene import RunScene
        from .server import Viewer

        model, cfg = task.model, task.cfg
        scene = RunScene.of_radiance(model, cfg, getattr(task, "train", None),
                                     title=f"{self.run}: {cfg.field} (training)")  # fmt: skip
        self.viewer = Viewer(scene, host=self.host, port=self.port, run=self.run, live=True,
                             log=self.log, **self.viewer_kw)  # fmt: skip
        self.log(f"viewer: {self.viewer.url} (live; frames render between training steps)")

    def on_step(self, step: int, history: dict, lr: float) -> None:
        v = self.viewer
        v.weights_changed()
        v.tick()

    def close(self) -> None:
        if self.viewer is not None:
            self.viewer.close()
            self.viewer = None
