"""Camera paths of ``warpnerf render``: the built-in ones around the training cameras
(:func:`camera_path`, ``--path spiral|orbit``) and camera-path files, keyframes a user places in
the viewer (``warpnerf view``), rendered to video by ``warpnerf render RUN --path FILE``.

The file is JSON::

    {"warpnerf_camera_path": 1,
     "fov_y": 0.8,                 # vertical field of view, radians, in (0, pi)
     "aspect": 1.5,                # width / height of the viewer's canvas
     "frames": 120,                # frames of the rendered video
     "loop": false,                # true: the path returns to its first keyframe
     "keyframes": [{"c2w": [[...], [...], [...], [0, 0, 0, 1]],
                    "near": 3.0, "far": 6.0}, ...]}   # optional, on every keyframe or none

``c2w`` is an OpenGL camera-to-world matrix (x right, y up, looking down -z) in the run's world
frame. Between keyframes the position follows a Catmull-Rom spline through the keyframes'
positions and the rotation a spherical linear interpolation (slerp) of their quaternions, each
segment taking the same number of frames. ``near``/``far`` are the depth range the viewer
rendered the keyframe with (:func:`window_rule`: the run's near..far moved with the camera's
distance to the scene); between keyframes they are interpolated linearly. A file without them
(written before they were saved) gets them from the same rule when rendered. A path file is
input like any other: every count and number is bounded and checked, and a bad file is a
:class:`~warpnerf.errors.UserError` naming the file and field.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from ..errors import UserError
from ..json_input import read_json
from .cameras import MAX_DEPTH, camera_target, check_poses, look_at

__all__ = [
    "camera_path",
    "PATHS",
    "CameraPath",
    "load_camera_path",
    "interpolate_path",
    "PATH_FORMAT",
    "matrix_to_quat",
    "quat_to_matrix",
    "window_rule",
]

PATH_FORMAT = 1
MAX_KEYFRAMES = 1000
MAX_FRAMES = 100000
# MAX_DEPTH (data/cameras.py): bound on a keyframe's near/far, as on a run's


class CameraPath:
    """Keyframes [k, 4, 4] (float64 OpenGL c2w) with the field of view, aspect, frame count and,
    optionally, each keyframe's depth range ``windows`` [k, 2] (near, far)."""

    def __init__(self, keyframes, fov_y: float = 0.8, aspect: float = 1.0, frames: int = 120,
                 loop: bool = False, windows=None):  # fmt: skip
        self.keyframes = np.asarray(keyframes, dtype=np.float64).reshape(-1, 4, 4)
        self.fov_y, self.aspect = float(fov_y), float(aspect)
        self.frames, self.loop = int(frames), bool(loop)
        self.windows = None
        if windows is not None:
            self.windows = np.asarray(windows, dtype=np.float64).reshape(-1, 2)
            if len(self.windows) != len(self.keyframes):
                raise ValueError("windows needs one (near, far) per keyframe")

    def to_dict(self) -> dict:
        keys = [{"c2w": k.tolist()} for k in self.keyframes]
        if self.windows is not None:
            for key, (near, far) in zip(keys, self.windows.tolist()):
                key.update(near=near, far=far)
        return {
            "warpnerf_camera_path": PATH_FORMAT, "fov_y": self.fov_y, "aspect": self.aspect,
            "frames": self.frames, "loop": self.loop, "keyframes": keys,
        }  # fmt: skip

    def save(self, path) -> None:
        """Writes the path atomically, checked as :func:`load_camera_path` checks a file (a
        keyframe with a NaN, a frame count out of range: :class:`UserError`, nothing written).
        An existing file is replaced only when it is a camera path warpnerf wrote (never a run's
        config, history or another file); a link, FIFO or device at ``path`` is refused without
        being opened (:func:`~warpnerf.safe_writes.check_foreign`), so it cannot hang the save."""
        from ..json_input import JSON_LIMITS
        from ..outputs import write_json
        from ..safe_writes import check_foreign, read_regular

        p = Path(path)
        if len(self.keyframes) == 0:
            raise UserError(f"{p}: a camera path needs at least one keyframe")
        d = self.to_dict()
        _from_dict(p, d)  # (what the file would say, checked before writing)
        check_foreign([p])
        data = read_regular(p, JSON_LIMITS["camera path"], "camera path")
        if data is not None:
            try:
                _from_dict(p, json.loads(data.decode("utf-8")))
            except (UserError, ValueError, RecursionError):  # (UnicodeDecodeError, JSON)
                raise UserError(f"{p}: exists and is not a camera path; refusing to replace "
                                "it (choose another name)") from None  # fmt: skip
        write_json(p, d)

    def cameras(self, frames: int | None = None) -> torch.Tensor:
        """[frames, 4, 4] float32 cameras along the path (:func:`interpolate_path`)."""
        return interpolate_path(self.keyframes, frames or self.frames, self.loop)

    def iter_cameras(self, frames: int | None = None):
        """The cameras [4, 4] (float64) along the path one at a time, each computed when asked
        for (a long path costs no memory); the same cameras as :meth:`cameras`."""
        return _path_frames(self.keyframes, frames or self.frames, self.loop)

    def frame_windows(self, frames: int | None = None) -> np.ndarray | None:
        """[frames, 2] (near, far) of the frames along the path: the keyframes' depth ranges
        interpolated linearly (same frames per segment as :meth:`cameras`); None when the file
        has none (use :func:`window_rule`)."""
        if self.windows is None:
            return None
        w, n, out = self.windows, len(self.windows), []
        for f in range(frames or self.frames):
            i, t = _segment(f, frames or self.frames, n, self.loop)
            out.append(w[i] if n == 1 else (1 - t) * w[i] + t * w[(i + 1) % n])
        return np.stack(out)

    def intrinsics(self, width: int, height: int) -> torch.Tensor:
        """[4] fx, fy, cx, cy of the path's vertical field of view at ``width`` x ``height``."""
        f = 0.5 * height / math.tan(0.5 * self.fov_y)
        return torch.tensor([f, f, 0.5 * width, 0.5 * height])


