"""Exports of a trained run that other tools open: a coloured point cloud with normals (PLY, for
MeshLab, Blender, pyvista) and the cameras as a nerfstudio ``transforms.json``.

Point cloud: every ``stride``-th pixel (in x and y) of the chosen training views is rendered with
the run's own renderer; where the ray's opacity exceeds ``min_opacity`` the point is where it
terminates, origin + direction * (expected depth / opacity), coloured with the rendered colour
(the view's own, so view-dependent highlights are baked as seen from that camera). Normals: the
normalised central-difference gradient of the level-set function at the point (the SDF for SDF
fields, minus the density for NeRF fields: both grow outwards), step ``1e-3`` of the scene box.
For COLMAP/LLFF runs points and normals are mapped back to the capture's world units (a normal as
the image of a short step along it, so NDC runs work too).

Cameras: the run's training (and validation) cameras, OpenGL camera-to-world in the frame the run
trains in, with per-frame intrinsics and image paths relative to the JSON; a capture's
world-to-normalised transform is recorded as nerfstudio's ``applied_transform``. Datasets without
image files (the built-in scene), and runs trained on downscaled copies of their files
(``--downscale``), get the images the run trained on written beside the JSON: every frame's
intrinsics and size describe its file. An export never replaces a file a dataset or run may read:
an image already at an exported image's name is kept when it holds the same pixels (the same
export again) and refused otherwise, and ``--out`` may not be the index (``transforms*.json``) of
the dataset the run reads; both before anything is written.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from .errors import UserError
from .outputs import check_foreign, json_safe, make_folder, write_image, write_json

__all__ = ["export_pointcloud", "export_cameras"]


@torch.no_grad()
def export_pointcloud(run, out, views: int = 0, stride: int = 2, min_opacity: float = 0.5,
                      device=None, progress: bool = False) -> dict:  # fmt: skip
    """Writes the point cloud PLY ``out``; returns a summary dict. ``progress``: the views
    rendered, on stderr (:class:`~warpnerf.train.progress.Progress`)."""
    from .mesh import write_ply
    from .train.nerf import dataset_rays, load_data, load_run, render_rays_of, with_refined_poses
    from .train.progress import Progress

    if not 1 <= stride <= 64:
        raise UserError(f"--stride must be in [1, 64], got {stride}")
    if not 0.0 < min_opacity < 1.0:
        raise UserError(f"--min-opacity must be in (0, 1), got {min_opacity}")
    if views < 0:
        raise UserError(f"--views must be >= 0, got {views}")
    check_foreign([out])  # before the work: another program's file there is refused
    cfg, model, _ = load_run(run, device)
    ds = with_refined_poses(model, load_data(cfg, "train"), "train")
    n = ds.images.shape[0] if not views else min(views, ds.images.shape[0])
    pick = torch.linspace(0, ds.images.shape[0] - 1, n).round().long().unique().tolist()
    h, w = ds.height, ds.width
    keep_px = torch.zeros(h, w, dtype=torch.bool)
    keep_px[::stride, ::stride] = True
    keep_px = keep_px.reshape(-1)
    pts, cols = [], []
    bar = Progress(len(pick), "export pointcloud", unit="view", enabled=progress)
    for i in pick:
        o, d = dataset_rays(cfg, ds, image=i)
        sel = keep_px.to(o.device)
        o, d = o[sel], d[sel]
        r = render_rays_of(model, cfg, o, d, chunk=cfg.chunk)
        ok = r["opacity"] > min_opacity
        z = r["depth"][ok] / r["opacity"][ok]
        pts.append(o[ok] + d[ok] * z.unsqueeze(-1))
        cols.append(r["rgb"][ok])
        bar.update()
    bar.close()
    p = torch.cat(pts) if pts else torch.zeros(0, 3)
    c = torch.cat(cols) if cols else torch.zeros(0, 3)
    if len(p) == 0:
        raise UserError(f"{run}: no ray reaches opacity {min_opacity}; nothing to export")
    field = model.field
    step = 1e-3 * (cfg.aabb if cfg.aabb > 0 else 1.0)
    if model.kind == "sdf":
        fn = field.sdf
    else:

        def fn(x):
            return -field.density(x)[0]

    nrm = _normals(fn, p.float(), step)
    pw, nw = p.cpu().numpy().astype(np.float64), nrm.cpu().numpy().astype(np.float64)
    if cfg.scene is not None:  # back to the capture's world units
        from .data.capture import normalised_to_world

        ndc = cfg.ndc_camera()
        a = normalised_to_world(pw, cfg.scene["transform"], ndc)
        b = normalised_to_world(pw + step * nw, cfg.scene["transform"], ndc)
        nw = b - a
        nw /= np.maximum(np.linalg.norm(nw, axis=1, keepdims=True), 1e-12)
        pw = a
    good = np.isfinite(pw).all(1) & np.isfinite(nw).all(1)
    pw, nw = pw[good], nw[good]
    rgb = (c.float().clamp(0, 1).cpu().numpy()[good] * 255 + 0.5).astype(np.uint8)
    write_ply(out, pw.astype(np.float32), np.zeros((0, 3), np.int32), colors=rgb,
              normals=nw.astype(np.float32))  # fmt: skip
    return {"out": str(out), "points": int(len(pw)), "views": len(pick), "stride": stride,
            "min_opacity": min_opacity, "bounds_min": pw.min(0).tolist(),
            "bounds_max": pw.max(0).tolist()}  # fmt: skip


def _normals(fn, x: torch.Tensor, h: float, chunk: int = 1 << 16) -> torch.Tensor:
    """Unit outward normals [n, 3]: normalised central differences of ``fn`` (+z where the
    gradient vanishes)."""
    e = torch.eye(3, device=x.device)
    out = []
    for s in range(0, len(x), chunk):
        q = x[s : s + chunk]
        d = fn(torch.cat([q + h * e[i] for i in range(3)] + [q - h * e[i] for i in range(3)]))
        d = d.float().reshape(6, -1)
        g = torch.nan_to_num((d[:3] - d[3:]).T)
        n = torch.nn.functional.normalize(g, dim=-1)
        up = torch.tensor([0.0, 0.0, 1.0], device=x.device)
        out.append(torch.where(n.norm(dim=-1, keepdim=True) > 0, n, up))
    return torch.cat(out) if out else torch.zeros(0, 3, device=x.device)


def _image_size(path) -> tuple | None:
    """(width, height) from an image file's header (nothing decoded); None if unreadable."""
    from PIL import Image

    from .safe_writes import open_input

    try:
        with open_input(path, "image", follow=True) as fh, Image.open(fh) as im:
            return im.size
    except Exception:  # (the loader read it a moment ago; then: the run's images are written)
        return None


