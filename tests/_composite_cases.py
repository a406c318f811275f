"""Shared cases and helpers for the compositing tests (not a test module)."""

from __future__ import annotations

from types import SimpleNamespace

import torch

import warpnerf as W
from warpnerf import reference as R

from ._twin import TOL64, assert_matches_twin

F32, F64 = torch.float32, torch.float64
OUT_NAMES = ("rgb", "depth", "opacity", "weights")


# --------------------------------------------------------------------------------------------------
# helpers


def _mk(layout, mode, n_rays, t_starts, t_ends, ray_indices, values, rgbs):
    """A test case: samples ([n] packed or [n_rays, n_samples] dense) and their inputs."""
    return SimpleNamespace(
        layout=layout,
        mode=mode,
        n_rays=n_rays,
        t_starts=t_starts,
        t_ends=t_ends,
        ray_indices=ray_indices,
        values=values,
        rgbs=rgbs,
    )


def _pack(case):
    """The dense case as a packed one (every ray keeps all its samples)."""
    n_rays, n_s = case.values.shape
    ray_indices = torch.arange(n_rays, device=case.values.device).repeat_interleave(n_s)
    flat = [x.reshape(-1) for x in (case.t_starts, case.t_ends, case.values)]
    return _mk(
        "packed", case.mode, n_rays, *flat[:2], ray_indices, flat[2], case.rgbs.reshape(-1, 3)
    )


def _packed_case(counts, mode, *, sigma_max=4.0, dtype=F64, device="cpu"):
    """Random packed samples: per-ray ordered, touching intervals starting at a random near."""
    counts = torch.as_tensor(counts, dtype=torch.int64)
    n_rays, n = len(counts), int(counts.sum())
    ray_indices = torch.repeat_interleave(torch.arange(n_rays), counts)
    deltas = torch.rand(n, dtype=F64) * 0.3 + 0.02
    t_starts = torch.empty(n, dtype=F64)
    start = 0
    for c in counts.tolist():
        edges = torch.cumsum(torch.cat([torch.rand(1, dtype=F64), deltas[start : start + c]]), 0)
        t_starts[start : start + c] = edges[:-1]
        start += c
    t_ends = t_starts + deltas
    if mode == "alpha":
        values = torch.rand(n, dtype=F64) * 0.9 + 0.05
    else:
        values = torch.rand(n, dtype=F64) * sigma_max
    rgbs = torch.rand(n, 3, dtype=F64)
    case = _mk("packed", mode, n_rays, t_starts, t_ends, ray_indices, values, rgbs)
    return _to(case, device, dtype)


def _dense_case(n_rays, n_samples, mode, *, sigma_max=4.0, dtype=F64, device="cpu"):
    deltas = torch.rand(n_rays, n_samples, dtype=F64) * 0.3 + 0.02
    near = torch.rand(n_rays, 1, dtype=F64)
    t_ends = near + torch.cumsum(deltas, 1)
    t_starts = t_ends - deltas
    if mode == "alpha":
        values = torch.rand(n_rays, n_samples, dtype=F64) * 0.9 + 0.05
    else:
        values = torch.rand(n_rays, n_samples, dtype=F64) * sigma_max
    rgbs = torch.rand(n_rays, n_samples, 3, dtype=F64)
    case = _mk("dense", mode, n_rays, t_starts, t_ends, None, values, rgbs)
    return _to(case, device, dtype)


def _case(layout, mode, **kw):
    kw.setdefault("sigma_max", 8.0)  # dense enough that T drops below 1e-2 on several rays
    if layout == "packed":
        # Uneven counts, including an empty ray in the middle.
        return _packed_case([5, 12, 0, 1, 9, 16, 3], mode, **kw)
    return _dense_case(6, 11, mode, **kw)


def _to(case, device, dtype):
    out = SimpleNamespace(**vars(case))
    for k in ("t_starts", "t_ends", "values", "rgbs"):
        setattr(out, k, getattr(case, k).to(device, dtype))
    if case.ray_indices is not None:
        out.ray_indices = case.ray_indices.to(device)
    return out


def _background(kind, n_rays, device, dtype=F64):
    if kind == "none":
        return None
    if kind == "shared":
        return torch.rand(3, dtype=F64).to(device, dtype)
    return torch.rand(n_rays, 3, dtype=F64).to(device, dtype)


def _upstream(case, return_weights=True):
    """Random upstream gradients for (rgb, depth, opacity[, weights])."""
    dev, dt = case.values.device, case.values.dtype
    g = [
        torch.randn(case.n_rays, 3, dtype=F64),
        torch.randn(case.n_rays, dtype=F64),
        torch.randn(case.n_rays, dtype=F64),
    ]
    if return_weights:
        g.append(torch.randn(case.values.shape, dtype=F64))
    return [x.to(dev, dt) for x in g]


def _render(lib, case, values, rgbs, background, t_threshold=0.0, return_weights=True):
    sig, kw = (None, {"alphas": values}) if case.mode == "alpha" else (values, {})
    if case.layout == "packed":
        return lib.render_packed(
            case.t_starts,
            case.t_ends,
            case.ray_indices,
            sig,
            rgbs,
            case.n_rays,
            background,
            t_threshold=t_threshold,
            return_weights=return_weights,
            **kw,
        )
    return lib.render_dense(
        case.t_starts,
        case.t_ends,
        sig,
        rgbs,
        background,
        t_threshold=t_threshold,
        return_weights=return_weights,
        **kw,
    )


def _run(lib, case, background=None, t_threshold=0.0, upstream=None, return_weights=True):
    """Outputs (detached) and, with upstream gradients g, d<g, outputs> / d(values, rgbs[, bg])."""
    values = case.values.detach().clone().requires_grad_()
    rgbs = case.rgbs.detach().clone().requires_grad_()
    bg = None if background is None else background.detach().clone().requires_grad_()
    out = _render(lib, case, values, rgbs, bg, t_threshold, return_weights)
    if upstream is None:
        return [o.detach() for o in out], None
    leaves = [values, rgbs] + ([bg] if bg is not None else [])
    grads = torch.autograd.grad(out, leaves, upstream[: len(out)])
    return [o.detach() for o in out], list(grads)


def _match(case, background=None, t_threshold=0.0, *, return_weights=True, tol=TOL64, **kw):
    """The Warp compositing (warpnerf.ops) against its float64 twin (warpnerf.reference) on one
    case: outputs rgb, depth, opacity[, weights] and gradients d/dvalues, d/drgbs[, d/dbackground]
    (tests/_twin.py; ``kw`` go to assert_matches_twin)."""

    def call(lib):
        def render(values, rgbs, background):
            return _render(lib, case, values, rgbs, background, t_threshold, return_weights)

        return render

    inputs = {"values": case.values, "rgbs": case.rgbs, "background": background}
    grad = ["values", "rgbs"] + ([] if background is None else ["background"])
    names = OUT_NAMES if return_weights else OUT_NAMES[:3]
    return assert_matches_twin(call(W), call(R), inputs, grad=grad, names=names, tol=tol, **kw)
