"""What the renderers call on a field (docs/ARCHITECTURE.md, "Fields and the model"), where one
rule must hold at every call site.

A field whose density depends on the ray's direction (hash_sdf with NeuS's density: how fast a
ray approaches the surface, :func:`warpnerf.fields.hash_sdf.neus_density`) says so with
``density_needs_directions = True``; every density evaluation along rays then passes each
sample's direction. :func:`density` is that rule in one place; fields without the flag are
called as before, ``density(positions)``.
"""

from __future__ import annotations

import torch

__all__ = ["density", "needs_directions"]


def needs_directions(field) -> bool:
    """Whether ``field.density`` takes the samples' directions."""
    return bool(getattr(field, "density_needs_directions", False))


def density(field, positions: torch.Tensor, directions: torch.Tensor | None = None, **kw):
    """``field.density(positions, **kw)``, with ``directions`` [n, 3] (each sample's ray
    direction) when the field's density needs them; ``directions`` may then be a callable
    returning them, so a caller gathers them only for such fields."""
    if not needs_directions(field):
        return field.density(positions, **kw)
    if callable(directions):
        directions = directions()
    if directions is None:
        raise ValueError(f"{type(field).__name__}'s density needs the samples' directions")
    return field.density(positions, directions, **kw)
