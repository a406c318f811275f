"""Real captures: COLMAP sparse models and LLFF ``poses_bounds.npy`` folders.

Both become the same thing: images sorted by file name, OpenGL camera-to-world poses, pinhole
intrinsics plus OpenCV distortion ``(k1, k2, p1, p2)`` (undistorted per pixel ray by
:func:`warpnerf.data.cameras.camera_rays`; the images are never resampled), per-image depth bounds,
and a **scene normalisation** ``transform`` [4, 4] with ``x_norm = transform @ x_world``:

- forward-facing captures (every camera's viewing axis within 45 degrees of their mean), as the
  NeRF paper: recentre on the mean camera pose (it becomes the identity: looking down -z, +y up)
  and scale by ``1 / (0.75 * min near)``; rendering then uses NDC rays (near plane 1).
- other captures (objects, 360-degree): centre = the point closest to all viewing axes (least
  squares), +z = the cameras' mean up vector, scale = 4 / the cameras' median distance to the
  centre (so cameras sit near radius 4, as in the Blender scenes).

Only camera poses decide the transform, so a COLMAP model and the LLFF file made from it normalise
the same way. The transform is a similarity (rotation, uniform scale, translation) and is stored
in the run's config; meshes are mapped back to world units with its inverse.

Cameras are checked at load (:mod:`warpnerf.data.cameras`): poses finite, camera centres within
``MAX_WORLD`` = 1e9 world units of the origin (the normalisation runs in float64), rotations
orthonormal with determinant +1 (used as they are within 1e-4, replaced by the nearest rotation
with a UserWarning within 0.05, refused beyond: degenerate, scaled or mirrored); intrinsics of
the images read finite, focal lengths in (0, 1e8] pixels, field of view below about 179.8
degrees, images at most 65536 pixels a side; LLFF depth bounds 0 < near < far. After the
normalisation the scene must be sane: camera centres within 1e6, 0 < near < far <= 1e6, else the
capture is refused as degenerate (cameras at one point, absurd bounds).

Hold-out: the one rule of :func:`~warpnerf.data.dataset.holdout_indices` (the LLFF convention):
images ``i % holdout == 0`` in sorted-name order are val/test, the others train; ``holdout = 0``
trains on all and validates on all.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..errors import UserError
from ..safe_writes import open_input
from ._paths import OPT_IN, outside_reason
from .arrays import load_npy
from .blender import area_downscale, composite_rgba, data_root
from .capture_frame import (
    CAMERA_RADIUS,
    NDC_NEAR,
    apply_transform,
    check_capture_cameras,
    check_capture_scene,
    check_undistortion,
    normalised_to_world,
    scene_normalisation,
)
from .colmap import find_model, qvec_to_rotmat, read_model
from .dataset import HOLDOUT, REGISTRY, Dataset, LoadRequest, holdout_indices, register_format
from .images import read_all, read_image

__all__ = [
    "detect_capture",
    "capture_info",
    "load_capture",
    "reprojection_errors",
    "NDC_NEAR",
    "apply_transform",
    "normalised_to_world",
]

MAX_KEYPOINTS = 1_000_000  # sparse-point observations kept per split (a random subset beyond)
_EXTS = (".png", ".jpg", ".jpeg")
_OPENCV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def detect_capture(root: Path) -> str | None:
    """ "colmap" (a sparse model under sparse/0, sparse or the folder), "llff"
    (poses_bounds.npy) or None."""
    for name in ("colmap", "llff"):
        if REGISTRY[name].detect(root, "train"):
            return name
    return None


def _image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in _EXTS and p.is_file())


def _image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file, read from its header where possible."""
    try:
        from PIL import Image

        with open_input(path, "image", follow=True) as fh, Image.open(fh) as im:
            return im.size
    except ImportError:  # pragma: no cover - imageio brings pillow
        pass
    except UserError:  # (a FIFO or device: refused, never waited on or read)
        raise
    except Exception as e:
        raise UserError(f"{path}: cannot read image ({e})") from None
    return _read(path).shape[1::-1]


