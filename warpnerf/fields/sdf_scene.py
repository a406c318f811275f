"""Analytic SDF scenes from Python: primitives with transforms, folded by CSG operations.

    scene = SDFScene()
    scene.box(size=(1, 1, 1), rounding=0.05).sphere(0.65, op="subtraction")
    scene.torus(0.8, 0.1, center=(0, 0.5, 0), rotation_deg=(90, 0, 0), op="smooth_union", k=0.1)

Primitives are folded left to right (``acc = op(acc, d_i)``; the first one's op is ignored), which
covers unions of many objects, carved solids and blends; see kernels/sphere_trace.py for the
distance functions and the operations. ``scene.sdf(points)`` and ``warpnerf.ops.sphere_trace``
run the Warp kernels; ``warpnerf.reference.scene_sdf`` is the PyTorch twin.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..errors import UserError

__all__ = ["SDFScene", "Primitive", "torus_scene", "many_primitives_scene", "KINDS", "OPS"]

KINDS = {"sphere": 0, "box": 1, "torus": 2, "capsule": 3, "plane": 4}
OPS = {"union": 0, "smooth_union": 1, "intersection": 2, "subtraction": 3}


def rotation_from_euler_deg(rx: float, ry: float, rz: float) -> torch.Tensor:
    """Local-to-world rotation R = Rz @ Ry @ Rx (degrees), float64 [3, 3]."""
    a, b, c = (math.radians(v) for v in (rx, ry, rz))
    rx_ = torch.tensor([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    ry_ = torch.tensor([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rz_ = torch.tensor([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    return (rz_ @ ry_ @ rx_).double()


@dataclass
class Primitive:
    kind: str
    params: tuple  # 4 floats, meaning per kind (kernels/sphere_trace.py)
    center: tuple = (0.0, 0.0, 0.0)
    rotation_deg: tuple = (0.0, 0.0, 0.0)  # local-to-world, R = Rz Ry Rx
    op: str = "union"
    k: float = 0.0  # smooth-union width
    color: tuple = (0.8, 0.8, 0.8)

    def validate(self, where: str = "primitive"):
        """Raises UserError naming the field unless every value has the right type and range."""

        def numbers(name, v, n):
            ok = isinstance(v, (list, tuple)) and len(v) == n
            ok = ok and all(
                isinstance(x, (int, float))
                and not isinstance(x, bool)
                and math.isfinite(x)
                and abs(x) < 1e30
                for x in v
            )
            if not ok:
                raise UserError(f"{where}: {name} must be {n} finite numbers, got {v!r}")

        if not isinstance(self.kind, str) or self.kind not in KINDS:
            raise UserError(f"{where}: kind must be one of {sorted(KINDS)}, got {self.kind!r}")
        if not isinstance(self.op, str) or self.op not in OPS:
            raise UserError(f"{where}: op must be one of {sorted(OPS)}, got {self.op!r}")
        numbers("params", self.params, 4)
        numbers("center", self.center, 3)
        numbers("rotation_deg", self.rotation_deg, 3)
        numbers("color", self.color, 3)
        numbers("k", (self.k,), 1)
        needs = {"sphere": 1, "box": 3, "torus": 2, "capsule": 2, "plane": 0}[self.kind]
        if any(p <= 0 for p in self.params[:needs]) or self.params[3] < 0:
            raise UserError(f"{where}: {self.kind} sizes must be positive, got {self.params}")
        if self.kind == "box" and self.params[3] > min(self.params[:3]):
            raise UserError(f"{where}: box rounding larger than its half size")
        if self.op == "smooth_union" and self.k <= 0:
            raise UserError(f"{where}: smooth_union needs k > 0")


@dataclass
class SDFScene:
    primitives: list = field(default_factory=list)

    # ---- building -----------------------------------------------------------------------
    def add(self, kind, params, center=(0, 0, 0), rotation_deg=(0, 0, 0), op="union", k=0.0,
            color=(0.8, 0.8, 0.8)):  # fmt: skip
        prim = Primitive(
            kind,
            tuple(float(v) for v in params),
            tuple(float(v) for v in center),
            tuple(float(v) for v in rotation_deg),
            op,
            float(k),
            tuple(float(v) for v in color),
        )
        prim.validate(f"primitive {len(self.primitives)}")
        self.primitives.append(prim)
        return self

    def sphere(self, radius, **kw):
        return self.add("sphere", (radius, 0, 0, 0), **kw)

    def box(self, size=(1, 1, 1), rounding=0.0, **kw):
        """size: full side lengths; rounding: edge radius (inside the size)."""
        return self.add("box", (size[0] / 2, size[1] / 2, size[2] / 2, rounding), **kw)

    def torus(self, major, minor, **kw):
        """Ring of radius ``major`` in the local xz plane, tube radius ``minor``."""
        return self.add("torus", (major, minor, 0, 0), **kw)

    def capsule(self, length, radius, **kw):
        """Segment of ``length`` along local y, swept by a ball of ``radius``."""
        return self.add("capsule", (length / 2, radius, 0, 0), **kw)

    def plane(self, height=0.0, **kw):
        """The ground plane z = height (z up, as the cameras), solid below; ``rotation_deg``
        overrides the orientation (the local plane is y = 0: rotation (90, 0, 0) makes it z)."""
        c = kw.pop("center", (0.0, 0.0, height))
        rot = kw.pop("rotation_deg", (90.0, 0.0, 0.0))
        return self.add("plane", (0, 0, 0, 0), center=c, rotation_deg=rot, **kw)

    # ---- serialisation ------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"primitives": [vars(p).copy() for p in self.primitives]}

    @classmethod
    def from_dict(cls, d, where="scene") -> SDFScene:
        if not isinstance(d, dict) or not isinstance(d.get("primitives"), list):
            raise UserError(f"{where}: expected an object with a 'primitives' list")
        if not d["primitives"]:
            raise UserError(f"{where}: 'primitives' is empty")
        scene = cls()
        known = set(Primitive.__dataclass_fields__)
        for i, p in enumerate(d["primitives"]):
            if not isinstance(p, dict) or "kind" not in p or "params" not in p:
                raise UserError(f"{where}: primitives[{i}] needs 'kind' and 'params'")
            unknown = set(p) - known
            if unknown:
                raise UserError(f"{where}: primitives[{i}] has unknown fields {sorted(unknown)}")
            try:
                prim = Primitive(
                    **{k: tuple(v) if isinstance(v, list) else v for k, v in p.items()}
                )
            except TypeError as e:
                raise UserError(f"{where}: primitives[{i}]: {e}") from None
            prim.validate(f"{where}: primitives[{i}]")
            scene.primitives.append(prim)
        return scene

    @classmethod
    def load(cls, path) -> SDFScene:
        """The scene of a JSON file ({"primitives": [...]}, as :meth:`to_dict`); UserError naming
        the file for a missing, unreadable, oversized, malformed or too deeply nested file and
        for any field of the wrong type or range."""
        from ..json_input import read_json

        path = Path(path)
        if not path.exists():
            raise UserError(f"{path}: no such scene file")
        return cls.from_dict(read_json(path, "JSON scene"), str(path))

    # ---- evaluation ---------------------------------------------------------------------
    def arrays(self, device="cpu") -> dict:
        """Flat float32 arrays the kernels read: kinds [m], params [m, 4], rots [m, 3, 3]
        (world-to-local), centers [m, 3], ops [m], ks [m], colors [m, 3]."""
        if not self.primitives:
            raise ValueError("the scene has no primitives")
        key = str(device)
        cache = self.__dict__.setdefault("_arrays", {})
        sig = json.dumps(self.to_dict())
        if key not in cache or cache[key][0] != sig:
            P = self.primitives
            rots = torch.stack([rotation_from_euler_deg(*p.rotation_deg).T for p in P])
            out = {
                "kinds": torch.tensor([KINDS[p.kind] for p in P], dtype=torch.int32),
                "params": torch.tensor([p.params for p in P], dtype=torch.float32),
                "rots": rots.float().contiguous(),
                "centers": torch.tensor([p.center for p in P], dtype=torch.float32),
                "ops": torch.tensor([OPS[p.op] for p in P], dtype=torch.int32),
                "ks": torch.tensor([max(p.k, 1e-12) for p in P], dtype=torch.float32),
                "colors": torch.tensor([p.color for p in P], dtype=torch.float32),
            }
            cache[key] = (sig, {k: v.to(device) for k, v in out.items()})
        return cache[key][1]

    def sdf(self, points: torch.Tensor, return_ids: bool = False):
        """Signed distance at points [n, 3] (Warp kernel, float32); with ``return_ids`` also the
        deciding primitive per point [n]."""
        from ..ops.sphere_trace import scene_sdf

        d, ids = scene_sdf(points, self)
        return (d, ids) if return_ids else d

    def __len__(self):
        return len(self.primitives)


def torus_scene(major=0.7, minor=0.25) -> SDFScene:
    """The seed's torus (its ring tilted 30 degrees from the xz plane about x)."""
    return SDFScene().torus(major, minor, rotation_deg=(30, 0, 0), color=(0.9, 0.55, 0.2))


