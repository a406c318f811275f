"""COLMAP sparse models (``cameras``, ``images``, ``points3D``; binary ``.bin`` or text ``.txt``).

Read as COLMAP writes them: ``images`` hold world-to-camera poses in the OpenCV camera convention
(x right, y down, z forward), ``X_cam = R(q) X_world + t`` with ``q = (qw, qx, qy, qz)``; the
loader (:mod:`warpnerf.data.capture`) converts them once to OpenGL camera-to-world.

Camera models read (COLMAP's ids and parameter orders):

==============  ==  ============================
SIMPLE_PINHOLE   0  f, cx, cy
PINHOLE          1  fx, fy, cx, cy
SIMPLE_RADIAL    2  f, cx, cy, k
RADIAL           3  f, cx, cy, k1, k2
OPENCV           4  fx, fy, cx, cy, k1, k2, p1, p2
==============  ==  ============================

Every camera becomes ``(fx, fy, cx, cy)`` plus OpenCV distortion ``(k1, k2, p1, p2)``. Other
models (fisheye ones, FULL_OPENCV, ...) raise a UserError naming the model.

The files are untrusted: a malformed line (wrong number of fields, non-numeric values), a count
in a binary file larger than the rest of the file can hold (checked before anything is
allocated), trailing bytes, duplicate camera / image / point ids, duplicate image names, image
names that leave the images folder (absolute, ``..``), an image whose camera is not defined,
camera sizes outside [1, 65536], non-finite camera parameters, poses or sparse points, and points
farther than ``MAX_WORLD`` from the origin are each a UserError naming the file (and line).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..outputs import atomic_path, read_input
from .cameras import MAX_IMAGE_SIDE

__all__ = ["Camera", "Image", "read_model", "find_model", "qvec_to_rotmat", "rotmat_to_qvec"]

# id -> (name, number of parameters)
MODELS = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
}
_OTHER_MODELS = {
    5: "OPENCV_FISHEYE",
    6: "FULL_OPENCV",
    7: "FOV",
    8: "SIMPLE_RADIAL_FISHEYE",
    9: "RADIAL_FISHEYE",
    10: "THIN_PRISM_FISHEYE",
}
_BY_NAME = {name: (i, n) for i, (name, n) in MODELS.items()}
MAX_WORLD = 1e9  # |camera centre| and |sparse point| in world units, before normalisation
MAX_MODEL_BYTES = 1 << 34  # one file of a COLMAP model (16 GiB: far beyond any reconstruction)


@dataclass
class Camera:
    id: int
    model: str
    width: int
    height: int
    params: np.ndarray  # as COLMAP stores them (see the module docstring)

    def pinhole(self) -> tuple[np.ndarray, np.ndarray]:
        """(fx, fy, cx, cy) [4] and OpenCV distortion (k1, k2, p1, p2) [4], float64."""
        p, m = self.params, self.model
        dist = np.zeros(4)
        if m in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            k = np.array([p[0], p[0], p[1], p[2]])
            dist[: len(p) - 3] = p[3:]
        else:  # PINHOLE, OPENCV
            k = p[:4].copy()
            dist[: len(p) - 4] = p[4:]
        return k, dist


@dataclass
class Image:
    id: int
    qvec: np.ndarray  # [4] (qw, qx, qy, qz), world-to-camera rotation
    tvec: np.ndarray  # [3]
    camera_id: int
    name: str
    point3d_ids: np.ndarray  # [n] int64, -1 where a 2D observation has no 3D point
    xys: np.ndarray | None = None  # [n, 2] float64 pixel positions of the 2D observations


def qvec_to_rotmat(q) -> np.ndarray:
    """[3, 3] rotation of the unit quaternion (qw, qx, qy, qz) (normalised first)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotmat_to_qvec(r) -> np.ndarray:
    """(qw, qx, qy, qz) with qw >= 0 of a [3, 3] rotation (for writing models in tests)."""
    r = np.asarray(r, dtype=np.float64)
    k = (
        np.array(
            [
                [r[0, 0] - r[1, 1] - r[2, 2], 0, 0, 0],
                [r[1, 0] + r[0, 1], r[1, 1] - r[0, 0] - r[2, 2], 0, 0],
                [r[2, 0] + r[0, 2], r[2, 1] + r[1, 2], r[2, 2] - r[0, 0] - r[1, 1], 0],
                [
                    r[2, 1] - r[1, 2],
                    r[0, 2] - r[2, 0],
                    r[1, 0] - r[0, 1],
                    r[0, 0] + r[1, 1] + r[2, 2],
                ],
            ]
        )
        / 3.0
    )
    vals, vecs = np.linalg.eigh(k)
    q = vecs[[3, 0, 1, 2], np.argmax(vals)]
    return -q if q[0] < 0 else q