def _confine(root: Path, folder: Path, names, allow_outside: bool, where) -> None:
    """UserError naming the image unless every file ``folder / name`` stays inside the dataset
    folder ``root`` once links are resolved (the folder itself may be the link), the rule of the
    Blender loader (:func:`~._paths.outside_reason`); ``allow_outside``
    (``--allow-outside-paths``) lets them lead anywhere. Checked before any image is read."""
    if allow_outside:
        return
    for name in names:
        file = folder / name
        why = outside_reason(root, file.relative_to(root).as_posix(), file)
        if why is not None:
            raise UserError(f"{where}: image {file} {why}, outside the dataset folder {root} "
                            f"(pass {OPT_IN} to use images outside it)")  # fmt: skip


def _read(path: Path) -> np.ndarray:
    """float32 [H, W, 3|4] in [0, 1], bounded decoding (:func:`._images.read_image`)."""
    return read_image(path)


# --------------------------------------------------------------------------------------------
# Poses of each format, in world units: names, c2w [N, 4, 4] OpenGL, intrinsics [N, 4] of the
# chosen image folder, distortion [N, 4], bounds [N, 2] (or None), points [M, 3] (or None).


def _colmap(root: Path, downscale: int, allow_outside: bool = False) -> dict:
    model = find_model(root)
    cams, images, points = read_model(model)
    if not images:
        raise UserError(f"{model}: the model has no registered images")
    folder = root / "images"
    if downscale > 1 and (root / f"images_{downscale}").is_dir():
        folder = root / f"images_{downscale}"
    if not folder.is_dir():
        raise UserError(f"{root}: no images/ folder next to the COLMAP model {model}")
    ims = sorted(images.values(), key=lambda im: im.name)
    missing = [im.name for im in ims if not (folder / im.name).is_file()]
    if missing:
        raise UserError(
            f"{folder}: {len(missing)} image(s) of the model are missing, e.g. {missing[:3]}"
        )
    _confine(root, folder, [im.name for im in ims], allow_outside, model)
    registered = {im.name for im in ims}
    unregistered = [p.name for p in _image_files(folder) if p.name not in registered]
    c2w, k, dist, bounds, observations = [], [], [], [], []
    index = _point_index(points)
    for im in ims:
        cam = cams[im.camera_id]
        m = _c2w_opencv(im)
        c2w.append(m @ _OPENCV_TO_GL)
        ki, di = cam.pinhole()
        k.append(ki)
        dist.append(di)
        pos, rows = _point_rows(index, im.point3d_ids)
        xys = im.xys[pos] if im.xys is not None else np.zeros((0, 2))
        observations.append((xys, rows[: len(xys)]))  # pixels of the COLMAP camera, point rows
        if len(rows):
            z = (points["xyz"][rows] - m[:3, 3]) @ m[:3, 2]  # depth along the viewing axis (+z)
            z = z[z > 0]
            bounds.append(np.percentile(z, [0.1, 99.9]) if len(z) else [np.nan, np.nan])
        else:
            bounds.append([np.nan, np.nan])
    size = {(cams[im.camera_id].width, cams[im.camera_id].height) for im in ims}
    if len(size) > 1:
        raise UserError(f"{model}: cameras of different sizes {sorted(size)}; one size needed")
    (w_cam, h_cam) = size.pop()
    first = folder / ims[0].name
    w_img, h_img = _image_size(first)
    k = np.asarray(k)
    if (w_img, h_img) != (w_cam, h_cam):
        sx, sy = w_img / w_cam, h_img / h_cam
        if folder.name == "images" or abs(sx - sy) > 1e-3:
            raise UserError(
                f"{first}: image is {w_img}x{h_img} but its COLMAP camera is {w_cam}x{h_cam}"
            )
        k = k * np.array([sx, sy, sx, sy])  # images_N: a downscaled copy
        observations = [(xy * np.array([sx, sy]), rows) for xy, rows in observations]
    bounds = np.asarray(bounds, dtype=np.float64)
    return {
        "names": [im.name for im in ims],
        "folder": folder,
        "c2w": np.asarray(c2w),
        "intrinsics": k,
        "distortion": np.asarray(dist),
        "bounds": None if np.isnan(bounds).all() else bounds,
        "points": points["xyz"] if points is not None and len(points["xyz"]) else None,
        "observations": observations,  # per image: (pixel positions [m, 2], point rows [m])
        "size": (w_img, h_img),
        "unregistered": unregistered,
        "model": str(model),
        "camera_models": sorted({cams[im.camera_id].model for im in ims}),
    }


