"""What the viewer shows of a run, independent of the web page: a :class:`RunScene` renders any
camera of the scene through the project's own renderers, and lists the overlays (training
cameras with their images, the scene box, the occupancy grid's occupied cells, a mesh).

Two kinds of run:

- radiance runs (``train nerf`` / ``train volsdf``: the NeRF MLP, the hash field, VolSDF and
  hash_sdf): :func:`~warpnerf.train.nerf.render_rays_of` (grid marching or stratified samples,
  rendered in chunks by :func:`~warpnerf.render.render_chunks`); modes ``rgb``, ``depth``,
  ``opacity`` and, for SDF fields, ``normals`` (the field's SDF gradient at the rendered depth);
- neural SDFs fitted to points (``train sdf``): the SDF sphere-traced inside its normalised box,
  modes ``shaded`` (grey, headlight), ``normals``, ``depth`` and ``opacity`` (hits);
- box fits (``train box``, the main job's task): the fitted analytic box volume-rendered with
  the fit's settings, modes ``rgb``, ``depth``, ``opacity``.

Cameras are OpenGL camera-to-world matrices [4, 4] (x right, y up, looking down -z) with pixel
intrinsics, as everywhere in the project. :meth:`RunScene.render` holds the scene's ``lock`` per
block of rays (a checkpoint reload swaps the weights under it; a live training renders in its
own thread between steps, so it needs no lock) and polls an ``abort`` callable between blocks,
so a frame that a newer camera, a closed browser or a stop request has made useless stops
early. For that it sizes the blocks from the measured speed (:attr:`ray_seconds` and the fixed
cost of a block, :attr:`block_overhead`, fitted to recent blocks) so that each takes about
``block_seconds`` (0.2 s in the viewer), also on a slow CPU; :meth:`RunScene.rays_within` says
how many rays a frame can have to render in a given time.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from pathlib import Path

import numpy as np
import torch

from ..data.camera_path import window_rule
from ..errors import UserError
from ..outputs import to_uint8

__all__ = ["RunScene", "load_scene", "scene_of", "RADIANCE_MODES", "SDF_MODES", "POINT_SDF_MODES"]

RADIANCE_MODES = ("rgb", "depth", "opacity")
SDF_MODES = ("rgb", "depth", "normals", "opacity")
POINT_SDF_MODES = ("shaded", "normals", "depth", "opacity")
MAX_OVERLAY_POINTS = 20000  # occupied cells drawn at most
THUMBNAIL = 64  # training images shown in the frustums, longest side in pixels
BLOCK_RAYS = 1 << 14  # rays rendered at a time (at most; fewer when blocks are timed)
FIRST_BLOCK_RAYS = 64  # the first timed block while the speed is unknown
TIMED_BLOCKS = 32  # recent blocks the speed is fitted to


class Aborted(Exception):
    """A frame given up because ``abort()`` said so."""


class RunScene:
    """A run as the viewer sees it. Build it with :func:`load_scene` (a run folder) or
    :meth:`of_radiance` (a live model, e.g. from a training loop)."""

    def __init__(self, render_rays, modes, box, *, up=(0.0, 0.0, 1.0), cameras=None,
                 intrinsics=None, size=None, images=None, grid=None, far=None,
                 window=None, title=""):  # fmt: skip
        self._render_rays = render_rays  # (o [n,3], d [n,3], mode) -> image values [n, 3]
        self.modes = tuple(modes)
        self.box = [float(v) for v in box]  # [6]
        self.up = tuple(float(v) for v in up)
        self.cameras = cameras  # [n, 4, 4] OpenGL c2w (host) or None
        self.intrinsics = intrinsics  # [n, 4] fx, fy, cx, cy or None
        self.size = size  # (W, H) of the training images
        self.images = images  # [n, h, w, 3] uint8 thumbnails or None
        self.grid = grid
        self.far = far
        self.window = window  # camera position [3] -> (near, far) the frame uses, or None
        self.title = title
        ext = max(self.box[3] - self.box[0], self.box[4] - self.box[1], self.box[5] - self.box[2])
        self.frustum_scale = 0.035 * ext if ext > 0 else 0.1  # training cameras' drawn size
        self.ray_seconds = None  # measured seconds per ray, None until measured
        self.block_overhead = 0.0  # measured fixed seconds of a block (launches, Python)
        self._timings: list = []  # (rays, seconds) of recent blocks
        self.lock = threading.Lock()  # held while rendering and while reloading weights
        self.mesh = None  # (vertices [v, 3], faces [f, 3], colours [v, 3] uint8 or None)
        self.reload = None  # () -> step: re-reads the run's checkpoint (a run folder's scene)

    # --------------------------------------------------------------------------- overlays

    def target(self) -> np.ndarray:
        """Where a new viewer camera looks: the training cameras' common target, else the box
        centre."""
        if self.cameras is not None and len(self.cameras) > 1:
            from ..data.cameras import camera_target

            return np.asarray(camera_target(torch.as_tensor(self.cameras)), dtype=np.float64)
        b = self.box
        return np.array([(b[0] + b[3]) / 2, (b[1] + b[4]) / 2, (b[2] + b[5]) / 2])

    def occupied_cells(self, limit: int = MAX_OVERLAY_POINTS) -> np.ndarray | None:
        """Centres [m, 3] of occupied occupancy-grid cells (an even subsample of at most
        ``limit``), or None without a grid."""
        if self.grid is None:
            return None
        from ..ops.occupancy import unpack_bits

        with self.lock:
            occ = unpack_bits(self.grid.bits).cpu()
        idx = torch.nonzero(occ).squeeze(1)
        if idx.numel() > limit:
            idx = idx[torch.linspace(0, idx.numel() - 1, limit).long()]
        res = self.grid.res
        ijk = torch.stack([idx // (res * res), (idx // res) % res, idx % res], -1).double()
        lo, hi = torch.tensor(self.grid.box[:3]), torch.tensor(self.grid.box[3:])
        return ((ijk + 0.5) / res * (hi - lo).double() + lo.double()).numpy()

    def load_mesh(self, path) -> bool:
        """Shows the mesh in ``path`` (a PLY from ``warpnerf mesh``, vertex colours kept) when it
        exists; False when there is none. A broken file is a :class:`UserError`."""
        from ..mesh import read_ply

        p = Path(path)
        if not p.is_file():
            return False
        v, f, c = read_ply(p, colors=True)
        self.mesh = (np.asarray(v, np.float32), np.asarray(f, np.int32), c)
        return True

    # -------------------------------------------------------------------------- rendering

    @torch.no_grad()
    def render(self, c2w, fx: float, fy: float, width: int, height: int, mode: str = "",
               abort=None, block_seconds: float | None = None) -> np.ndarray:  # fmt: skip
        """An image [height, width, 3] uint8 of the camera ``c2w`` [4, 4] (OpenGL) with focal
        lengths ``fx, fy`` (pixels, principal point at the centre) in ``mode`` (default the
        first of :attr:`modes`). Rendered :data:`BLOCK_RAYS` rays at a time or, with
        ``block_seconds``, in blocks sized from the measured speed to take about that long
        (the first one :data:`FIRST_BLOCK_RAYS` rays while the speed is unknown; each at most 4
        times the last), each block an even sample of the whole image (a fixed shuffle of its
        rays) so that every block costs alike, whatever part of it is empty; ``abort()`` true
        between blocks raises :class:`Aborted`."""
        from ..ops import generate_rays

        mode = mode or self.modes[0]
        if mode not in self.modes:
            raise ValueError(f"mode must be one of {self.modes}, got {mode!r}")
        if not (0 < width <= 8192 and 0 < height <= 8192):
            raise ValueError(f"image size must be 1..8192 pixels a side, got {width}x{height}")
        c2w = torch.as_tensor(np.asarray(c2w, dtype=np.float32)).reshape(4, 4)
        if not bool(torch.isfinite(c2w).all()) or not (math.isfinite(fx) and math.isfinite(fy)):
            raise ValueError("camera pose and focal lengths must be finite")
        k = torch.tensor([float(fx), float(fy), width / 2.0, height / 2.0], dtype=torch.float32)
        o, d = generate_rays(c2w[None], k[None], width, height)
        n = width * height
        img, start = torch.empty(n, 3), 0
        order = torch.arange(n)
        if block_seconds is not None:
            order = torch.randperm(n, generator=torch.Generator().manual_seed(0))
        size = BLOCK_RAYS if block_seconds is None else self._block_rays(block_seconds, None)
        while start < n:
            if abort is not None and abort():
                raise Aborted
            idx = order[start : start + size]
            with self.lock:
                t0 = time.perf_counter()
                img[idx] = self._render_rays(o[idx], d[idx], mode).float().cpu()
                dt = time.perf_counter() - t0
            self._timed(len(idx), dt)
            if block_seconds is not None:
                size = self._block_rays(block_seconds, size)
            start += len(idx)
        return to_uint8(img.reshape(height, width, 3))

    def _timed(self, n: int, seconds: float) -> None:
        """Updates the speed from a block of ``n`` rays that took ``seconds``: the fixed cost
        ``a`` of ``seconds = a + b n`` fitted to the recent blocks when their sizes differ
        enough, the cost ``b`` a ray from the last 4 (so it follows what the camera sees)."""
        t = self._timings
        t.append((n, seconds))
        del t[:-TIMED_BLOCKS]
        ns, ts = np.array(t, dtype=np.float64).T
        if len(t) >= 3 and ns.std() > 0.2 * ns.mean():
            b, a = np.polyfit(ns, ts, 1)
            if b > 0:  # (less than the quickest block took)
                self.block_overhead = float(min(max(a, 0.0), 0.9 * ts.min()))
        rn, rt = float(ns[-4:].sum()), float(ts[-4:].sum())
        self.ray_seconds = max(rt - self.block_overhead * min(4, len(t)), 0.1 * rt) / rn

    def _block_rays(self, seconds: float, last: int | None = None) -> int:
        """Rays in the next timed block: about ``seconds`` at the measured speed, 16 to
        :data:`BLOCK_RAYS`, at most 4 times the ``last`` block (default: the last one timed), so
        that a wrong estimate costs one block at most."""
        if self.ray_seconds is None:
            return FIRST_BLOCK_RAYS
        a = self.block_overhead  # (a block cannot take less: aim at 1.5 times it at least)
        n = int((max(seconds, 1.5 * a) - a) / max(self.ray_seconds, 1e-12))
        if last is None:
            last = self._timings[-1][0] if self._timings else BLOCK_RAYS
        return max(16, min(BLOCK_RAYS, n, 4 * last))

    def rays_within(self, seconds: float, block_seconds: float = 0.2) -> int | None:
        """How many rays a frame rendered in blocks of ``block_seconds`` can have to take at
        most ``seconds`` at the measured speed (the blocks' fixed cost included); None while the
        speed is unknown."""
        if self.ray_seconds is None:
            return None
        a, b = self.block_overhead, max(self.ray_seconds, 1e-12)
        block = max(16, min(BLOCK_RAYS, int((max(block_seconds, 1.5 * a) - a) / b)))
        if seconds <= a + b * block:  # one block
            return max(1, int((seconds - a) / b))
        return max(1, int(seconds / (b + a / block)))

    # ------------------------------------------------------------------------ constructors

    @classmethod
    def of_radiance(cls, model, cfg, train=None, title: str = "") -> RunScene:
        """A radiance run's scene (``model`` a :class:`~warpnerf.fields.model.RadianceModel`,
        ``cfg`` its NeRFConfig, ``train`` its training split for the camera overlay)."""
        from ..data.cameras import ndc_rays
        from ..train.nerf import render_rays_of

        dev, ndc = cfg.device, cfg.ndc_camera()
        contracted = getattr(cfg, "contract", "off") == "on"
        sdf = model.kind == "sdf"
        far = float(cfg.far)
        cams = train.c2w if train is not None else None
        shifted = window_rule(cams, cfg.near, cfg.far) if ndc is None else None

        def window(cam):  # (the run's config with this camera's near/far: a copy)
            if shifted is None:
                return cfg
            near, far = shifted(cam)
            return dataclasses.replace(cfg, near=near, far=far)

        def render_rays(o, d, mode):
            o, d = o.to(dev), d.to(dev)
            c = window(o[0])
            if ndc is not None:
                o, d = ndc_rays(o, d, ndc)
            res = render_rays_of(model, c, o, d, chunk=cfg.chunk)
            if mode != "normals":  # (contracted: far lies 1000 scene sizes away)
                return _image_values(res, mode, c.far if not contracted else 4.0 * cfg.aabb)
            x = o + d * res["depth"].reshape(-1, 1)  # normals of an SDF field at the depth
            n = model.coarse.normals(x)
            return torch.where(res["opacity"].reshape(-1, 1) > 0.5, (n + 1) / 2, torch.ones_like(n))

        intr = images = size = None
        if train is not None:
            cams, intr = train.c2w.detach().cpu().numpy(), train.intrinsics.detach().cpu().numpy()
            size = (int(train.width), int(train.height))
            images = _thumbnails(train.images)
        box = cfg.aabb_box() or [-cfg.aabb, -cfg.aabb, -cfg.aabb, cfg.aabb, cfg.aabb, cfg.aabb]
        if ndc is not None:  # forward-facing: draw the cameras' neighbourhood instead
            box = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]
        elif cfg.aabb <= 0 and cams is not None:  # an MLP run has no box: what the cameras see
            box = cameras_box(cams, cfg.near, cfg.far)
        up = _up_of(cams)
        return cls(render_rays, SDF_MODES if sdf else RADIANCE_MODES, box, up=up, cameras=cams,
                   intrinsics=intr, size=size, images=images, grid=model.grid, far=far,
                   window=shifted, title=title)  # fmt: skip

    @classmethod
    def of_box(cls, volume, cfg, train=None, title: str = "") -> RunScene:
        """A box fit (``train box``): its analytic SDF volume rendered with the fit's settings."""
        from ..render import render_rays as render_volume

        dev = volume.center.device
        shifted = window_rule(train.c2w if train is not None else None, cfg.near, cfg.far)

        def render_rays(o, d, mode):
            o, d = o.to(dev), d.to(dev)
            near, far = shifted(o[0])
            return _image_values(render_volume(o, d, near, far, volume, **cfg.render_kwargs()),
                                 mode, far)  # fmt: skip

        c = volume.center.detach().cpu().tolist()
        h = (0.5 * volume.side_lengths.detach().abs().cpu()).tolist()
        box = [c[0] - h[0], c[1] - h[1], c[2] - h[2], c[0] + h[0], c[1] + h[1], c[2] + h[2]]
        cams = intr = images = size = None
        if train is not None:
            cams, intr = train.c2w.cpu().numpy(), train.intrinsics.cpu().numpy()
            size, images = (int(train.width), int(train.height)), _thumbnails(train.images)
        return cls(render_rays, RADIANCE_MODES, box, up=_up_of(cams), cameras=cams,
                   intrinsics=intr, size=size, images=images, far=cfg.far, window=shifted,
                   title=title)  # fmt: skip

    @classmethod
    def of_point_sdf(cls, model, cfg, title: str = "") -> RunScene:
        """A neural SDF fitted to points: sphere-traced in its normalised box [-1, 1]^3."""
        from ..ops import ray_aabb_intersect
        from ..sphere_tracing import shade, sphere_trace_fn

        dev = cfg.device
        box = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]
        grey = torch.tensor([[0.8, 0.8, 0.8]])

        def render_rays(o, d, mode):
            o, d = o.to(dev), d.to(dev)
            t0, t1, hit = ray_aabb_intersect(o, d, box)
            t1 = torch.where(hit, t1, t0)
            tr = sphere_trace_fn(model, o, d, t0, t1, eps=1e-3, max_iters=128)
            m = tr.hit.reshape(-1, 1)
            if mode == "shaded":
                return shade(tr, d, grey.to(dev), light=None)
            if mode == "normals":
                return torch.where(m, (tr.normals + 1) / 2, torch.ones_like(tr.normals))
            if mode == "opacity":
                return m.float().expand(-1, 3)
            far = float(o[0].norm()) + math.sqrt(3.0)  # the box's far side: one scale a frame
            return ((1.0 - tr.t.reshape(-1, 1) / far).clamp(0, 1) * m).expand(-1, 3)

        return cls(render_rays, POINT_SDF_MODES, box, up=(0.0, 1.0, 0.0), title=title)


