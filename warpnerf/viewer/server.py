"""The web viewer: a viser server (a three.js page served on a local port) whose background is
the run rendered by the project's own renderer from each browser's camera.

Each connected browser has its own camera; a frame is rendered when that camera moves, when the
mode changes, and (live training) when the weights have changed. The resolution adapts to the
measured render speed (seconds per ray): while the camera moves, frames are sized to take about
``frame_seconds`` (coarse, fast); once it has been still for ``settle_seconds``, still frames
refine it: the first sized to take at most ``still_seconds``, each next one allowed 4 times
longer, up to the full resolution (the browser canvas, at most ``max_resolution`` pixels a
side) or ``refine_seconds`` a frame. A frame renders in blocks of rays sized to take about
``BLOCK_SECONDS`` and stops at the next block when it is no longer wanted: a newer camera, the
browser gone, the viewer closing, or (live training) Ctrl-C/SIGTERM.

:meth:`Viewer.close` is bounded (about 2 s): the render thread stops at its next block, and
viser's own stop (which may wait seconds on its event loop for browsers to answer the close)
runs in a daemon thread that is waited for at most the rest of the time; the listening socket is
the first thing it closes.

Overlays drawn by the browser itself (three.js, toggled in the panel): the training cameras as
frustums showing their images, the scene box, the occupancy grid's occupied cells, a mesh
(RUN/mesh.ply from ``warpnerf mesh`` or ``--mesh FILE``, with its vertex colours), and the
camera path being edited. The camera-path editor adds the current view as a keyframe, flies the
browser's camera along the path ("Preview") and saves it as a JSON file in the run folder that
``warpnerf render RUN --path FILE`` renders to video (:mod:`warpnerf.data.camera_path`). "Reload
checkpoint" re-reads the run's checkpoint (a training in another process keeps writing it).

The server binds 127.0.0.1 unless told otherwise (``host``: other addresses print a warning
naming the exposure). Every request needs the token in :attr:`Viewer.url` (or the cookie its
page sets), and a websocket from another site's page is refused (:mod:`.gate`). Every value a
browser sends is checked here: camera parameters (non-finite ones refused, the frame not
rendered), the resolution (never above ``max_resolution``), the path's frame count (at most
:data:`~warpnerf.data.camera_path.MAX_FRAMES`, flown lazily by "Preview") and keyframe count; a
panel callback that raises leaves one line in the panel and the log, never a traceback.
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import signal
import threading
import time
import warnings
from pathlib import Path

import numpy as np

from ..data.camera_path import MAX_FRAMES
from ..errors import UserError
from .access import Gate, check_address, client_pose, exposure
from .path_editor import PathEditor, gl_to_opencv, opencv_to_gl
from .scene import Aborted, RunScene

__all__ = ["Viewer", "opencv_to_gl", "gl_to_opencv", "signals_to"]

MAX_RESOLUTION = 4096  # pixels on the longest side of a frame
BLOCK_SECONDS = 0.2  # a frame checks whether it is still wanted about this often
FIRST_WIDTH = 16  # pixels across the first frame, which measures the render speed


@contextlib.contextmanager
def signals_to(handler):
    """While inside, SIGINT (Ctrl-C) and SIGTERM call ``handler(signum, frame, previous)``
    (``previous``: the handler it replaced); the previous handlers come back on exit. Outside
    the main thread nothing is installed (Python delivers signals to the main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {}

    def on_signal(signum, frame):
        handler(signum, frame, old[signum])

    for sig in (signal.SIGINT, signal.SIGTERM):
        old[sig] = signal.signal(sig, on_signal)
    try:
        yield
    finally:
        for sig, prev in old.items():
            if signal.getsignal(sig) is on_signal:
                signal.signal(sig, prev if prev is not None else signal.SIG_DFL)


def _quiet_viser() -> None:
    """Drops two messages that are not errors: viser's warning when a frame is sent to a browser
    that disconnected an instant before (the frame is simply not delivered), and websockets'
    traceback when something opens the port and closes it without a request (a port probe)."""
    warnings.filterwarnings(
        "ignore", "Queued a BackgroundImageMessage on a closed connection", UserWarning
    )

    class NoProbe(logging.Filter):
        def filter(self, record):
            return record.getMessage() != "opening handshake failed"

    log = logging.getLogger("websockets.server")
    if not any(type(f).__name__ == "NoProbe" for f in log.filters):
        log.addFilter(NoProbe())


class _ClientState:
    def __init__(self, client):
        self.client = client
        self.pose = None  # (c2w [4, 4], fov_y, aspect, canvas width) of the latest camera
        self.moved_at = 0.0
        self.version = 0  # bumped by every camera or mode change
        self.gone = False  # the browser disconnected
        # (version, weights version, level, final) of the last frame shown: level 0 while the
        # camera moves, 1, 2, ... the still frames; final: no finer frame will follow
        self.shown = (-1, -1, 0, False)


class Viewer(PathEditor):
    """A viser server showing ``scene`` (:class:`~warpnerf.viewer.scene.RunScene`).

    ``live`` False: a background thread renders frames (``warpnerf view``). ``live`` True: the
    owner calls :meth:`tick` between training steps and frames are rendered there, in the
    training thread (so a frame never sees a half-updated model or occupancy grid); call
    :meth:`weights_changed` after each step.
    """

    def __init__(self, scene: RunScene, *, host: str = "127.0.0.1", port: int = 7007,
                 run=None, live: bool = False, frame_seconds: float = 0.1,
                 settle_seconds: float = 0.3, still_seconds: float = 2.0,
                 refine_seconds: float = 60.0, max_resolution: int = 800,
                 refresh_seconds: float = 2.0, log=print):  # fmt: skip
        import viser

        self.scene, self.live, self.log = scene, live, log
        self.frame_seconds, self.settle_seconds = float(frame_seconds), float(settle_seconds)
        self.still_seconds, self.refine_seconds = float(still_seconds), float(refine_seconds)
        self.max_resolution, self.refresh_seconds = int(max_resolution), float(refresh_seconds)
        self.run = Path(run) if run is not None else None
        self.frames = 0
        self.weights_version, self._weights_at = 0, 0.0
        self._clients: dict[int, _ClientState] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._signalled = False  # live: a SIGINT/SIGTERM arrived while a frame rendered
        self._closed = False
        self._path: list = []
        self._path_handles: list = []
        self._last_tick_frame = self._last_frame_seconds = 0.0  # live: when and how long
        self.render_seconds = 0.0  # time spent rendering (live: taken from training)
        self._previews: dict = {}  # client id -> the number of its latest "Preview" click
        check_address(host)
        _quiet_viser()
        self.gate = Gate()
        try:
            # (viser prints a panel with its address, without the token, whatever `verbose`
            # says: the one address to open is the tokened URL this viewer prints)
            with self.gate.installed(), contextlib.redirect_stdout(io.StringIO()):
                self.server = viser.ViserServer(host=host, port=port, label="warpnerf",
                                                verbose=False)  # fmt: skip
        except OSError as e:
            raise UserError(f"viewer: cannot listen on {host}:{port} ({e.strerror or e})") from None
        if not self.gate.hooked:  # (a viser that no longer starts websockets.serve: fail closed)
            self.server.stop()
            raise RuntimeError("viewer: cannot install the token check on viser's server")
        self.port = self.server.get_port()
        shown = "localhost" if host in ("127.0.0.1", "localhost") else host
        self.url = f"http://{shown}:{self.port}/?token={self.gate.token}"
        warning = exposure(host, self.port)
        if warning is not None:
            self.log(warning)
        self._build_scene()
        self._build_gui()
        self.server.on_client_connect(self._guarded("connect", self._connect))
        self.server.on_client_disconnect(self._guarded("disconnect", self._disconnect))
        self._thread = None
        if not live:
            self._thread = threading.Thread(target=self._render_loop, daemon=True)
            self._thread.start()

    # ----------------------------------------------------------------------------- scene

    def _build_scene(self) -> None:
        sc, s = self.scene, self.server.scene
        s.set_up_direction(tuple(sc.up))
        b = sc.box
        corners = np.array([[x, y, z] for x in (b[0], b[3]) for y in (b[1], b[4])
                            for z in (b[2], b[5])])  # fmt: skip
        edges = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5),
                 (2, 6), (3, 7)]  # fmt: skip
        if max(b[3] - b[0], b[4] - b[1], b[5] - b[2]) > 0:  # (no box: nothing to draw)
            s.add_line_segments("/box", corners[np.array(edges)], (240, 160, 40),
                                thickness=2.0, thickness_units="screen")  # fmt: skip
        self.frustums = []
        if sc.cameras is not None:
            n = len(sc.cameras)
            w, h = sc.size
            pick = np.unique(np.linspace(0, n - 1, min(n, 200)).round().astype(int))
            scale = sc.frustum_scale
            for i in pick:
                k = sc.intrinsics[i]
                wxyz, pos = gl_to_opencv(sc.cameras[i])
                fov = 2 * np.arctan(0.5 * h / float(k[1]))
                img = sc.images[i] if sc.images is not None else None
                self.frustums.append(s.add_camera_frustum(
                    f"/cameras/{i}", fov=float(fov), aspect=w / h, scale=scale, image=img,
                    wxyz=wxyz, position=pos, color=(60, 90, 200),
                ))  # fmt: skip
        self.grid_points = None
        self._show_grid()
        self.mesh = None
        if sc.mesh is not None:
            v, f, c = sc.mesh
            if c is not None:  # the baked vertex colours (`mesh --colors`), through trimesh
                import trimesh

                tm = trimesh.Trimesh(v, f, vertex_colors=c, process=False)
                self.mesh = s.add_mesh_trimesh("/mesh", tm, visible=False)
            else:
                self.mesh = s.add_mesh_simple("/mesh", v, f, color=(200, 180, 110), visible=False)

    def _show_grid(self) -> None:
        pts = self.scene.occupied_cells()
        if pts is None:
            return
        visible = self.grid_points.visible if self.grid_points is not None else False
        size = (self.scene.box[3] - self.scene.box[0]) / max(self.scene.grid.res, 1)
        self.grid_points = self.server.scene.add_point_cloud(
            "/occupancy", pts.astype(np.float32), (255, 140, 0), point_size=float(size),
            visible=visible,
        )  # fmt: skip

    def _guarded(self, what: str, fn):
        """``fn`` as a viser callback: an exception it raises becomes one line in the panel's
        status and the log (``what failed: ...``), never a traceback or a dead server."""

        def run(*args):
            try:
                return fn(*args)
            except Exception as e:  # noqa: BLE001 (a browser's request must not kill the server)
                self._say(f"{what} failed: {type(e).__name__}: {e}")

        return run

    def _say(self, msg: str, line=None) -> None:
        """``msg`` in the panel (``line``, default the status line) and the log."""
        with contextlib.suppress(Exception):  # (the server may be stopping)
            (line or self.status).content = msg[:300]
        self.log(f"viewer: {msg[:300]}")

    def _build_gui(self) -> None:
        g, guard = self.server.gui, self._guarded
        g.add_markdown(f"**warpnerf** {self.scene.title}")
        self.mode = g.add_dropdown("Mode", self.scene.modes, initial_value=self.scene.modes[0])
        self.mode.on_update(guard("mode", lambda _: self._bump()))
        top = min(max(self.max_resolution, 64), MAX_RESOLUTION)
        self.max_res = g.add_slider("Max resolution", 64, top, 32, top)
        self.max_res.on_update(guard("resolution", lambda _: self._bump()))
        self.status = g.add_markdown("rendered frames: 0")
        self.train_info = g.add_markdown("training: starting") if self.live else None
        if self.scene.reload is not None and not self.live:
            reload = g.add_button("Reload checkpoint")
            reload.on_click(guard("reload", lambda _: self._reload()))
        with g.add_folder("Overlays"):
            show_cams = g.add_checkbox("Training cameras", True)
            show_cams.on_update(guard("cameras", lambda e: [
                setattr(f, "visible", bool(show_cams.value)) for f in self.frustums]))  # fmt: skip
            if self.grid_points is not None:
                show_grid = g.add_checkbox("Occupancy grid", False)

                def toggle_grid(_):
                    if self.live and show_grid.value:
                        self._show_grid()  # (the grid changes while training)
                    self.grid_points.visible = bool(show_grid.value)

                show_grid.on_update(guard("occupancy grid", toggle_grid))
            if self.mesh is not None:
                show_mesh = g.add_checkbox("Mesh", False)
                show_mesh.on_update(guard("mesh", lambda _: setattr(
                    self.mesh, "visible", bool(show_mesh.value))))  # fmt: skip
        with g.add_folder("Camera path"):
            add = g.add_button("Add keyframe (this view)")
            undo = g.add_button("Remove last keyframe")
            clear = g.add_button("Clear")
            self.path_frames = g.add_number("Frames", 120, min=1, max=MAX_FRAMES, step=1)
            self.path_loop = g.add_checkbox("Loop", False)
            self.path_file = g.add_text("File (in the run folder)", "camera_path.json")
            save = g.add_button("Save path")
            preview = g.add_button("Preview path (this browser)")
            self.path_info = g.add_markdown("keyframes: 0")
        preview.on_click(guard("preview", lambda e: self._start_preview(e.client)))
        add.on_click(guard("add keyframe", lambda e: self._add_keyframe(e.client)))
        undo.on_click(guard("remove keyframe", lambda _: self._set_path(self._path[:-1])))
        clear.on_click(guard("clear", lambda _: self._set_path([])))
        save.on_click(guard("save path", lambda e: self._save_path(e.client)))

    def _reload(self) -> None:
        try:
            step = self.scene.reload()
            self.weights_version += 1
            if self.grid_points is not None:
                self._show_grid()
            msg = f"reloaded the checkpoint of step {step}"
        except Exception as e:  # a checkpoint being replaced, a broken file: keep the old one
            msg = f"reload failed: {e}"
        self._say(msg)

    # ---------------------------------------------------------------------------- clients

    def _connect(self, client) -> None:
        if self._stop.is_set():
            return
        st = _ClientState(client)
        with self._lock:
            self._clients[client.client_id] = st
        sc = self.scene
        target = sc.target()
        if sc.cameras is not None:  # start behind the first training camera: the scene and
            w, h = sc.size  # the nearer cameras in view
            client.camera.fov = float(2 * np.arctan(0.5 * h / float(sc.intrinsics[0][1])))
            c0 = np.asarray(sc.cameras[0][:3, 3], dtype=np.float64)
            client.camera.position = tuple(target + 1.8 * (c0 - target))
        else:
            client.camera.position = tuple(target + 2.5 * np.asarray(sc.up)[[1, 2, 0]])
        client.camera.look_at = tuple(target)
        client.camera.up_direction = tuple(sc.up)
        client.camera.on_update(self._guarded("camera", lambda cam: self._camera(st)))

    def _disconnect(self, client) -> None:
        with self._lock:
            st = self._clients.pop(client.client_id, None)
            self._previews.pop(client.client_id, None)  # (its preview stops)
        if st is not None:
            st.gone = True  # (a frame rendering for it stops at its next block)

    def _camera(self, st: _ClientState) -> None:
        """A browser's camera moved: its pose checked (:func:`~.gate.client_pose`); a camera
        with non-finite values is refused (no frame; the panel says why)."""
        try:
            wxyz, position, fov, aspect, width = client_pose(st.client.camera)
        except ValueError as e:
            self._say(f"camera refused: {e}")
            return
        c2w = opencv_to_gl(wxyz, position)
        with self._lock:
            st.pose = (c2w, fov, aspect, width)
            st.moved_at = time.perf_counter()
            st.version += 1

    def _bump(self) -> None:
        with self._lock:
            for st in self._clients.values():
                st.version += 1

    def watched(self) -> bool:
        """Whether a browser is connected."""
        return bool(self._clients)

    def set_training_text(self, text: str) -> None:
        """Live training: the panel's training line (step, loss, PSNR, validation)."""
        if self.train_info is not None:
            self.train_info.content = f"training: {text}"

    def weights_changed(self) -> None:
        """Live training: the model changed (re-rendered at most every refresh_seconds)."""
        now = time.perf_counter()
        if now - self._weights_at >= self.refresh_seconds:
            self.weights_version += 1
            self._weights_at = now

    # -------------------------------------------------------------------------- rendering

    def resolution_cap(self, canvas: int = 0) -> int:
        """The longest side of the next frame at most: the slider's value (a browser may send
        any number: bounded here), never above ``max_resolution`` nor the browser's canvas
        (``canvas`` pixels across; 0: unknown), at least 16."""
        try:
            slider = float(self.max_res.value)
        except (TypeError, ValueError, OverflowError):
            slider = math.nan
        top = min(self.max_resolution, MAX_RESOLUTION)
        cap = int(min(slider, top)) if math.isfinite(slider) else top
        if canvas and canvas > 0:
            cap = min(cap, int(canvas))
        return max(16, cap)

    def _size(self, aspect: float, canvas: int, level: int) -> tuple:
        """(width, height, final) of the next frame, the longest side at most the slider's value
        (and the canvas): level 0 (moving) sized to take ``frame_seconds``; still level k sized
        to take at most ``still_seconds * 4**(k-1)`` (at most ``refine_seconds``) at the measured
        speed; final when it is the full size or may take ``refine_seconds``."""
        aspect = min(max(aspect, 1e-2), 1e2) if math.isfinite(aspect) else 1.0
        cap = self.resolution_cap(canvas)
        cap_w = cap if aspect >= 1 else max(1, int(cap * aspect))  # the longest side <= cap

        def dims(w: int) -> tuple:
            w = max(16, min(cap_w, w))
            return w, max(8, min(cap, int(round(w / aspect))))

        def within(seconds: float) -> int:  # rays that render in that time
            return self.scene.rays_within(seconds, BLOCK_SECONDS)

        if self.scene.ray_seconds is None:  # the speed is not known yet: a small frame measures it
            return (*dims(FIRST_WIDTH), False)
        if level == 0:
            return (*dims(int((within(self.frame_seconds) * aspect) ** 0.5)), False)
        full = dims(cap_w)
        budget = min(self.still_seconds * 4.0 ** (level - 1), self.refine_seconds)
        n = within(budget)
        if full[0] * full[1] <= n:
            return (*full, True)
        w, h = dims(int(full[0] * (n / (full[0] * full[1])) ** 0.5))
        return w, h, budget >= self.refine_seconds or (w, h) == full

    def _next_job(self):
        """(state, version, weights version, level) of the frame most worth rendering now (level
        0: a moving camera's; 1, 2, ...: the still camera's refinements), or None."""
        now = time.perf_counter()
        with self._lock:
            for st in self._clients.values():
                if st.pose is None:
                    continue
                still = now - st.moved_at >= self.settle_seconds
                v, wv = st.version, self.weights_version
                if st.shown[:2] != (v, wv):
                    return st, v, wv, 1 if still else 0
                if still and not st.shown[3]:
                    return st, v, wv, st.shown[2] + 1
        return None

    def _render_job(self, job) -> bool:
        st, version, wversion, level = job
        c2w, fov, aspect, canvas = st.pose
        if self.scene.ray_seconds is None:
            level = 0  # (a frame measuring the speed is no step of a still frame's refinement)
        w, h, final = self._size(aspect, canvas, level)
        f = 0.5 * h / np.tan(0.5 * fov)

        def unwanted():  # a newer camera, the browser gone, the viewer closing, a stop request
            return st.version != version or st.gone or self._stop.is_set() or self._signalled

        t0 = time.perf_counter()
        try:
            mode = str(self.mode.value)
            mode = mode if mode in self.scene.modes else self.scene.modes[0]
            img = self.scene.render(c2w, f, f, w, h, mode, abort=unwanted,
                                    block_seconds=BLOCK_SECONDS)  # fmt: skip
        except Aborted:
            return False
        dt = time.perf_counter() - t0
        self.render_seconds += dt
        if st.gone or self._stop.is_set():
            return False  # nobody to send it to (viser would warn of a closed connection)
        st.client.scene.set_background_image(img, format="jpeg", jpeg_quality=90)
        st.shown = (version, wversion, level, final)
        self.frames += 1
        self.status.content = (f"rendered frames: {self.frames}, last {w}x{h} in "
                               f"{1e3 * dt:.0f} ms")  # fmt: skip
        return True

    def _failed(self, job, e: Exception) -> None:
        """A frame that raised: not retried until the camera moves; said in the panel."""
        job[0].shown = (job[1], job[2], job[3], True)
        if not self._stop.is_set():
            self.status.content = f"render failed: {e}"
            self.log(f"viewer: render failed: {e}")

    def _render_loop(self) -> None:
        while not self._stop.is_set():
            job = self._next_job()
            if job is None:
                time.sleep(0.01)
                continue
            try:
                self._render_job(job)
            except Exception as e:  # a broken frame must not kill the server
                self._failed(job, e)

    def _on_signal(self, signum, frame, prev) -> None:
        """Live training: a SIGINT/SIGTERM while a frame renders stops the frame at its next
        block, and the training's own handler still gets it (it checkpoints and stops as
        without the viewer)."""
        if prev is signal.SIG_IGN:
            return
        self._signalled = True
        if callable(prev):
            prev(signum, frame)
        else:  # SIG_DFL (or a handler not set from Python): its usual effect
            signal.signal(signum, prev or signal.SIG_DFL)
            signal.raise_signal(signum)

    def tick(self, weights=contextlib.nullcontext) -> None:
        """Live training: renders at most one frame, in the caller's thread; frames are spaced
        so that rendering takes at most about a fifth of the time while someone watches.
        ``weights()``: a context manager open while a frame renders (the task's
        :meth:`~warpnerf.train.loop.Task.eval_weights`: ``--ema``'s averaged weights)."""
        if not self._clients or self._signalled:
            return
        now = time.perf_counter()
        if now - self._last_tick_frame < max(0.05, 4.0 * self._last_frame_seconds):
            return
        job = self._next_job()
        if job is None:
            return
        t0 = time.perf_counter()
        try:
            with signals_to(self._on_signal), weights():
                self._render_job(job)
        except Exception as e:  # a bad camera from a browser must not stop the training
            self._failed(job, e)
        self._last_frame_seconds = time.perf_counter() - t0
        self._last_tick_frame = time.perf_counter()

    def render_in_background(self) -> None:
        """A live viewer whose training has ended: from now on frames render in a background
        thread, as ``warpnerf view``'s do (nobody calls :meth:`tick` any more)."""
        if self._thread is None and not self._closed:
            self._signalled = False
            self._thread = threading.Thread(target=self._render_loop, daemon=True)
            self._thread.start()

    def serve_until_stopped(self, exit_after: float | None = None) -> str:
        """Serves (frames render in the background) until Ctrl-C or SIGTERM, or ``exit_after``
        seconds; then closes the viewer. Returns why it stopped: "signal" or "timeout"."""
        stop = threading.Event()
        self.render_in_background()
        why = "timeout"
        try:
            with signals_to(lambda *_: stop.set()):  # Ctrl-C, SIGTERM: stop in order
                t0 = time.perf_counter()
                while not stop.wait(0.1):
                    if exit_after is not None and time.perf_counter() - t0 >= exit_after:
                        break
                else:
                    why = "signal"
        finally:
            self.close()
        return why

    def rendering(self) -> bool:
        """Whether the render thread is still running (after :meth:`close`: a frame stuck in
        one long native call, e.g. a kernel compiling)."""
        return self._thread is not None and self._thread.is_alive()

    def close(self, timeout: float = 2.0) -> None:
        """Stops the render thread and the server within about ``timeout`` seconds (its port is
        free afterwards). A frame in flight stops at its next block (about ``BLOCK_SECONDS``);
        viser's stop runs in a daemon thread, waited for at most the time left (at least 0.5 s:
        closing the listening socket is the first thing it does)."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        t0 = time.perf_counter()
        if self._thread is not None:
            self._thread.join(timeout=timeout)
        stopper = threading.Thread(target=self.server.stop, daemon=True, name="viser-stop")
        with contextlib.redirect_stdout(io.StringIO()):  # (viser's "Server stopped" line)
            stopper.start()
            stopper.join(timeout=max(0.5, timeout - (time.perf_counter() - t0)))