def _llff(root: Path, downscale: int, allow_outside: bool = False) -> dict:
    path = root / "poses_bounds.npy"
    arr = load_npy(path, "LLFF poses_bounds")  # (its header's shape checked before reading)
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] < 1:
        raise UserError(f"{path}: expected an [N, 17] array (LLFF poses_bounds), got {arr.shape}")
    if not np.isfinite(arr).all():
        bad = sorted({int(i) for i in np.argwhere(~np.isfinite(arr))[:, 0]})
        raise UserError(f"{path}: non-finite values in row(s) {bad[:5]}")
    poses = arr[:, :15].reshape(-1, 3, 5).astype(np.float64)
    bounds = arr[:, 15:17].astype(np.float64)
    if (bounds <= 0).any() or (bounds[:, 1] <= bounds[:, 0]).any():
        raise UserError(f"{path}: bounds (columns 15, 16) must satisfy 0 < near < far")
    h_full, w_full, focal = poses[0, :, 4]
    if min(h_full, w_full, focal) <= 0:
        raise UserError(f"{path}: [H, W, focal] = {poses[0, :, 4]} must be positive")
    # Folder: images_<downscale>, else images, else the smallest images_<N> there is.
    cands = [root / f"images_{downscale}"] if downscale > 1 else []
    cands.append(root / "images")
    cands += sorted(
        (p for p in root.glob("images_*") if p.is_dir() and p.name[7:].isdigit()),
        key=lambda p: int(p.name[7:]),
    )
    folder = next((c for c in cands if c.is_dir() and _image_files(c)), None)
    if folder is None:
        raise UserError(f"{root}: no images/ or images_N/ folder with PNG/JPEG images")
    files = _image_files(folder)
    if len(files) != len(arr):
        raise UserError(
            f"{folder}: {len(files)} image(s) but {path} has {len(arr)} pose rows "
            "(one row per image, in sorted file-name order)"
        )
    _confine(root, folder, [p.name for p in files], allow_outside, path)
    w_img, h_img = _image_size(files[0])
    s = w_img / w_full
    if abs(h_img / h_full - s) > 0.01:
        raise UserError(
            f"{files[0]}: image {w_img}x{h_img} is not a scaled copy of the poses' "
            f"{int(w_full)}x{int(h_full)}"
        )
    c2w = np.tile(np.eye(4), (len(arr), 1, 1))
    # columns [down, right, back] -> OpenGL [right, up, back]
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2] = poses[:, :, 1], -poses[:, :, 0], poses[:, :, 2]
    c2w[:, :3, 3] = poses[:, :, 3]
    k = np.array([focal * s, focal * s, 0.5 * w_img, 0.5 * h_img])
    return {
        "names": [p.name for p in files],
        "folder": folder,
        "c2w": c2w,
        "intrinsics": np.tile(k, (len(arr), 1)),
        "distortion": np.zeros((len(arr), 4)),
        "bounds": bounds,
        "points": None,
        "size": (w_img, h_img),
        "unregistered": [],
        "model": str(path),
        "camera_models": ["PINHOLE"],
    }


# --------------------------------------------------------------------------------------------


