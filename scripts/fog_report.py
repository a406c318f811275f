"""Fog in a trained run: N frames of the spiral `warpnerf render` draws by default (at a reduced
size), one contact sheet of them, and per ray how much of its compositing weight lies near the
camera.

python3 scripts/fog_report.py RUN [--data DIR] [--device D] [--frames 8] [--size WxH]
    [--k 0.5] [--near-frac 0.6] [--out DIR] [--json F]

Definitions (every ray of every frame; w_i the weight of sample i in the ray's pixel, t_i its
midpoint's distance along the unit-length ray from the camera, W = sum_i w_i its opacity):

- ``near_median``: the share of W at t_i < k * m, m the ray's weighted median distance (the
  midpoint of the first sample at which the running sum of w reaches W / 2; ``--k``, 0.5).
  Weight well in front of where the ray's own surface lies, whatever the scene's scale.
- ``near_centre``: the share of W at t_i < f * D, D the camera's distance to the scene centre
  (the normalised scene's origin: the point nearest to every viewing axis of a capture, the
  centre of the built-in and Blender scenes) and ``--near-frac`` f (0.6: beer's near plane
  lies at 0.5 D, 99.97 % of the COLMAP points its cameras see beyond 0.75 D). The same stretch
  as ``train nerf --near-loss`` penalises with ``--near-loss-frac``. Weight close to the
  camera, whatever the ray's median (fog dense enough to pull the median in front of the
  surface still counts here).

For each, the JSON gives the mean share over rays (``share``) and the fraction of rays whose
share exceeds 10 % (``rays_over_10pct``), per frame and over all frames. Rays with W < 0.01
(nothing in front of the background) have no share and are counted as ``empty_rays``. The
weights are those of the image: the run's grid rendered by the rounds path (all samples
composited, early termination at the run's ``t_threshold``), or its proposal sampler's.

The sheet (``fog_sheet.png`` in ``--out``, default RUN/fog_report) has one column per frame:
colour, depth (darker is nearer, as `render` draws it), and the near_centre share per pixel
(black 0, white 0.5 or more). The JSON (``fog.json`` there, and ``--json`` if given) is also
printed, one line, last. Works with no GPU (its smoke test: a tiny built-in run on the CPU).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import torch

from warpnerf.data.cameras import camera_rays
from warpnerf.ops import packed_info_from_ray_indices
from warpnerf.outputs import contact_sheet, make_folder, to_uint8, write_image, write_json
from warpnerf.render import weight_before, weight_median
from warpnerf.train.nerf import depth_scale, load_data, load_run, render_rays_of
from warpnerf.train.nerf_eval import depth_image, path_cameras

MIN_OPACITY = 0.01  # rays below: no share (nothing but the background)
OVER = 0.1  # a ray "has fog" when more than this share of its weight is near the camera
SHEET_MAX = 0.5  # the sheet's near-share row: white at this share and above


def ray_shares(ri, t0, t1, w, origins, k: float, near_frac: float) -> dict:
    """Per ray [n_rays]: opacity W, and the near_median and near_centre weights (not yet
    divided by W) of the samples ``(ri, t0, t1, w)`` a render reported (any order)."""
    n_rays = origins.shape[0]
    order = torch.argsort(t0, stable=True)  # (t order within each ray, then rays grouped)
    order = order[torch.argsort(ri[order], stable=True)]
    ri, t0, t1, w = ri[order], t0[order], t1[order], w[order]
    info = packed_info_from_ray_indices(ri, n_rays)
    opacity = w.new_zeros(n_rays).index_add(0, ri.long(), w)
    median = weight_median(t0, t1, ri, w, info)
    cut = torch.nan_to_num(k * median, nan=0.0)
    return {
        "opacity": opacity,
        "median": median,
        "near_median": weight_before(t0, t1, ri, w, info, cut),
        "near_centre": weight_before(t0, t1, ri, w, info, near_frac * origins.norm(dim=-1)),
    }


def summary(shares: dict, mask) -> dict:
    """The figures of some rays: counted and empty rays, and per definition the mean share and
    the fraction of rays above :data:`OVER`."""
    seen = shares["opacity"] >= MIN_OPACITY
    out = {"rays": int((seen & mask).sum()), "empty_rays": int((~seen & mask).sum())}
    for name in ("near_median", "near_centre"):
        s = (shares[name] / shares["opacity"].clamp_min(MIN_OPACITY))[seen & mask].double()
        n = max(s.numel(), 1)
        out[name] = {"share": float(s.sum()) / n, "rays_over_10pct": float((s > OVER).sum()) / n}
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run")
    p.add_argument("--data", default=None, help="the dataset folder (default: the run's)")
    p.add_argument("--device", default=None, help="cpu or cuda (default: the run's)")
    p.add_argument("--frames", type=int, default=8, help="frames of the spiral")
    p.add_argument("--size", default=None, help="WxH (default: the training size, scaled down "
                   "to a longer side of 320)")  # fmt: skip
    p.add_argument("--k", type=float, default=0.5, help="near_median: t < k x median")
    p.add_argument("--near-frac", type=float, default=0.6, help="near_centre: t < this x the "
                   "camera's distance to the scene centre")  # fmt: skip
    p.add_argument("--out", default=None, help="folder of the sheet and fog.json (default "
                   "RUN/fog_report)")  # fmt: skip
    p.add_argument("--json", default=None, help="also write the JSON here")
    a = p.parse_args()
    if a.frames < 1 or not a.k > 0 or not a.near_frac > 0:
        raise SystemExit("--frames, --k and --near-frac must be positive")
    cfg, model, ckpt = load_run(a.run, a.device)
    if model.grid is None and model.proposal is None:
        raise SystemExit("fog_report needs a run with an occupancy grid or --sampler proposal")
    if cfg.ndc_camera() is not None:
        raise SystemExit("fog_report measures distances in world space: this run uses NDC rays")
    if a.data:  # (the run's config with the data moved: a checked, frozen copy)
        cfg = dataclasses.replace(cfg, data=a.data).check_values().freeze()
    train = load_data(cfg, "train")
    if a.size:
        w, h = (int(x) for x in a.size.lower().split("x"))
    else:
        f = min(1.0, 320 / max(train.width, train.height))
        w, h = max(1, round(train.width * f)), max(1, round(train.height * f))
    cams, k = path_cameras(cfg, train, "spiral", a.frames, (w, h))
    out_dir = Path(a.out or Path(a.run) / "fog_report")
    make_folder(out_dir, "fog report folder")
    rows, frames, scale, t_all = [], [], None, time.perf_counter()
    totals = {n: [] for n in ("opacity", "near_median", "near_centre")}
    with torch.no_grad():
        for f in range(a.frames):
            t0 = time.perf_counter()
            o, d = camera_rays(cams[f], k, w, h)
            samples = []
            out = render_rays_of(model, cfg, o, d, chunk=cfg.chunk,
                                 on_weights=lambda *s, kept=samples: kept.append(s))  # fmt: skip
            ri, ts, te, wt = (torch.cat(x) for x in zip(*samples))
            sh = ray_shares(ri, ts, te, wt, o, a.k, a.near_frac)
            row = summary(sh, torch.ones(w * h, dtype=torch.bool, device=o.device))
            gap = float((sh["opacity"] - out["opacity"]).abs().max())  # (the hook's sums)
            row.update(frame=f, camera_distance=float(o[0].norm()), opacity_mismatch=gap,
                       seconds=time.perf_counter() - t0)  # fmt: skip
            rows.append(row)
            for n in totals:
                totals[n].append(sh[n].cpu())
            dep, opa = out["depth"].reshape(h, w).cpu(), out["opacity"].reshape(h, w).cpu()
            if scale is None:  # (the first frame that shows a surface: as `render` does)
                scale = depth_scale(cfg, dep, opa)
            near = (sh["near_centre"] / sh["opacity"].clamp_min(MIN_OPACITY)).reshape(h, w)
            frames.append([to_uint8(out["rgb"].reshape(h, w, 3).cpu()),
                           depth_image(dep, opa, scale or cfg.far).numpy(),
                           to_uint8((near / SHEET_MAX).cpu())])  # fmt: skip
    sheet = contact_sheet([fr[r] for r in range(3) for fr in frames], cols=a.frames)
    write_image(out_dir / "fog_sheet.png", sheet)
    allr = {n: torch.cat(v) for n, v in totals.items()}
    res = {
        "run": str(a.run), "step": int(ckpt["step"]), "device": cfg.device, "field": cfg.field,
        "sampler": "proposal" if model.proposal is not None else "grid",
        "frames": a.frames, "size": [w, h], "k": a.k, "near_frac": a.near_frac,
        "min_opacity": MIN_OPACITY, "over": OVER,
        "overall": summary(allr, torch.ones_like(allr["opacity"], dtype=torch.bool)),
        "per_frame": rows, "sheet": str(out_dir / "fog_sheet.png"),
        "seconds": time.perf_counter() - t_all,
    }  # fmt: skip
    if cfg.device.startswith("cuda"):
        res["gpu"] = torch.cuda.get_device_name()
    write_json(out_dir / "fog.json", res)
    if a.json:
        write_json(a.json, res)
    print(json.dumps(res))


if __name__ == "__main__":
    main()