def many_primitives_scene(n_side: int = 5) -> SDFScene:
    """A ground plane and a grid of n_side^2 mixed objects (n_side = 5: 32 primitives): spheres,
    rounded boxes, tori, capsules, boxes with a sphere carved out, a smooth blend."""
    scene = SDFScene().plane(-0.5, color=(0.55, 0.55, 0.6))
    palette = [(0.9, 0.3, 0.25), (0.25, 0.6, 0.9), (0.95, 0.8, 0.25), (0.4, 0.8, 0.4)]
    spacing = 0.75
    for i in range(n_side):
        for j in range(n_side):
            x, y = (i - (n_side - 1) / 2) * spacing, (j - (n_side - 1) / 2) * spacing
            c = (x, y, -0.2)  # z up
            col = palette[(i + 2 * j) % 4]
            kind = (i + j) % 5
            if kind == 0:
                scene.sphere(0.28, center=c, color=col)
            elif kind == 1:
                scene.box((0.45, 0.5, 0.45), rounding=0.05, center=c, rotation_deg=(0, 20 * j, 0),
                          color=col)  # fmt: skip
            elif kind == 2:
                scene.torus(0.22, 0.07, center=c, rotation_deg=(60, 15 * i, 0), color=col)
            elif kind == 3:
                scene.capsule(0.35, 0.11, center=c, rotation_deg=(0, 0, 35), color=col)
            else:
                scene.box((0.5, 0.5, 0.5), center=c, color=col)
                scene.sphere(0.33, center=c, op="subtraction", color=(0.1, 0.1, 0.1))
    scene.sphere(0.2, center=(0.0, 0.0, 0.45), op="smooth_union", k=0.15, color=(0.9, 0.9, 0.9))
    return scene