def _image_values(res: dict, mode: str, far: float) -> torch.Tensor:
    """[n, 3] pixel values of a volume renderer's output for ``mode``: rgb, opacity, or depth
    (near: bright; beyond ``far`` or on rays with opacity below 0.5: black)."""
    acc = res["opacity"].reshape(-1, 1)
    if mode == "rgb":
        return res["rgb"]
    if mode == "opacity":
        return acc.expand(-1, 3)
    dep = (1.0 - res["depth"].reshape(-1, 1) / max(far, 1e-6)).clamp(0, 1)
    return (dep * (acc > 0.5)).expand(-1, 3)


def cameras_box(c2w, near: float, far: float) -> list:
    """[6] a cube around the training cameras' common target holding what every camera sees
    between ``near`` and ``far`` (for runs without a scene box, e.g. ``--field mlp``): half side
    ``min(R - near, far - R)``, ``R`` the cameras' mean distance to the target (``R / 2`` when
    that is not positive, e.g. cameras looking past each other)."""
    from ..data.cameras import camera_target

    c2w = torch.as_tensor(c2w).detach().cpu().double()
    if len(c2w) < 2:
        centre = c2w[0, :3, 3] - c2w[0, :3, 2] * 0.5 * (near + far)
        half = 0.25 * (far - near)
    else:
        centre = camera_target(c2w)
        r = float((c2w[:, :3, 3] - centre).norm(dim=-1).mean())
        half = min(r - near, far - r)
        half = half if half > 0 else 0.5 * r
    c = centre.tolist()
    return [c[0] - half, c[1] - half, c[2] - half, c[0] + half, c[1] + half, c[2] + half]


