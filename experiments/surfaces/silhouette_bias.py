"""Issue 49: why materials' hash_sdf spheres come out uniformly ~0.02 too small.

A ray that passes a sphere at distance m outside its zero level set still crosses the density's
tail in front of the surface: with VolSDF's Laplace density sigma = Psi_beta(-d) / beta, near the
closest point d(t) ~ m + t^2 / (2 r), so the ray's optical depth is about
(0.5 / beta) exp(-m / beta) sqrt(2 pi r beta), and its opacity reaches 1/2 at

    m(r, beta) = beta * ln((0.5 / beta) * sqrt(2 pi r beta) / ln 2)

outside the zero level. A field fitted to the images' silhouettes (the mask loss, the colour at
the edges) therefore puts its zero level m *inside* the true surface: the rendered outline is
the true one, the mesh (the zero level) is eroded by m. The same for the density "along the
normal" of NeuS (s sigmoid(-s d), ``--sdf-density logistic``), whose tail is heavier. This script
measures m by bisection on the exact sphere SDF, float64, for the library's two densities, and
prints it beside the closed form and the head-on depth bias (a plane seen along its normal).

    python3 experiments/surfaces/silhouette_bias.py [--radius 0.32] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import math

import torch

from warpnerf.fields.hash_sdf import sdf_density

BETAS = (0.02, 0.01, 0.005, 0.003, 0.002, 0.001)


def opacity_past(kind: str, b: float, radius: float, beta: float, dt: float = 2e-5) -> float:
    """Opacity of a straight ray passing the sphere's centre at distance b (exact SDF)."""
    t = torch.arange(-1.0, 1.0, dt, dtype=torch.float64)
    d = torch.sqrt(t * t + b * b) - radius
    tau = float((sdf_density(kind, d, beta) * dt).sum())
    return 1.0 - math.exp(-tau)


def silhouette_shift(kind: str, radius: float, beta: float) -> float:
    """How far outside the zero level the rendered outline (opacity 1/2) lies."""
    lo, hi = radius - 10 * beta, radius + 20 * beta
    for _ in range(45):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if opacity_past(kind, mid, radius, beta) > 0.5 else (lo, mid)
    return 0.5 * (lo + hi) - radius


def laplace_closed_form(radius: float, beta: float) -> float:
    return beta * math.log((0.5 / beta) * math.sqrt(2 * math.pi * radius * beta) / math.log(2))


def head_on_depth(kind: str, beta: float, dt: float = 1e-5) -> float:
    """Expected depth behind a plane's zero level along its normal (positive: behind)."""
    t = torch.arange(-0.5, 0.5, dt, dtype=torch.float64)
    sigma = sdf_density(kind, -t, beta)
    alpha = 1.0 - torch.exp(-sigma * dt)
    trans = torch.exp(-(torch.cumsum(sigma * dt, 0) - sigma * dt))
    w = trans * alpha
    return float((w * t).sum() / w.sum())


def table(radius: float, betas=BETAS) -> list[dict]:
    return [
        {
            "beta": b,
            "laplace_shift": silhouette_shift("laplace", radius, b),
            "laplace_closed_form": laplace_closed_form(radius, b),
            "logistic_shift": silhouette_shift("logistic", radius, b),
            "laplace_head_on_depth": head_on_depth("laplace", b),
        }
        for b in betas
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--radius", type=float, default=0.32, help="sphere radius (materials: 0.32)")
    ap.add_argument("--json", help="write the rows here")
    a = ap.parse_args()
    rows = table(a.radius)
    print(f"sphere radius {a.radius}: the rendered outline lies this far outside the zero level")
    print("| beta | Laplace (VolSDF) | closed form | logistic (s sigmoid(-s d)) | head-on depth |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['beta']:g} | {r['laplace_shift']:+.4f} | {r['laplace_closed_form']:+.4f} | "
              f"{r['logistic_shift']:+.4f} | {r['laplace_head_on_depth']:+.4f} |")  # fmt: skip
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"radius": a.radius, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