def _scene(root: Path, fmt: str | None, downscale: int, allow_outside: bool = False) -> dict:
    root = data_root(root)  # (DIR/poses_bounds.npy: DIR)
    if not root.is_dir():
        raise UserError(f"{root}: data folder not found")
    found = detect_capture(root)
    fmt = fmt or found
    if fmt not in ("colmap", "llff"):
        raise UserError(f"{root}: no COLMAP model (sparse/0) or poses_bounds.npy found")
    if fmt == "colmap" and find_model(root) is None:
        raise UserError(f"{root}: --format colmap, but no cameras/images.{{bin,txt}} found")
    if fmt == "llff" and not (root / "poses_bounds.npy").is_file():
        raise UserError(f"{root}: --format llff, but no poses_bounds.npy found")
    read = _colmap if fmt == "colmap" else _llff
    sc = read(root, downscale, allow_outside)
    sc["format"] = fmt
    check_capture_cameras(sc)
    check_undistortion(sc)
    # --downscale d reads images_d when it exists, else area-averages the folder used by d.
    name = sc["folder"].name
    base = int(name[7:]) if name.startswith("images_") and name[7:].isdigit() else 1
    if base > 1 and downscale > 1 and base != downscale:
        raise UserError(
            f"{root}: --downscale {downscale}: no images_{downscale}/ folder (found {name}/, "
            f"which is already 1/{base}); use --downscale 1 for {name}/ as it is"
        )
    sc["extra"] = 1 if base > 1 else downscale
    transform, forward, scale = scene_normalisation(sc["c2w"], sc["bounds"])
    sc.update(transform=transform, forward_facing=forward, scale=scale)
    sc["c2w_norm"] = apply_transform(transform, sc["c2w"])
    # Scene-wide depth bounds in normalised units.
    if sc["bounds"] is not None and np.isfinite(sc["bounds"]).any():
        # bounds are depths along the viewing axis; the corner rays reach 1/cos further
        k, (w, h) = sc["intrinsics"], sc["size"]
        corner = np.sqrt(((np.maximum(k[:, 2], w - k[:, 2])) / k[:, 0]) ** 2
                         + ((np.maximum(k[:, 3], h - k[:, 3])) / k[:, 1]) ** 2)  # fmt: skip
        slant = float(np.sqrt(1 + corner.max() ** 2))
        near = np.nanmin(sc["bounds"][:, 0]) * scale * 0.9
        far = np.nanmax(sc["bounds"][:, 1]) * scale * 1.1 * slant
    else:
        near, far = 0.1 * CAMERA_RADIUS, 3.0 * CAMERA_RADIUS
    sc["near"], sc["far"] = float(near), float(far)
    # Scene box half-size for fields that need one (not used with NDC): the sparse points'
    # 2-98 % box when there are points, else 1.5 camera radii.
    aabb = 1.5 * CAMERA_RADIUS
    if sc["points"] is not None and not forward:
        p = sc["points"] @ transform[:3, :3].T + transform[:3, 3]
        box = np.abs(np.percentile(p, [2, 98], axis=0)).max()
        aabb = float(np.clip(box, 1.0, sc["far"]))
    sc["aabb"] = round(aabb, 3)
    check_capture_scene(sc)
    return sc


def _c2w_opencv(im) -> np.ndarray:
    """[4, 4] camera-to-world of a COLMAP image, OpenCV axes (x right, y down, z forward)."""
    r = qvec_to_rotmat(im.qvec)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r.T, -r.T @ im.tvec
    return m


def _point_index(points) -> tuple[np.ndarray, np.ndarray] | None:
    """(order, sorted ids) of a model's sparse points, for :func:`_point_rows`; None if none."""
    if points is None or not len(points["ids"]):
        return None
    order = np.argsort(points["ids"], kind="stable")
    return order, points["ids"][order]


