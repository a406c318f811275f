"""A small built-in scene for NeRF demos and tests (no data needed): a diffuse rainbow box and a
glossy sphere whose highlight moves with the viewpoint, rendered by warpnerf's own pipeline.

The field is analytic: density sigma = (1 / beta) * Psi_beta(-sdf) (VolSDF's Laplace-CDF density,
beta = 0.02), colour from the nearer object; the sphere adds a Phong highlight
max(0, reflect(d, n) . l)^6 that depends on the view direction d, so a model without view
dependence cannot reproduce it.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
import sys
from pathlib import Path

import torch
from torch import nn

from ..fields.sdf_volume import laplace_cdf, sdf_box, sdf_sphere
from ..render import render_views
from .builtin_cache import cached_arrays
from .cameras import intrinsics_from_fov, orbit_views
from .dataset import Dataset, LoadRequest, register_format

__all__ = ["GlossyScene", "make_synthetic_dataset"]

NEAR, FAR, RADIUS, FOV_X = 1.0, 4.0, 2.5, 0.7
BOUND = 1.0  # the scene lies inside [-BOUND, BOUND]^3
# Bump when the scene's images change for a reason the sources hashed by _code_version miss
# (e.g. a kernel of the renderer): cached images of older versions are then made again.
SCENE_VERSION = 2  # 2: the splits' alpha (the rendered opacity) cached beside their images


class GlossyScene(nn.Module):
    def __init__(self, view_dependent: bool = True, beta: float = 0.02):
        super().__init__()
        self.view_dependent, self.beta = view_dependent, beta
        self.box_c, self.box_s = torch.tensor([-0.4, -0.1, 0.0]), torch.tensor([0.55, 0.55, 0.55])
        self.sph_c, self.sph_r = torch.tensor([0.4, 0.15, 0.05]), 0.38
        self.light = torch.nn.functional.normalize(torch.tensor([0.6, -0.8, 1.2]), dim=0)

    def surface_points(self, n: int = 4000, seed: int = 0) -> torch.Tensor:
        """About n points [n, 3] spread by area over the scene's analytic surface (the box's
        faces and the sphere; the two do not touch): the reference a mesh of it is scored by."""
        g = torch.Generator().manual_seed(seed)
        a_sph, a_box = 4 * math.pi * self.sph_r**2, 6 * float(self.box_s[0]) ** 2
        k = round(n * a_sph / (a_sph + a_box))
        unit = torch.nn.functional.normalize(torch.randn(k, 3, generator=g), dim=-1)
        sph = self.sph_c + self.sph_r * unit
        u = torch.rand(n - k, 3, generator=g) - 0.5
        axis = torch.randint(0, 3, (n - k,), generator=g)
        u[torch.arange(n - k), axis] = torch.randint(0, 2, (n - k,), generator=g) - 0.5
        return torch.cat([sph, self.box_c + u * self.box_s])

    def forward(self, p: torch.Tensor, d: torch.Tensor):  # [n, 3], [n, 3] -> [n], [n, 3]
        dev = p.device
        bc, bs, sc = self.box_c.to(dev), self.box_s.to(dev), self.sph_c.to(dev)
        s_box = sdf_box(p, bc, bs)
        s_sph = sdf_sphere(p, sc, self.sph_r)
        sdf = torch.minimum(s_box, s_sph)
        sigma = laplace_cdf(-sdf, self.beta) / self.beta
        box_rgb = ((p - bc).abs() * 1.6).clamp(0.05, 0.95)
        n = torch.nn.functional.normalize(p - sc, dim=-1)
        light = self.light.to(dev)
        diffuse = (n @ light).clamp_min(0.0).unsqueeze(-1)
        base = torch.tensor([0.85, 0.35, 0.2], device=dev)
        sph_rgb = base * (0.35 + 0.65 * diffuse)
        if self.view_dependent:
            refl = d - 2.0 * (d * n).sum(-1, keepdim=True) * n
            spec = (refl @ light).clamp_min(0.0) ** 6
            sph_rgb = sph_rgb + 0.7 * spec.unsqueeze(-1)
        rgb = torch.where((s_box < s_sph).unsqueeze(-1), box_rgb, sph_rgb.clamp(0.0, 1.0))
        return sigma, rgb


@functools.lru_cache(maxsize=1)
def _code_version() -> str:
    """SHA-256 of the sources that define the scene's images: this module (the field, cameras'
    settings), the SDFs and density, the cameras and the rendering pipeline."""
    h = hashlib.sha256(f"scene {SCENE_VERSION}".encode())
    for fn in (render_views, laplace_cdf, orbit_views, GlossyScene):
        path = getattr(sys.modules.get(fn.__module__), "__file__", None)
        try:
            h.update(Path(path).read_bytes() if path else fn.__module__.encode())
        except OSError:
            h.update(fn.__module__.encode())
    return h.hexdigest()


def _views(n: int, seed: int, size: int, device):
    """The cameras of a split: c2w [n, 4, 4], intrinsics [n, 4]."""
    cams = orbit_views(n, radius=RADIUS, seed=seed * 1.7).to(device)
    k = intrinsics_from_fov(size, size, FOV_X).to(device).expand(n, 4).contiguous()
    return cams, k


def cache_entry(
    n_train: int, n_val: int, size: int, view_dependent: bool, n_samples: int, device
) -> tuple[dict, dict]:
    """The disk cache's key of the scene's images (everything that determines them: the
    settings, the device type and the code) and the spec the cached arrays must match."""
    key = {
        "code": _code_version(),
        "n_train": n_train,
        "n_val": n_val,
        "size": size,
        "view_dependent": bool(view_dependent),
        "n_samples": n_samples,
        "device": torch.device(device).type,  # (the GPU's floats differ from the CPU's)
    }
    spec = {
        "train": ((n_train, size, size, 3), "float32", 0.0, 1.0),
        "val": ((n_val, size, size, 3), "float32", 0.0, 1.0),
        "train_alpha": ((n_train, size, size), "float32", 0.0, 1.0),
        "val_alpha": ((n_val, size, size), "float32", 0.0, 1.0),
    }
    return key, spec


def _scene_images(
    n_train: int, n_val: int, size: int, view_dependent: bool, n_samples: int, device
) -> dict:
    """The splits' images {"train": [n_train, size, size, 3], "val": ...} and alpha
    {"train_alpha": [n_train, size, size], "val_alpha": ...} (the rendered opacity; float32 numpy
    in [0, 1]), from the disk cache (:mod:`~warpnerf.data.builtin_cache`) when they were made
    before with the same settings, device type and code, else rendered (and stored)."""
    key, spec = cache_entry(n_train, n_val, size, view_dependent, n_samples, device)

    def make():
        scene = GlossyScene(view_dependent)
        out = {}
        for split, n, seed in (("train", n_train, 0), ("val", n_val, 1)):
            cams, k = _views(n, seed, size, device)
            views = render_views(cams, k, size, size, NEAR, FAR, scene, n_samples=n_samples,
                                 mode="sigma", background=1.0)  # fmt: skip
            out[split] = views["rgb"].clamp(0, 1).float().cpu().numpy()
            out[f"{split}_alpha"] = views["opacity"].clamp(0, 1).float().cpu().numpy()
        return out

    return cached_arrays("builtin", key, spec, make)


@functools.lru_cache(maxsize=4)
def make_synthetic_dataset(
    n_train: int = 64,
    n_val: int = 4,
    size: int = 48,
    view_dependent: bool = True,
    n_samples: int = 256,
    device="cpu",
):
    r"""Renders the built-in scene: (train, val) :class:`~warpnerf.data.dataset.Dataset`\ s
    (images [N, H, W, 3], c2w [N, 4, 4], intrinsics [N, 4], near, far; no paths); white
    background; each split's alpha (the rendered opacity, [N, H, W]) in ``alpha``. Cached in
    the process (treat the returned tensors as read-only) and on disk across processes (the
    images; see :func:`_scene_images`)."""
    images = _scene_images(n_train, n_val, size, view_dependent, n_samples, device)
    out = []
    for split, n, seed in (("train", n_train, 0), ("val", n_val, 1)):
        cams, k = _views(n, seed, size, device)
        out.append(
            Dataset(
                images=torch.from_numpy(images[split]).to(device),
                alpha=torch.from_numpy(images[f"{split}_alpha"]).to(device),
                c2w=cams,
                intrinsics=k,
                format="builtin",
                split=split,
                near=NEAR,
                far=FAR,
            )
        )
    return out[0], out[1]


def _load_builtin(req: LoadRequest) -> Dataset:
    """The ``builtin`` format: a split of the built-in scene (rendered on ``req.device``)."""
    train, val = make_synthetic_dataset(size=req.builtin_size, device=req.device)
    ds = train if req.split == "train" else val
    n = req.max_images or len(ds)
    images, alpha = ds.images[:n], ds.alpha[:n] if req.alpha else None
    if req.uint8:
        images = (images.clamp(0, 1) * 255).round().to(torch.uint8)
        alpha = None if alpha is None else (alpha * 255).round().to(torch.uint8)
    return dataclasses.replace(ds, images=images, alpha=alpha, c2w=ds.c2w[:n],
                               intrinsics=ds.intrinsics[:n])  # fmt: skip


register_format("builtin", _load_builtin, lambda root, _: str(root) == "builtin", folder=False)
