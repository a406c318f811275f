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

import torch
from torch import nn

from ..fields.sdf_volume import laplace_cdf, sdf_box, sdf_sphere
from ..render import render_views
from .cameras import intrinsics_from_fov, orbit_views
from .dataset import Dataset, LoadRequest, register_format

__all__ = ["GlossyScene", "make_synthetic_dataset"]

NEAR, FAR, RADIUS, FOV_X = 1.0, 4.0, 2.5, 0.7
BOUND = 1.0  # the scene lies inside [-BOUND, BOUND]^3


class GlossyScene(nn.Module):
    def __init__(self, view_dependent: bool = True, beta: float = 0.02):
        super().__init__()
        self.view_dependent, self.beta = view_dependent, beta
        self.box_c, self.box_s = torch.tensor([-0.4, -0.1, 0.0]), torch.tensor([0.55, 0.55, 0.55])
        self.sph_c, self.sph_r = torch.tensor([0.4, 0.15, 0.05]), 0.38
        self.light = torch.nn.functional.normalize(torch.tensor([0.6, -0.8, 1.2]), dim=0)

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
    background. Cached: treat the returned tensors as read-only."""
    scene = GlossyScene(view_dependent)
    out = []
    for n, seed in ((n_train, 0), (n_val, 1)):
        cams = orbit_views(n, radius=RADIUS, seed=seed * 1.7).to(device)
        k = intrinsics_from_fov(size, size, FOV_X).to(device).expand(n, 4).contiguous()
        img = render_views(
            cams, k, size, size, NEAR, FAR, scene, n_samples=n_samples, mode="sigma", background=1.0
        )["rgb"]
        out.append(
            Dataset(
                images=img.clamp(0, 1),
                c2w=cams,
                intrinsics=k,
                format="builtin",
                split="train" if seed == 0 else "val",
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
    images = ds.images[:n]
    if req.uint8:
        images = (images.clamp(0, 1) * 255).round().to(torch.uint8)
    return dataclasses.replace(ds, images=images, c2w=ds.c2w[:n], intrinsics=ds.intrinsics[:n])


register_format("builtin", _load_builtin, lambda root, _: str(root) == "builtin")