def _point_rows(index, ids) -> tuple[np.ndarray, np.ndarray]:
    """(positions in ``ids`` [k], rows of the points [k]) of the ids that name a sparse point
    (ids of -1 and ids missing from the model are left out); ``index``: :func:`_point_index`."""
    if index is None:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    order, sorted_ids = index
    rows = np.searchsorted(sorted_ids, ids).clip(0, len(sorted_ids) - 1)
    found = (sorted_ids[rows] == ids) & (ids >= 0)
    return np.nonzero(found)[0], order[rows[found]]


def reprojection_errors(root, max_observations: int = 200_000, seed: int = 0) -> dict | None:
    """How well the loader's camera model (poses, intrinsics, undistortion) explains a COLMAP
    model's own 2D observations of its sparse points: for each observation, the angle between
    the ray through its pixel and the direction to its 3D point, times the focal length
    (pixels). Statistics over at most ``max_observations`` observations (drawn at random,
    ``seed``), next to COLMAP's own mean reprojection error. A median far above COLMAP's means
    that the loader (or the images) disagree with the model; one close to it means the poses
    are as good as the model says, and pose refinement has little to correct. None without
    sparse points or observations."""
    from .cameras import camera_rays

    model = find_model(data_root(root))
    cams, images, points = read_model(model)
    ims = sorted(images.values(), key=lambda im: im.name)
    cam_idx, xys, xyz = [], [], []
    index = _point_index(points)
    for i, im in enumerate(ims):
        pos, rows = _point_rows(index, im.point3d_ids)
        if len(pos) and im.xys is not None:
            cam_idx.append(np.full(len(pos), i))
            xys.append(im.xys[pos])
            xyz.append(points["xyz"][rows])
    if not cam_idx:
        return None
    cam_idx, xys, xyz = np.concatenate(cam_idx), np.concatenate(xys), np.concatenate(xyz)
    finite = np.isfinite(xys).all(axis=1)  # (an untrusted file's NaN pixel: left out, counted)
    n_bad = int((~finite).sum())
    size = np.array([[cams[im.camera_id].width, cams[im.camera_id].height] for im in ims])
    inside = finite & (np.nan_to_num(xys) >= 0).all(axis=1)
    inside &= (np.nan_to_num(xys) <= size[cam_idx]).all(axis=1)
    n_out = int((finite & ~inside).sum())
    cam_idx, xys, xyz = cam_idx[inside], xys[inside], xyz[inside]
    n_all = len(cam_idx)
    if not n_all:
        return None
    if n_all > max_observations:
        keep = np.sort(np.random.default_rng(seed).choice(n_all, max_observations, replace=False))
        cam_idx, xys, xyz = cam_idx[keep], xys[keep], xyz[keep]
    k, dist = zip(*(cams[im.camera_id].pinhole() for im in ims))
    c2w = torch.from_numpy(np.stack([_c2w_opencv(im) @ _OPENCV_TO_GL for im in ims]))
    k, dist = torch.from_numpy(np.stack(k)), torch.from_numpy(np.stack(dist))
    idx = torch.from_numpy(cam_idx)
    try:
        o, d = camera_rays(c2w, k, cam_idx=idx, px=torch.from_numpy(xys[:, 0]),
                           py=torch.from_numpy(xys[:, 1]), distortion=dist)  # fmt: skip
    except ValueError as e:  # an observation past the distortion model's invertible range
        raise UserError(f"{model}: {e}") from None
    v = torch.from_numpy(xyz) - o
    depth = (v * d).sum(-1)
    angle = torch.atan2(torch.linalg.cross(v, d).norm(dim=-1), depth)
    err = (angle * 0.5 * (k[idx, 0] + k[idx, 1])).numpy()
    front = depth.numpy() > 0
    e = err[front]
    out = {
        "observations": int(n_all),
        "used": int(len(err)),
        "behind_camera": int((~front).sum()),
        "non_finite": n_bad,
        "outside_image": n_out,
        "median_px": round(float(np.median(e)), 4) if len(e) else None,
        "p90_px": round(float(np.percentile(e, 90)), 4) if len(e) else None,
        "max_px": round(float(e.max()), 4) if len(e) else None,
    }
    if "error" in points and len(points["error"]):
        out["colmap_mean_error_px"] = round(float(np.mean(points["error"])), 4)
    return out