def _thumbnails(images: torch.Tensor) -> np.ndarray:
    """uint8 [n, h, w, 3] copies of [n, H, W, 3] float (or already 8-bit: a training split kept
    on the host) images, longest side :data:`THUMBNAIL`."""
    n, h, w = images.shape[:3]
    s = max(1, math.ceil(max(h, w) / THUMBNAIL))
    small = images[:, ::s, ::s, :3].detach().cpu()
    if small.dtype == torch.uint8:
        return small.contiguous().numpy()
    return to_uint8(small.float())


def _up_of(c2w) -> tuple:
    """The training cameras' mean up vector (their y axis), or +z."""
    if c2w is None or len(c2w) == 0:
        return (0.0, 0.0, 1.0)
    u = np.asarray(c2w)[:, :3, 1].mean(0)
    n = float(np.linalg.norm(u))
    return tuple((u / n).tolist()) if n > 1e-6 else (0.0, 0.0, 1.0)


def scene_of(method, opened) -> RunScene:
    """The :class:`RunScene` of a run or a training task opened by its method
    (:mod:`warpnerf.train.methods`): ``method.view`` picks the renderer."""
    o = opened
    if method.view == "radiance":
        scene = RunScene.of_radiance(o.model, o.cfg, o.training_cameras(), title=o.title)
        if o.reload is not None:
            scene.reload = lambda: o.reload(scene.lock)
        return scene
    if method.view == "point_sdf":
        return RunScene.of_point_sdf(o.model, o.cfg, title=o.title)
    return RunScene.of_box(o.model, o.cfg, o.training_cameras(), title=o.title)


def load_scene(run, device: str | None = None, mesh: str | None = None) -> RunScene:
    """The :class:`RunScene` of a run folder: a ``train nerf``/``train volsdf`` run (its
    training cameras too) or a ``train sdf`` run. ``mesh``: a PLY to show (default RUN/mesh.ply
    when it exists)."""
    from ..train.methods import method_of_run

    method = method_of_run(run)  # (UserError: not a run folder, a kind of run no one knows)
    scene = scene_of(method, method.open_run(run, device))
    if mesh is not None:
        if not scene.load_mesh(mesh):
            raise UserError(f"{mesh}: no such mesh file")
    else:
        scene.load_mesh(Path(run) / "mesh.ply")
    return scene
