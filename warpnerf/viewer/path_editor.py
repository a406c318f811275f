"""The viewer's camera-path editor (:class:`PathEditor`, a part of :class:`~.server.Viewer`):
keyframes added from a browser's view, drawn as frustums and a line, flown by "Preview" and
saved as a JSON file in the run folder that ``warpnerf render RUN --path FILE`` renders
(:mod:`warpnerf.data.camera_path`); and the conversions between viser's camera (OpenCV axes,
a quaternion and a position) and the OpenGL c2w the project uses."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np

from ..data.camera_path import (
    MAX_FRAMES,
    MAX_KEYFRAMES,
    CameraPath,
    matrix_to_quat,
    quat_to_matrix,
)
from ..errors import UserError
from .access import bounded

__all__ = ["PathEditor", "opencv_to_gl", "gl_to_opencv"]

_FLIP = np.diag([1.0, -1.0, -1.0])  # OpenCV camera axes <-> OpenGL camera axes


def opencv_to_gl(wxyz, position) -> np.ndarray:
    """OpenGL camera-to-world [4, 4] of a viser camera (rotation ``wxyz`` of OpenCV camera axes:
    x right, y down, looking down +z; ``position`` in world)."""
    m = np.eye(4)
    m[:3, :3] = quat_to_matrix(np.asarray(wxyz, dtype=np.float64)) @ _FLIP
    m[:3, 3] = np.asarray(position, dtype=np.float64)
    return m


def gl_to_opencv(c2w) -> tuple:
    """(wxyz, position) of viser's OpenCV-axes camera for an OpenGL camera-to-world [4, 4]."""
    c2w = np.asarray(c2w, dtype=np.float64)
    return matrix_to_quat(c2w[:3, :3] @ _FLIP), c2w[:3, 3].copy()


class PathEditor:
    """The camera-path panel's actions. The :class:`~.server.Viewer` it is part of provides
    ``server``, ``scene``, ``run``, the panel's widgets (``path_info``, ``path_frames``,
    ``path_loop``, ``path_file``), ``_path``, ``_path_handles``, ``_clients``, ``_previews``,
    ``_lock``, ``_stop``, ``_say`` and ``_guarded``."""

    def _add_keyframe(self, client) -> None:
        st = self._clients.get(client.client_id)
        if st is None or st.pose is None:
            return
        if len(self._path) >= MAX_KEYFRAMES:
            self._say(f"not added: a path has at most {MAX_KEYFRAMES} keyframes", self.path_info)
            return
        self._set_path(self._path + [st.pose])

    def _set_path(self, keys: list) -> None:
        self._path = keys
        s = self.server.scene
        for h in self._path_handles:
            h.remove()
        self._path_handles = []
        for i, (c2w, fov, aspect, _) in enumerate(keys):
            wxyz, pos = gl_to_opencv(c2w)
            self._path_handles.append(s.add_camera_frustum(
                f"/path/key_{i}", fov=fov, aspect=aspect, scale=0.08, wxyz=wxyz, position=pos,
                color=(220, 40, 40),
            ))  # fmt: skip
        if len(keys) >= 2:
            cams = self.path(min(400, 20 * len(keys))).cameras().numpy()
            pts = cams[:, :3, 3]
            self._path_handles.append(s.add_line_segments(
                "/path/line", np.stack([pts[:-1], pts[1:]], 1), (220, 40, 40), thickness=2.0,
                thickness_units="screen",
            ))  # fmt: skip
        self.path_info.content = f"keyframes: {len(keys)}"

    def path_frame_count(self) -> int:
        """The panel's "Frames", checked (a browser may send any number): ValueError unless an
        integer in 1..:data:`~warpnerf.data.camera_path.MAX_FRAMES`."""
        return bounded(self.path_frames.value, 1, MAX_FRAMES, "Frames")

    def path(self, frames: int | None = None) -> CameraPath:
        """The camera path being edited (the first keyframe's field of view and aspect, and each
        keyframe's near/far as the viewer renders it, so `render --path` sees what it showed);
        ``frames`` default: the panel's (:meth:`path_frame_count`)."""
        keys = self._path
        fov, aspect = (keys[0][1], keys[0][2]) if keys else (0.8, 1.0)
        rule = self.scene.window
        windows = [rule(k[0][:3, 3]) for k in keys] if rule is not None and keys else None
        frames = self.path_frame_count() if frames is None else frames
        return CameraPath([k[0] for k in keys], fov, aspect, frames,
                          self.path_loop.value is True, windows)  # fmt: skip

    def path_target(self) -> Path:
        """Where "Save path" writes: the file name typed in the panel, inside the run folder (or
        the working folder without one). The browser chooses the name only: no folders, so a
        client can never write elsewhere on the machine."""
        name = str(self.path_file.value)[:1000].strip()
        if (not name or "/" in name or "\\" in name or name in (".", "..") or "\0" in name
                or not name.endswith(".json") or len(name) > 200):  # fmt: skip
            raise UserError(f"{name[:60]!r}: give a plain file name ending in .json (it is saved "
                            "in the run folder)")  # fmt: skip
        return (self.run if self.run is not None else Path(".")) / name

    def _start_preview(self, client) -> None:
        """The "Preview" button: flies this browser's camera along the path in a thread; a
        newer click (or the browser leaving) ends the one before: one flight per browser."""
        cid = client.client_id
        with self._lock:
            n = self._previews.get(cid, 0) + 1
            self._previews[cid] = n
        threading.Thread(target=self._guarded("preview", self._preview), args=(client, 20.0, n),
                         daemon=True).start()  # fmt: skip

    def _preview(self, client, fps: float = 20.0, number: int | None = None) -> None:
        """Flies the browser's camera along the path (frames at ``fps``; the viewer renders what
        it can keep up with), each camera computed when it is shown (a path of 100000 frames
        costs no memory); stops early when ``number`` is no longer the browser's latest
        preview, the browser leaves or the viewer closes."""
        if not self._path:
            return
        path = self.path()
        cid = client.client_id
        for c2w in path.iter_cameras():
            if self._stop.is_set() or (number is not None and self._previews.get(cid) != number):
                return
            st = self._clients.get(cid)
            if st is not None and st.gone:
                return
            wxyz, pos = gl_to_opencv(c2w)
            with client.atomic():
                client.camera.wxyz, client.camera.position = wxyz, pos
            time.sleep(1.0 / fps)

    def _save_path(self, client) -> None:
        try:
            target = self.path_target()
            self.path().save(target)
            msg = f"saved {len(self._path)} keyframes to {target}"
        except (UserError, OSError, ValueError) as e:
            msg = f"not saved: {e}"
        self._say(msg, self.path_info)