def find_model(root: Path) -> Path | None:
    """The folder holding ``cameras.{bin,txt}`` and ``images.{bin,txt}``: ``root/sparse/0``,
    ``root/sparse`` or ``root`` itself (first found), else None."""
    for d in (root / "sparse" / "0", root / "sparse", root):
        for ext in (".bin", ".txt"):
            if (d / f"cameras{ext}").is_file() and (d / f"images{ext}").is_file():
                return d
    return None


class _Reader:
    """Little-endian binary reader that turns a short file into a UserError naming it."""

    def __init__(self, path: Path):
        self.path = path
        try:  # (a regular file only: a FIFO or device is refused, never waited on or read)
            self.data = read_input(path, "COLMAP model file", MAX_MODEL_BYTES, follow=True)
        except OSError as e:
            raise UserError(f"{path}: cannot read ({e.strerror or e})") from None
        self.pos = 0

    def read(self, fmt: str):
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise UserError(f"{self.path}: truncated at byte {self.pos} (not a COLMAP model?)")
        out = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return out

    def array(self, dtype, count: int) -> np.ndarray:
        size = np.dtype(dtype).itemsize * count
        if self.pos + size > len(self.data):
            raise UserError(f"{self.path}: truncated at byte {self.pos} (not a COLMAP model?)")
        out = np.frombuffer(self.data, dtype=dtype, count=count, offset=self.pos)
        self.pos += size
        return out

    def count(self, min_bytes: int, what: str) -> int:
        """A uint64 count of records of at least ``min_bytes`` bytes each, checked against the
        bytes left in the file before anything is allocated for them."""
        (n,) = self.read("Q")
        left = len(self.data) - self.pos
        if n * min_bytes > left:
            raise UserError(
                f"{self.path}: byte {self.pos - 8} says {n} {what}, more than the {left} bytes "
                "left can hold (truncated, or not a COLMAP model?)"
            )
        return n

    def string(self) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise UserError(f"{self.path}: truncated image name at byte {self.pos}")
        s = self.data[self.pos : end].decode("utf-8", errors="replace")
        self.pos = end + 1
        return s

    def done(self):
        if self.pos != len(self.data):
            raise UserError(f"{self.path}: {len(self.data) - self.pos} unexpected trailing bytes")


def _model(model_id_or_name, path, cam_id) -> tuple[str, int]:
    if isinstance(model_id_or_name, str):
        if model_id_or_name in _BY_NAME:
            return model_id_or_name, _BY_NAME[model_id_or_name][1]
        name = model_id_or_name
    else:
        if model_id_or_name in MODELS:
            return MODELS[model_id_or_name]
        name = _OTHER_MODELS.get(model_id_or_name, f"id {model_id_or_name}")
    raise UserError(
        f"{path}: camera {cam_id} uses model {name}; supported: {', '.join(_BY_NAME)} "
        "(undistort the images with `colmap image_undistorter` for other models)"
    )


def _camera(cam_id, model, w, h, params, path) -> Camera:
    params = np.asarray(params, dtype=np.float64)
    if not (1 <= w <= MAX_IMAGE_SIDE and 1 <= h <= MAX_IMAGE_SIDE):
        raise UserError(
            f"{path}: camera {cam_id}: size {w}x{h} must be in [1, {MAX_IMAGE_SIDE}] pixels a side"
        )
    if not np.isfinite(params).all():
        raise UserError(f"{path}: camera {cam_id}: non-finite parameters {params.tolist()}")
    cam = Camera(int(cam_id), model, int(w), int(h), params)
    k, _ = cam.pinhole()
    if k[0] <= 0 or k[1] <= 0:
        raise UserError(f"{path}: camera {cam_id}: focal length must be positive, got {k[:2]}")
    return cam