def capture_info(root, fmt=None, downscale: int = 1, holdout: int = HOLDOUT,
                 allow_outside: bool = False) -> dict:  # fmt: skip
    """Everything but the pixels: format, splits, image size, intrinsics, near/far, NDC use,
    scene transform and bounds (normalised), camera centres' box. JSON-ready. Images (the
    first one's header is read) must lie inside the folder unless ``allow_outside``."""
    req = LoadRequest.make(root, downscale=downscale, holdout=holdout)
    sc = _scene(req.root, fmt, downscale, allow_outside)
    n = len(sc["names"])
    folder = sc["folder"]
    extra = sc["extra"]
    w, h = sc["size"][0] // extra, sc["size"][1] // extra
    centres = sc["c2w_norm"][:, :3, 3]
    info = {
        "format": sc["format"],
        "model": sc["model"],
        "images_folder": str(folder),
        "images": n,
        "splits": {s: len(holdout_indices(n, s, holdout, root)) for s in ("train", "val")},
        "holdout": holdout,
        "image_size": [w, h],
        "camera_models": sc["camera_models"],
        "intrinsics": (sc["intrinsics"][0] / extra).round(4).tolist(),
        "distortion": sc["distortion"][0].tolist(),
        "distorted": bool(np.abs(sc["distortion"]).max() > 0),
        "unregistered_images": sc["unregistered"],
        "forward_facing": sc["forward_facing"],
        "ndc": sc["forward_facing"],
        "near": sc["near"],
        "far": sc["far"],
        "transform": sc["transform"].tolist(),
        "scale": sc["scale"],
        "aabb": sc["aabb"],
        "camera_centres_box": [centres.min(0).round(4).tolist(), centres.max(0).round(4).tolist()],
    }
    if sc["points"] is not None:
        p = sc["points"] @ sc["transform"][:3, :3].T + sc["transform"][:3, 3]
        info["points"] = len(p)
        info["points_box_2_98"] = [
            np.percentile(p, 2, axis=0).round(4).tolist(),
            np.percentile(p, 98, axis=0).round(4).tolist(),
        ]
    info["ndc_camera"] = _ndc_camera_info(sc, extra)  # used when NDC is on
    return info


def _ndc_camera_info(sc, extra) -> list[float]:
    k = sc["intrinsics"][0] / extra
    return [float(k[0]), float(k[1]), sc["size"][0] / extra, sc["size"][1] / extra]


def load_capture(root, split: str = "train", fmt: str | None = None, **options) -> Dataset:
    """A COLMAP or LLFF folder (``fmt``: "colmap", "llff" or None to detect) as a
    :class:`~warpnerf.data.dataset.Dataset` in the normalised frame, with ``distortion`` [N, 4],
    ``transform`` [4, 4] (float64, world -> normalised), ``near``/``far``, ``ndc`` (None, or
    [fx, fy, W, H] of the NDC camera) and ``indices``. ``options``: those of
    :class:`~warpnerf.data.dataset.LoadRequest`."""
    return _load(LoadRequest.make(root, split, **options), fmt)