def _indexes_read_by(cfg) -> set:
    """The resolved paths of the dataset index files (``transforms*.json``) a run reads."""
    if cfg.data == "builtin":
        return set()
    root = Path(cfg.data)
    files = [root] if root.is_file() else sorted(root.glob("transforms*.json"))
    return {p.resolve() for p in files}


def _keeps(path: Path, img: torch.Tensor) -> bool:
    """Whether the image ``path`` (absent, or a file warpnerf wrote) may stay as the exported
    image ``img`` (uint8 [H, W, C]): False when absent; True when it holds exactly these pixels
    (the same export again); a :class:`UserError` when it holds others, which a dataset (an
    earlier export) or a run may read: an export never replaces them."""
    from .data.images import read_image, to_uint8

    if not os.path.lexists(path):
        return False
    old = to_uint8(read_image(path))
    new = img.numpy()
    if old.shape == new.shape and np.array_equal(old, new):
        return True
    (h, w), (nh, nw) = old.shape[:2], new.shape[:2]
    raise UserError(
        f"{path}: exists and holds other pixels ({w}x{h} there, {nw}x{nh} from this run); a "
        "dataset or run may read it and export never replaces an image: export into another "
        "folder (--out OTHER/transforms.json)"
    )


def export_cameras(run, out, splits=("train", "val")) -> dict:
    """Writes a nerfstudio ``transforms.json`` (``out``) of the run's cameras (and, in
    ``images/`` beside it, the images the run trained on where they are no file of that size:
    the built-in scene, a run with ``--downscale``); returns a summary. Every target is
    checked before anything is written: a file warpnerf did not write there (the JSON or an
    image), or a link in place of ``images/``, is refused with nothing written. Nothing a
    dataset or run may read is replaced: ``out`` may not be the index of the run's own dataset,
    and an image already at an exported name must hold the same pixels (it is then kept)."""
    from .train.nerf import load_data, load_run, with_refined_poses

    out = Path(out)
    if out.suffix != ".json":
        raise UserError(f"--out must be a .json file, got {out}")
    cfg, model, _ = load_run(run, "cpu")
    frames, images = [], []  # images: (path relative to the JSON, uint8 [H, W, C]) to write
    for split in splits:
        try:
            ds = with_refined_poses(model, load_data(cfg, split), split)
        except UserError:
            if split == "train":
                raise
            continue  # no such split
        for i in range(ds.images.shape[0]):
            fx, fy, cx, cy = (float(v) for v in ds.intrinsics[i])
            trained = (ds.width, ds.height)  # the run's pixels (after --downscale)
            if i < len(ds.paths) and _image_size(ds.paths[i]) == trained:
                path = os.path.relpath(Path(ds.paths[i]).resolve(), out.parent.resolve())
            else:  # no image file (the built-in scene), or one of another size than the run
                # trained on (--downscale): the run's images, written beside the JSON, so that
                # every frame's intrinsics describe its file
                path = f"images/{split}_{i:03d}.png"
                images.append((path, (ds.images[i].clamp(0, 1) * 255 + 0.5).to(torch.uint8)))
            frames.append({
                "file_path": path, "transform_matrix": ds.c2w[i].double().tolist(),
                "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": ds.width, "h": ds.height,
                "split": split,
            })  # fmt: skip
    doc = {"camera_model": "OPENCV", "frames": frames}
    if cfg.scene is not None:  # a capture: poses are in the run's normalised frame
        doc["applied_transform"] = np.asarray(cfg.scene["transform"])[:3].tolist()
        if cfg.ndc_camera() is None:  # its scene settings, so that a run on it trains the same
            keys = ("near", "far", "aabb", "inner")
            doc["warpnerf_scene"] = {k: float(cfg.scene[k]) for k in keys if k in cfg.scene}
    folder = out.parent / "images"
    if images and os.path.lexists(folder):  # a link or a file there: refused before any write
        make_folder(folder, "exported images folder")
    if out.exists() and out.resolve() in _indexes_read_by(cfg):
        raise UserError(
            f"{out}: the run {run} reads it (its dataset's index); export never replaces a file "
            "a dataset or run reads: choose another --out"
        )
    check_foreign([out, *(out.parent / rel for rel, _ in images)])
    todo = [(rel, img) for rel, img in images if not _keeps(out.parent / rel, img)]
    if images:
        make_folder(folder, "exported images folder")
    for rel, img in todo:
        write_image(out.parent / rel, img.numpy())
    write_json(out, json_safe(doc))
    frame = "normalised (applied_transform)" if cfg.scene is not None else "data"
    return {"out": str(out), "frames": len(frames), "images_written": len(todo),
            "images_unchanged": len(images) - len(todo),
            "images_folder": str(folder) if images else None, "frame": frame}  # fmt: skip