def load_camera_path(path) -> CameraPath:
    """Reads and checks a camera-path file (the format in the module's docstring)."""
    p = Path(path)
    return _from_dict(p, read_json(p, "camera path"))


def _from_dict(p: Path, d) -> CameraPath:
    """The :class:`CameraPath` of a parsed file ``d`` (from ``p``), checked; UserError naming
    ``p`` and the field otherwise."""
    if not isinstance(d, dict) or d.get("warpnerf_camera_path") != PATH_FORMAT:
        raise UserError(f"{p}: not a warpnerf camera path (expected a JSON object with "
                        f'"warpnerf_camera_path": {PATH_FORMAT})')  # fmt: skip

    def number(key, lo, hi, default, kind=float):
        v = d.get(key, default)
        try:
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        except OverflowError:  # an integer too large for a float
            ok = False
        if not ok or not lo <= v <= hi or (kind is int and v != int(v)):
            what = "an integer" if kind is int else "a number"
            raise UserError(f"{p}: field '{key}' must be {what} in [{lo}, {hi}], got {v!r}")
        return kind(v)

    fov = number("fov_y", 1e-3, math.pi - 1e-3, 0.8)
    aspect = number("aspect", 1e-2, 1e2, 1.0)
    frames = number("frames", 1, MAX_FRAMES, 120, int)
    loop = d.get("loop", False)
    if not isinstance(loop, bool):
        raise UserError(f"{p}: field 'loop' must be true or false, got {loop!r}")
    keys = d.get("keyframes")
    if not isinstance(keys, list) or not 1 <= len(keys) <= MAX_KEYFRAMES:
        raise UserError(f"{p}: field 'keyframes' must be a list of 1 to {MAX_KEYFRAMES} "
                        "keyframes")  # fmt: skip
    mats = []
    for i, k in enumerate(keys):
        m = k.get("c2w") if isinstance(k, dict) else None
        try:
            a = np.asarray(m, dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            a = None
        if a is None or a.shape != (4, 4) or not np.isfinite(a).all():
            raise UserError(f"{p}: keyframes[{i}].c2w must be a 4x4 matrix of finite numbers")
        mats.append(a)
    c2w = np.stack(mats)
    labels = [f"keyframes[{i}]" for i in range(len(mats))]
    c2w = check_poses(c2w, str(p), labels)  # rotations, bottom row, centres
    windows = _read_windows(p, keys)
    return CameraPath(np.asarray(c2w, dtype=np.float64), fov, aspect, frames, loop, windows)


def _read_windows(p: Path, keys: list) -> np.ndarray | None:
    """[k, 2] (near, far) of the keyframes, None when no keyframe has them; UserError unless
    every keyframe has both, finite, with 0 <= near < far <= :data:`MAX_DEPTH`."""
    has = [("near" in k) or ("far" in k) for k in keys]
    if not any(has):
        return None
    out = []
    for i, k in enumerate(keys):
        vals = [k.get("near"), k.get("far")]
        ok = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals)
        try:
            ok = ok and all(math.isfinite(v) for v in vals)
        except OverflowError:  # an integer too large for a float
            ok = False
        if not ok or not 0 <= vals[0] < vals[1] <= MAX_DEPTH:
            raise UserError(f"{p}: keyframes[{i}] needs 'near' and 'far' numbers with "
                            f"0 <= near < far <= {MAX_DEPTH:g} (on every keyframe or none), "
                            f"got near={vals[0]!r}, far={vals[1]!r}")  # fmt: skip
        out.append([float(vals[0]), float(vals[1])])
    return np.array(out)