def _load(req: LoadRequest, fmt: str | None) -> Dataset:
    root, downscale = data_root(req.root), req.downscale
    sc = _scene(root, fmt, downscale, req.allow_outside)
    idx = req.select(len(sc["names"]), root)
    bg = req.bg
    extra = sc["extra"]
    paths = [str(sc["folder"] / sc["names"][i]) for i in idx]

    def read_one(p):
        img = _read(Path(p))
        if img.shape[1::-1] != tuple(sc["size"])[:2]:
            raise UserError(
                f"{p}: size {img.shape[1]}x{img.shape[0]} differs from "
                f"{sc['size'][0]}x{sc['size'][1]} of {sc['folder'] / sc['names'][0]}"
            )
        if min(img.shape[:2]) < extra:
            raise UserError(f"downscale {extra} is larger than the image {p}")
        return area_downscale(composite_rgba(img, bg), extra).astype(np.float32)

    images = read_all(paths, read_one, dtype=np.uint8 if req.uint8 else np.float32)
    return Dataset(
        images=torch.from_numpy(np.ascontiguousarray(images)),
        c2w=torch.from_numpy(sc["c2w_norm"][idx]).float(),
        intrinsics=torch.from_numpy(sc["intrinsics"][idx] / extra).float(),
        paths=paths,
        format=sc["format"],
        split=req.split,
        distortion=torch.from_numpy(sc["distortion"][idx]).float(),
        transform=sc["transform"],
        near=sc["near"],
        far=sc["far"],
        ndc=_ndc_camera_info(sc, extra) if sc["forward_facing"] else None,
        indices=idx,
        keypoints=_keypoints(sc, idx),
    )


def _keypoints(sc: dict, idx: list) -> dict | None:
    """The split's sparse-point observations (COLMAP): ``cam`` [K] int64 (the image's position
    in the split), ``px``/``py`` [K] float32 (pixels of the loaded images), ``xyz`` [K, 3]
    float32 (the point, normalised frame). Observations with a non-finite pixel, one outside
    the image, or of a point not in front of the camera are left out; at most MAX_KEYPOINTS,
    drawn at random (fixed seed). None without points or observations. (A run with NDC rays
    cannot use them: its rays are not in the points' space.)"""
    obs = sc.get("observations")
    if sc.get("points") is None or not obs or not len(idx):
        return None
    extra = sc["extra"]
    w, h = sc["size"][0] // extra, sc["size"][1] // extra
    t = sc["transform"]
    world = sc["points"] @ t[:3, :3].T + t[:3, 3]  # the points in the normalised frame
    cams, xys, rows = [], [], []
    for j, i in enumerate(idx):
        xy, r = obs[i]
        xy = xy / extra
        ok = np.isfinite(xy).all(axis=1) & (xy >= 0).all(axis=1) & (xy[:, 0] <= w) & (xy[:, 1] <= h)
        c2w = sc["c2w_norm"][i]  # in front of the camera only (OpenGL: it looks down -z)
        ok &= (world[r] - c2w[:3, 3]) @ -c2w[:3, 2] > 1e-6 * sc["near"]
        cams.append(np.full(int(ok.sum()), j, dtype=np.int64))
        xys.append(xy[ok])
        rows.append(r[ok])
    cam, xy, row = np.concatenate(cams), np.concatenate(xys), np.concatenate(rows)
    if not len(cam):
        return None
    if len(cam) > MAX_KEYPOINTS:
        keep = np.sort(np.random.default_rng(0).choice(len(cam), MAX_KEYPOINTS, replace=False))
        cam, xy, row = cam[keep], xy[keep], row[keep]
    xyz = world[row]
    return {
        "cam": torch.from_numpy(cam),
        "px": torch.from_numpy(xy[:, 0].astype(np.float32)),
        "py": torch.from_numpy(xy[:, 1].astype(np.float32)),
        "xyz": torch.from_numpy(xyz.astype(np.float32)),
    }


register_format(
    "colmap", lambda req: _load(req, "colmap"), lambda root, _: find_model(root) is not None,
    capture=True,
)  # fmt: skip
register_format(
    "llff", lambda req: _load(req, "llff"), lambda root, _: (root / "poses_bounds.npy").is_file(),
    capture=True,
)  # fmt: skip


def capture_summary(root, fmt: str, downscale: int, holdout: int,
                    allow_outside: bool = False) -> dict:  # fmt: skip
    """``warpnerf data``'s figures of a capture: :func:`capture_info`, and for COLMAP the
    reprojection error of the model's observations through the loader's cameras."""
    info = capture_info(root, fmt, downscale, holdout, allow_outside)
    if fmt == "colmap":
        info["reprojection"] = reprojection_errors(root)
    return info