def _unique(table: dict, key, what: str, path, where="") -> None:
    if key in table:
        raise UserError(f"{path}{where}: {what} {key!r} appears twice")


def _read_cameras_bin(path: Path) -> dict[int, Camera]:
    r = _Reader(path)
    n = r.count(24 + 3 * 8, "cameras")
    cams = {}
    for _ in range(n):
        cam_id, model_id, w, h = r.read("iiQQ")
        model, n_params = _model(model_id, path, cam_id)
        _unique(cams, cam_id, "camera id", path)
        cams[cam_id] = _camera(cam_id, model, w, h, r.array("<f8", n_params), path)
    r.done()
    return cams


def _read_images_bin(path: Path) -> dict[int, Image]:
    r = _Reader(path)
    n = r.count(64 + 1 + 8, "images")
    images = {}
    for _ in range(n):
        image_id, *pose, cam_id = r.read("i7di")
        name = r.string()
        n_pts = r.count(24, "2D points")
        pts = r.array(np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")]), n_pts)
        _unique(images, image_id, "image id", path)
        images[image_id] = Image(
            image_id,
            np.array(pose[:4]),
            np.array(pose[4:]),
            cam_id,
            name,
            pts["id"].copy(),
            np.stack([pts["x"], pts["y"]], axis=-1),
        )
    r.done()
    return images


def _read_points_bin(path: Path) -> dict:
    r = _Reader(path)
    n = r.count(struct.calcsize("<Q3d3BdQ"), "3D points")
    xyz, ids, err = np.empty((n, 3)), np.empty(n, dtype=np.int64), np.empty(n)
    for i in range(n):
        pid, x, y, z, _, _, _, err[i], track = r.read("Q3d3BdQ")
        if pid >= 2**63:  # images refer to points by int64 ids
            raise UserError(f"{path}: 3D point id {pid} out of the 64-bit range")
        ids[i] = pid
        r.array("<i4", 2 * track)
        xyz[i] = (x, y, z)
    r.done()
    return {"ids": ids, "xyz": xyz, "error": err}


def _text_lines(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, fields) of the non-comment lines; blank lines kept for images.txt."""
    try:
        text = read_input(path, "COLMAP model file", MAX_MODEL_BYTES, follow=True).decode()
    except (OSError, UnicodeDecodeError) as e:
        raise UserError(f"{path}: cannot read ({e})") from None
    return [(i + 1, ln.split()) for i, ln in enumerate(text.splitlines()) if not ln.startswith("#")]


def _parse(path, lineno, fields, types):
    try:
        return [t(f) for t, f in zip(types, fields, strict=True)]
    except ValueError:
        names = " ".join(t.__name__ for t in types)
        raise UserError(f"{path}:{lineno}: expected {len(types)} values ({names})") from None


def _points2d(path, lineno, fields) -> tuple[np.ndarray, np.ndarray]:
    """(POINT3D_ID [n] int64 (-1: none), X Y [n, 2]) of the triples of a POINTS2D line."""
    try:
        xys = [float(v) for i, v in enumerate(fields) if i % 3 < 2]
        ids = [int(v) for v in fields[2::3]]
    except ValueError:
        raise UserError(
            f"{path}:{lineno}: POINTS2D must be triples X Y POINT3D_ID (numbers, integer ids)"
        ) from None
    if any(not -(2**63) <= v < 2**63 for v in ids):
        raise UserError(f"{path}:{lineno}: POINT3D_ID out of the 64-bit range")
    return np.array(ids, dtype=np.int64), np.array(xys, dtype=np.float64).reshape(-1, 2)


def _read_cameras_txt(path: Path) -> dict[int, Camera]:
    cams = {}
    for lineno, f in _text_lines(path):
        if not f:
            continue
        if len(f) < 4:
            raise UserError(f"{path}:{lineno}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        model, n_params = _model(f[1], path, f[0])
        if len(f) != 4 + n_params:
            raise UserError(f"{path}:{lineno}: model {model} needs {n_params} parameters")
        cam_id, w, h = _parse(path, lineno, [f[0], f[2], f[3]], [int, int, int])
        params = _parse(path, lineno, f[4:], [float] * n_params)
        _unique(cams, cam_id, "camera id", path, f":{lineno}")
        cams[cam_id] = _camera(cam_id, model, w, h, params, path)
    return cams


def _read_images_txt(path: Path) -> dict[int, Image]:
    lines = _text_lines(path)
    images, i = {}, 0
    while i < len(lines):
        lineno, f = lines[i]
        if not f:  # a blank line where an image line is expected
            i += 1
            continue
        if len(f) < 10:
            raise UserError(
                f"{path}:{lineno}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"
            )
        vals = _parse(path, lineno, f[:9], [int] + [float] * 7 + [int])
        name = " ".join(f[9:])
        pts = lines[i + 1][1] if i + 1 < len(lines) else []
        if len(pts) % 3:
            raise UserError(f"{path}:{lines[i + 1][0]}: POINTS2D must be triples X Y POINT3D_ID")
        ids, xys = _points2d(path, lines[i + 1][0] if i + 1 < len(lines) else lineno, pts)
        _unique(images, vals[0], "image id", path, f":{lineno}")
        images[vals[0]] = Image(
            vals[0], np.array(vals[1:5]), np.array(vals[5:8]), vals[8], name, ids, xys
        )
        i += 2
    return images


def _read_points_txt(path: Path) -> dict:
    xyz, ids, err = [], [], []
    for lineno, f in _text_lines(path):
        if f:
            if len(f) < 8:
                raise UserError(f"{path}:{lineno}: expected POINT3D_ID X Y Z R G B ERROR TRACK[]")
            ids.append(_parse(path, lineno, f[:1], [int])[0])
            xyz.append(_parse(path, lineno, f[1:4], [float] * 3))
            err.append(_parse(path, lineno, f[7:8], [float])[0])
            if not -(2**63) <= ids[-1] < 2**63:
                raise UserError(f"{path}:{lineno}: POINT3D_ID out of the 64-bit range")
    return {
        "ids": np.asarray(ids, dtype=np.int64),
        "xyz": np.asarray(xyz).reshape(-1, 3),
        "error": np.asarray(err, dtype=np.float64),
    }


def read_model(folder) -> tuple[dict[int, Camera], dict[int, Image], dict | None]:
    """(cameras by id, images by id, points3D {"ids": [n], "xyz": [n, 3], "error": [n] (mean
    reprojection error in pixels)} or None) of a sparse-model folder, binary preferred when
    both exist. Every image's camera must exist; qvec/tvec must be finite."""
    folder = Path(folder)
    ext = ".bin" if (folder / "cameras.bin").is_file() else ".txt"
    read = {
        ".bin": (_read_cameras_bin, _read_images_bin, _read_points_bin),
        ".txt": (_read_cameras_txt, _read_images_txt, _read_points_txt),
    }[ext]
    cams = read[0](folder / f"cameras{ext}")
    img_ext = ".bin" if (folder / "images.bin").is_file() else ".txt"
    images = (read[1] if img_ext == ext else _read_images_txt)(folder / f"images{img_ext}")
    pts = [folder / f"points3D{e}" for e in (ext, ".bin", ".txt")]
    pts_path = next((p for p in pts if p.is_file()), None)
    points = None
    if pts_path is not None:
        points = (_read_points_bin if pts_path.suffix == ".bin" else _read_points_txt)(pts_path)
    img_path = folder / f"images{img_ext}"
    _check_points(points, pts_path)
    names = set()
    for im in images.values():
        _check_name(im.name, img_path)
        if im.name in names:
            raise UserError(f"{img_path}: image name {im.name!r} appears twice")
        names.add(im.name)
        if im.camera_id not in cams:
            raise UserError(
                f"{folder / f'images{img_ext}'}: image {im.name!r} refers to camera "
                f"{im.camera_id}, which cameras{ext} does not define"
            )
        if not (np.isfinite(im.qvec).all() and np.isfinite(im.tvec).all()) or not np.linalg.norm(
            im.qvec
        ):
            raise UserError(
                f"{folder / f'images{img_ext}'}: image {im.name!r}: non-finite or zero pose"
            )
    return cams, images, points


def _check_name(name: str, path) -> None:
    """An image name must be a relative path inside the images folder."""
    from ._paths import is_inside_name

    if not is_inside_name(name):
        raise UserError(
            f"{path}: image name {name!r} must be a relative path inside the images folder"
        )


def _check_points(points, path) -> None:
    """Sparse points finite, within MAX_WORLD of the origin, with distinct ids."""
    if points is None or not len(points["ids"]):
        return
    xyz = points["xyz"]
    bad = ~(np.abs(xyz) <= MAX_WORLD).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise UserError(
            f"{path}: 3D point {int(points['ids'][i])} at {xyz[i].tolist()} is not finite or "
            f"farther than {MAX_WORLD:g} from the origin"
        )
    uniq, counts = np.unique(points["ids"], return_counts=True)
    if (counts > 1).any():
        raise UserError(f"{path}: 3D point id {int(uniq[np.argmax(counts > 1)])} appears twice")


def _write(path: Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(data)


def _xys(im: Image) -> list:
    """An image's observation positions to write ((0, 0) each when it has none)."""
    if im.xys is None:
        return [(0.0, 0.0)] * len(im.point3d_ids)
    xys = np.asarray(im.xys, dtype=np.float64).reshape(-1, 2)
    if len(xys) != len(im.point3d_ids):
        raise ValueError(f"image {im.name!r}: {len(xys)} xys for {len(im.point3d_ids)} point ids")
    return xys.tolist()


def write_model(folder, cams: dict[int, Camera], images: dict[int, Image], points=None, text=False):
    """Writes a sparse model (binary or text) as COLMAP does; used by tests and tools."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    points = np.zeros((0, 3)) if points is None else np.asarray(points, dtype=np.float64)
    # points3D ids are 1-based, in order
    if text:
        lines = [f"{c.id} {c.model} {c.width} {c.height} " + " ".join(map(repr, c.params.tolist()))
                 for c in cams.values()]  # fmt: skip
        _write(folder / "cameras.txt", ("# Camera list\n" + "\n".join(lines) + "\n").encode())
        lines = []
        for im in images.values():
            pose = " ".join(map(repr, [*im.qvec.tolist(), *im.tvec.tolist()]))
            lines.append(f"{im.id} {pose} {im.camera_id} {im.name}")
            xys = _xys(im)
            lines.append(
                " ".join(f"{x!r} {y!r} {int(p)}" for (x, y), p in zip(xys, im.point3d_ids))
            )
        _write(folder / "images.txt", ("# Image list\n" + "\n".join(lines) + "\n").encode())
        pts = enumerate(points.tolist())
        lines = [f"{i + 1} {x!r} {y!r} {z!r} 128 128 128 0.5" for i, (x, y, z) in pts]
        _write(folder / "points3D.txt", ("\n".join(lines) + ("\n" if lines else "")).encode())
        return
    out = [struct.pack("<Q", len(cams))]
    for c in cams.values():
        out.append(struct.pack("<iiQQ", c.id, _BY_NAME[c.model][0], c.width, c.height))
        out.append(np.asarray(c.params, "<f8").tobytes())
    _write(folder / "cameras.bin", b"".join(out))
    out = [struct.pack("<Q", len(images))]
    for im in images.values():
        out.append(struct.pack("<i7di", im.id, *im.qvec, *im.tvec, im.camera_id))
        out.append(im.name.encode() + b"\0" + struct.pack("<Q", len(im.point3d_ids)))
        for (x, y), p in zip(_xys(im), im.point3d_ids):
            out.append(struct.pack("<ddq", x, y, int(p)))
    _write(folder / "images.bin", b"".join(out))
    out = [struct.pack("<Q", len(points))]
    for i, p in enumerate(points):
        out.append(struct.pack("<Q3d3BdQ", i + 1, *p, 128, 128, 128, 0.5, 0))
    _write(folder / "points3D.bin", b"".join(out))