def window_rule(c2w, near: float, far: float):
    """``position [3] -> (near, far)``: the depth range the viewer renders a camera at
    ``position`` with. The run's near..far window is kept at the same distance from the scene
    centre (the training cameras ``c2w`` [n, 4, 4]'s common target), so that a camera further
    out (or closer) than the training cameras sees the scene instead of a clipped part of it:
    with ``s`` = the camera's distance to the centre minus the training cameras' mean distance,
    the range is ``(max(0, near + s), far + s)``; unchanged while ``|s|`` is within 5 % of
    ``far - near``. Without cameras (``None`` or one) the centre is the origin at distance
    ``(near + far) / 2``."""
    if c2w is not None and len(c2w) > 1:
        from .cameras import camera_target

        c2w = torch.as_tensor(c2w).detach().cpu().double()
        centre = camera_target(c2w)
        dist0 = float((c2w[:, :3, 3] - centre).norm(dim=-1).mean())
    else:
        centre, dist0 = torch.zeros(3, dtype=torch.float64), 0.5 * (near + far)

    def window(position) -> tuple:
        pos = torch.as_tensor(np.asarray(position, dtype=np.float64).reshape(3))
        shift = float((pos - centre).norm()) - dist0
        if abs(shift) <= 0.05 * (far - near):
            return float(near), float(far)
        return max(0.0, near + shift), far + shift

    return window


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix [3, 3] (Shepperd's method: branch on
    the largest of 4w^2, 4x^2, 4y^2, 4z^2, exact for half turns too)."""
    t = np.trace(r)
    d = [t, r[0, 0], r[1, 1], r[2, 2]]
    k = int(np.argmax(d))
    if k == 0:
        s = 2.0 * math.sqrt(max(1.0 + t, 1e-300))
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif k == 1:
        s = 2.0 * math.sqrt(max(1.0 + r[0, 0] - r[1, 1] - r[2, 2], 1e-300))
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(max(1.0 + r[1, 1] - r[0, 0] - r[2, 2], 1e-300))
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(max(1.0 + r[2, 2] - r[0, 0] - r[1, 1], 1e-300))
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    return q / np.linalg.norm(q)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix [3, 3] of a quaternion (w, x, y, z), normalised first."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


def _slerp(a: np.ndarray, b: np.ndarray, t: float) -> np.ndarray:
    dot = float(a @ b)
    if dot < 0:  # the shorter way round
        b, dot = -b, -dot
    if dot > 0.9995:
        q = a + t * (b - a)
        return q / np.linalg.norm(q)
    th = math.acos(min(dot, 1.0))
    return (math.sin((1 - t) * th) * a + math.sin(t * th) * b) / math.sin(th)


def _segment(f: int, frames: int, n: int, loop: bool) -> tuple:
    """(segment i, fraction t) of frame ``f`` of ``frames`` along ``n`` keyframes: equal frames
    per segment; frame 0 is keyframe 0 and, without ``loop``, the last frame the last keyframe."""
    segments = n if loop else n - 1
    if segments <= 0:
        return 0, 0.0
    s = f / frames * segments if loop else f / max(frames - 1, 1) * segments
    i = min(int(s), segments - 1)
    return i, s - i


def interpolate_path(keyframes, frames: int, loop: bool = False) -> torch.Tensor:
    """[frames, 4, 4] float32 cameras through ``keyframes`` [k, 4, 4] (OpenGL c2w): Catmull-Rom
    positions, slerped rotations, equal frames per segment; frame 0 is the first keyframe and,
    without ``loop``, the last frame is the last keyframe."""
    out = list(_path_frames(keyframes, frames, loop))
    return torch.as_tensor(np.stack(out), dtype=torch.float32)


def _path_frames(keyframes, frames: int, loop: bool = False):
    """The cameras of :func:`interpolate_path` one at a time ([4, 4] float64)."""
    k = np.asarray(keyframes, dtype=np.float64).reshape(-1, 4, 4)
    if len(k) == 0 or frames < 1:
        raise ValueError("need at least one keyframe and one frame")
    pos, quats = k[:, :3, 3], [matrix_to_quat(m[:3, :3]) for m in k]
    n = len(k)
    segments = n if loop else n - 1
    for f in range(frames):
        if segments == 0:
            yield k[0].copy()
            continue
        i, t = _segment(f, frames, n, loop)

        def p(j):
            return pos[j % n] if loop else pos[min(max(j, 0), n - 1)]

        p0, p1, p2, p3 = p(i - 1), p(i), p(i + 1), p(i + 2)
        c = 0.5 * ((2 * p1) + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t * t
                   + (-p0 + 3 * p1 - 3 * p2 + p3) * t ** 3)  # fmt: skip
        m = np.eye(4)
        m[:3, :3] = quat_to_matrix(_slerp(quats[i], quats[(i + 1) % n], t))
        m[:3, 3] = c
        yield m


def camera_path(c2w: torch.Tensor, kind: str, frames: int) -> torch.Tensor:
    """[frames, 4, 4] cameras around the training cameras' target: centre = the point nearest to
    all optical axes, radius = their mean distance to it, up = their mean up vector; "orbit" keeps
    their mean elevation, "spiral" swings it by +-15 degrees."""
    if kind not in PATHS:
        raise UserError(f"--path must be spiral or orbit, got {kind!r}")
    c2w = c2w.double().cpu()
    o, centre = c2w[:, :3, 3], camera_target(c2w)
    up = torch.nn.functional.normalize(c2w[:, :3, 1].mean(0), dim=0)
    rel = o - centre
    radius = float(rel.norm(dim=-1).mean())
    elev = float(torch.asin((torch.nn.functional.normalize(rel, dim=-1) @ up).clamp(-1, 1)).mean())
    a = torch.nn.functional.normalize(
        torch.linalg.cross(up, torch.tensor([0.3, 0.2, 0.9], dtype=torch.float64)), dim=0
    )
    b = torch.linalg.cross(up, a)
    mats = []
    for f in range(frames):
        s = f / frames
        el = elev + (math.radians(15) * math.sin(2 * math.pi * s) if kind == "spiral" else 0.0)
        az = 2 * math.pi * s
        direction = math.cos(el) * (math.cos(az) * a + math.sin(az) * b) + math.sin(el) * up
        mats.append(look_at(centre + radius * direction, centre, up, dtype=torch.float64))
    return torch.stack(mats).float()


PATHS = ("spiral", "orbit")  # the built-in camera paths of `render --path`
