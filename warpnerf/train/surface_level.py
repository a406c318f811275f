"""Where a surface run's renders put its surface, against its SDF's zero level (issue 49): the
SDF at the rendered depths of opaque training rays, and the mesh level taken from them
(``warpnerf mesh RUN --level rendered``, ``warpnerf eval RUN --geometry REF --level rendered``).

The rule: a fixed, seeded subset of the training pixels (:data:`LEVEL_RAYS` draws of a camera
and a pixel centre, seed :data:`LEVEL_SEED`; every pixel of a smaller split) is rendered with
the run's own renderer; on the rays whose opacity exceeds 0.5, f is the SDF at the expected
depth (depth / opacity); the level is the median of f, clamped to +-:data:`LEVEL_BOUND` beta.
The densities (Laplace, logistic; neus is the logistic one head-on) are sigma = Psi(-f / beta)
/ beta, so one bound in units of beta serves them all: along a ray that meets a plane head-on
where |grad f| = g, f at the rendered depth is beta times a function of g (docs/design/
surfaces.md, "Issue 49, third round"), beyond 5 beta only for g below about 0.01 or above about
5: a field that far from a distance is not one a level can correct.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from ..errors import UserError

__all__ = [
    "RENDERED",
    "LEVEL_RAYS",
    "LEVEL_SEED",
    "LEVEL_BOUND",
    "parse_level",
    "check_level",
    "plain_level",
    "training_rays",
    "sdf_at_rendered_depth",
    "level_of",
    "rendered_level",
    "mesh_level",
]

RENDERED = "rendered"  # the rule's name, the word --level takes besides a number
LEVEL_RAYS = 1 << 15  # training pixels drawn for the rule
LEVEL_SEED = 0
LEVEL_BOUND = 5.0  # |level| <= LEVEL_BOUND * beta
MIN_OPACITY = 0.5  # a ray counts where its opacity exceeds this
_FORMS = ("a finite number (the SDF's level) or 'rendered' (the median SDF at the rendered "
          "depths of opaque training rays)")  # fmt: skip


def parse_level(value) -> float | str:
    """An SDF mesh level as given (a number, or its text) -> a float, or :data:`RENDERED` for
    the word; ValueError saying the accepted forms otherwise."""
    if isinstance(value, str) and value.strip().lower() == RENDERED:
        return RENDERED
    try:
        v = float(value) if not isinstance(value, bool) else math.nan
    except (TypeError, ValueError):
        raise ValueError(f"expected {_FORMS}, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"must be finite, or 'rendered'; got {value}")
    return v


def check_level(value, flag: str = "--level") -> float | str:
    """:func:`parse_level`, a UserError naming ``flag`` and the accepted forms."""
    try:
        return parse_level(value)
    except ValueError as e:
        raise UserError(f"{flag} {e}") from None


def plain_level(level, what: str) -> float | None:
    """``level`` (None or a number) of a surface that has no renders (an SDF scene, a neural SDF
    fitted to points, a NeRF's density); UserError for 'rendered'."""
    if level == RENDERED:
        raise UserError(f"--level rendered takes the level from an SDF run's renders (train "
                        f"volsdf); {what} has none: give a number")  # fmt: skip
    return level


def training_rays(cfg, ds, n: int = LEVEL_RAYS, seed: int = LEVEL_SEED) -> tuple:
    """(origins, directions) [m, 3] of training pixels' centres of the split ``ds`` (with the
    run's refined poses, :func:`~warpnerf.train.nerf_run.with_refined_poses`), in the field's
    frame: ``n`` drawn with ``seed`` (camera and pixel uniform, with replacement), or every
    pixel where the split has no more than ``n``."""
    from .nerf_run import dataset_rays

    k, w, h = int(ds.c2w.shape[0]), int(ds.width), int(ds.height)
    if k == 0 or w < 1 or h < 1:
        raise UserError("--level rendered: the training split has no pixels")
    if k * w * h <= n:  # (a small split: all of it)
        cam, py, px = (x.reshape(-1) for x in torch.meshgrid(
            torch.arange(k), torch.arange(h), torch.arange(w), indexing="ij"))  # fmt: skip
    else:
        g = torch.Generator().manual_seed(int(seed))
        cam = torch.randint(0, k, (n,), generator=g)
        px = torch.randint(0, w, (n,), generator=g)
        py = torch.randint(0, h, (n,), generator=g)
    px, py = px.float() + 0.5, py.float() + 0.5
    dev = ds.c2w.device
    return dataset_rays(cfg, ds, cam_idx=cam.to(dev), px=px.to(dev), py=py.to(dev))


@torch.no_grad()
def sdf_at_rendered_depth(model, cfg, origins, directions, min_opacity: float = MIN_OPACITY,
                          chunk: int = 1 << 16) -> dict:  # fmt: skip
    """Where the run renders its surface along each ray, and its SDF there.

    Args:
        model, cfg: an SDF run (:func:`~warpnerf.train.nerf_run.load_run`).
        origins, directions: [n, 3] rays in the field's frame.

    Returns:
        {"keep": [n] bool (opacity > ``min_opacity``), "opacity": [n], "t": [m] the kept rays'
        expected depth / opacity, "sdf": [m] float32 f at origins + t directions}.
    """
    from .nerf_run import render_rays_of

    out = render_rays_of(model, cfg, origins, directions, chunk=cfg.chunk)
    opacity = out["opacity"].reshape(-1)
    keep = opacity > min_opacity
    t = out["depth"].reshape(-1)[keep] / opacity[keep]
    p = origins[keep] + t.unsqueeze(-1) * directions[keep]
    f = [model.field.sdf(p[s : s + chunk]).float() for s in range(0, len(p), chunk)]
    sdf = torch.cat(f) if f else torch.zeros(0, device=p.device)
    return {"keep": keep, "opacity": opacity, "t": t, "sdf": sdf}


def level_of(sdf: torch.Tensor, beta: float, bound: float = LEVEL_BOUND) -> tuple:
    """The rule's level from the SDF at the rendered depths [m]: (their median clamped to
    +-``bound`` beta, its figures: median, p10, p90, opaque_rays, beta, bound (in world units),
    clamped)."""
    if sdf.numel() == 0:
        raise UserError("--level rendered: no training ray renders opaque (opacity > 0.5): "
                        "no surface to take a level from")  # fmt: skip
    f = sdf.detach().double().cpu()
    med, lim = float(f.median()), bound * float(beta)
    level = min(max(med, -lim), lim)
    p10, p90 = torch.quantile(f[:: max(1, f.numel() // 1_000_000)], torch.tensor(
        [0.1, 0.9], dtype=f.dtype)).tolist()  # fmt: skip
    return level, {"median": med, "p10": p10, "p90": p90, "opaque_rays": int(f.numel()),
                   "beta": float(beta), "bound": lim, "clamped": level != med}  # fmt: skip


def rendered_level(model, cfg, ds, rays: int = LEVEL_RAYS, seed: int = LEVEL_SEED,
                   bound: float = LEVEL_BOUND) -> tuple:  # fmt: skip
    """The rendered-level rule (the module's) on the training split ``ds``: (level, figures:
    rays, seed and :func:`level_of`'s, and "rule": the sentence the tools report)."""
    o, d = training_rays(cfg, ds, rays, seed)
    beta = float(torch.as_tensor(model.field.beta).detach())
    level, info = level_of(sdf_at_rendered_depth(model, cfg, o, d)["sdf"], beta, bound)
    info = {"rays": int(o.shape[0]), "seed": int(seed), **info}
    how = (f"clamped to +-{bound:g} beta = {info['bound']:.4g}" if info["clamped"] else
           f"within +-{bound:g} beta = {info['bound']:.4g}")  # fmt: skip
    info["rule"] = (f"rendered: the median SDF at the expected depths of the {info['opaque_rays']}"
                    f" opaque rays (opacity > {MIN_OPACITY}) of {info['rays']} training pixels "
                    f"(seed {seed}), {info['median']:.4g}, {how}")  # fmt: skip
    return level, info


def mesh_level(model, cfg, level, cameras: Callable) -> tuple:
    """The level to mesh an SDF run at: (``level`` checked, as a float (None: 0), None), or for
    'rendered' (the rule's level, :func:`rendered_level`'s figures) on the training split
    ``cameras()`` gives (None: the run's data is not at hand, a UserError)."""
    level = check_level(0.0 if level is None else level)
    if level != RENDERED:
        return level, None
    ds = cameras()
    if ds is None:
        raise UserError("--level rendered renders the run's training rays; its training data "
                        "is not at hand")  # fmt: skip
    return rendered_level(model, cfg, ds)
