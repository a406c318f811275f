"""Torch bridge for the multiresolution hash-grid encoding (kernels/encoding.py).

``hash_encode(x, table, grid)`` maps points x [n, 3] in [0, 1]^3 to features [n, L * F],
differentiable with respect to ``table`` (the learnable parameters) and, when they require it,
the positions ``x`` (pose refinement; a second kernel, launched only then).

``spherical_harmonics(d, degree)`` (pure torch, differentiable) encodes directions;
``sh_concat(features, d, degree)`` writes ``[features | SH(d)]`` in one kernel
(kernels/harmonics.py) for directions without a gradient (a colour MLP's input).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from functools import cached_property

import torch

from . import bridge

__all__ = [
    "HashGrid",
    "hash_encode",
    "hash_encode_given",
    "encoding_kernels",
    "spherical_harmonics",
    "sh_concat",
]


@dataclass(frozen=True)
class HashGrid:
    """Layout of a multiresolution hash grid: ``n_levels`` grids from ``base_res`` to ``max_res``
    cells per side (geometric progression, ``res_l = floor(base_res * b^l)``), each with at most
    ``2^log2_size`` rows of ``n_features`` features (dense indexing when a level fits)."""

    n_levels: int = 16
    n_features: int = 2
    log2_size: int = 19
    base_res: int = 16
    max_res: int = 2048

    def __post_init__(self):
        for name in ("n_levels", "n_features", "log2_size", "base_res", "max_res"):
            bridge.check_int(name, getattr(self, name), lo=-(2**62), hi=2**62)
        if not (1 <= self.n_levels <= 64 and 1 <= self.n_features <= 64):
            raise ValueError(
                f"n_levels and n_features must be in [1, 64], got {self.n_levels}, "
                f"{self.n_features}"
            )
        if not 4 <= self.log2_size <= 26:
            raise ValueError(f"log2_size must be in [4, 26], got {self.log2_size}")
        if not 1 <= self.base_res <= self.max_res <= 2**20:
            raise ValueError(
                f"need 1 <= base_res <= max_res <= 2^20, got {self.base_res}, {self.max_res}"
            )
        if self.n_rows * self.n_features > bridge.INT32_MAX:  # the kernels index rows in int32
            raise ValueError(
                f"the table would have {self.n_rows} rows x {self.n_features} features, more than "
                "int32 indices reach: use fewer levels or a smaller log2_size"
            )

    @cached_property
    def levels(self) -> tuple:
        """((res, first_row, rows), ...) per level."""
        growth = (
            math.exp((math.log(self.max_res) - math.log(self.base_res)) / (self.n_levels - 1))
            if self.n_levels > 1
            else 1.0
        )
        out, offset = [], 0
        for lvl in range(self.n_levels):
            res = max(1, int(math.floor(self.base_res * growth**lvl + 1e-9)))
            # dense when the level fits (rows rounded up to 8), else hashed into 2^log2_size rows
            # (a power of two: the kernel's modulo is a mask)
            rows = min(2**self.log2_size, ((res + 1) ** 3 + 7) // 8 * 8)
            out.append((res, offset, rows))
            offset += rows
        return tuple(out)

    @property
    def n_rows(self) -> int:
        res, offset, rows = self.levels[-1]
        return offset + rows

    @property
    def out_dim(self) -> int:
        return self.n_levels * self.n_features


_LEVELS: dict = {}  # (grid, device) -> the kernels' Levels (equal grids share one)


def _levels(grid: HashGrid, device: torch.device):
    """The kernels' ``Levels`` struct of ``grid`` on ``device``: per level its cells per side,
    first row, rows and whether it is indexed densely, int32 arrays [L] made once."""
    key = (grid, str(device))
    lv = _LEVELS.get(key)
    if lv is None:
        from warpnerf.kernels import encoding as K

        wp = bridge.load_warp()
        cols = [*zip(*grid.levels), [int((r + 1) ** 3 <= rows) for r, _, rows in grid.levels]]
        arrays = [wp.from_torch(torch.tensor(c, dtype=torch.int32, device=device)) for c in cols]
        lv = _LEVELS[key] = K.Levels()
        lv.res, lv.offsets, lv.sizes, lv.dense = arrays
    return lv


# The table's backward for float32 tables of an even number of features: "pairs" adds two
# features per atomic on sm_90 (kernels/encoding.py, add_corner; the same sums one by
# one elsewhere), False: one atomic per feature. Switched only through encoding_kernels().
_IMPL = {"pairs": True, "centred": False}


def centred_input() -> bool:
    """Whether an SDF network takes its input [2 u - 1, features] from one encoding kernel
    (``hash_encode(..., centred=True)``) instead of a concatenation after it (the A/B of issue
    47; the default until measured on a GPU: the concatenation)."""
    return _IMPL["centred"]


@contextlib.contextmanager
def encoding_kernels(pairs: bool | None = None, centred: bool | None = None):
    """Within the block the hash encoding's table gradient uses paired atomics (``pairs``: True,
    the default, or one atomic per feature) and SDF networks read the centred encoding
    (``centred``, :func:`centred_input`); None leaves a switch as it is; restored on exit
    (tests and benchmarks compare them)."""
    saved = dict(_IMPL)
    if pairs is not None:
        _IMPL["pairs"] = bool(pairs)
    if centred is not None:
        _IMPL["centred"] = bool(centred)
    try:
        yield
    finally:
        _IMPL.clear()
        _IMPL.update(saved)


def _encode_backward(ctx, v_out):
    """(v_x, v_table) of :class:`_HashEncode` and :class:`_HashEncodeGiven` (``ctx.col0``: the
    features' first column in ``v_out``, 3 after the centred positions)."""
    from warpnerf.kernels import encoding as K

    x, table = ctx.saved_tensors
    grid = ctx.grid
    lv = _levels(grid, x.device)
    a = bridge.arr
    v_out = v_out.contiguous()
    v_table = v_x = None
    if ctx.needs_input_grad[1]:
        v_table = torch.zeros(ctx.table_shape, device=x.device, dtype=x.dtype)
        pairs = _IMPL["pairs"] and x.dtype == torch.float32 and grid.n_features % 2 == 0
        bridge.launch(
            K.hash_encode_bwd,
            x.shape[0] * grid.n_levels,
            [a(x), a(v_out), lv, ctx.col0, int(pairs), a(v_table)],
            x.device,
        )
    if ctx.needs_input_grad[0]:
        v_x = torch.empty_like(x)
        bridge.launch(
            K.hash_encode_bwd_x,
            x.shape[0],
            [a(x), a(table), a(v_out), lv, ctx.col0, a(v_x)],
            x.device,
        )
    return v_x, v_table


class _HashEncode(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, table, grid, col0):
        from warpnerf.kernels import encoding as K

        out = torch.empty(x.shape[0], col0 + grid.out_dim, device=x.device, dtype=x.dtype)
        a = bridge.arr
        bridge.launch(
            K.hash_encode_fwd,
            x.shape[0] * grid.n_levels,
            [a(x), a(table), _levels(grid, x.device), col0, a(out)],
            x.device,
        )
        ctx.save_for_backward(x, table if ctx.needs_input_grad[0] else None)
        ctx.grid, ctx.table_shape, ctx.col0 = grid, table.shape, col0
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, v_out):
        return (*_encode_backward(ctx, v_out), None, None)


class _HashEncodeGiven(torch.autograd.Function):
    """:class:`_HashEncode` whose forward returns features already computed for these points
    (by the same kernel, without gradients); the backward is the same."""

    @staticmethod
    def forward(ctx, x, table, grid, features):
        ctx.save_for_backward(x, table if ctx.needs_input_grad[0] else None)
        ctx.grid, ctx.table_shape, ctx.col0 = grid, table.shape, 0
        return features.view_as(features)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, v_out):
        return (*_encode_backward(ctx, v_out), None, None)


def hash_encode_given(x: torch.Tensor, table: torch.Tensor, grid, features: torch.Tensor):
    """:func:`hash_encode` of ``x`` when its result is already known: ``features`` [n, L * F],
    computed by :func:`hash_encode` of the same points and table without gradients (a
    renderer's first pass over samples it evaluates again with gradients). Returns them with
    the encoding's gradient attached (the forward kernel does not run again)."""
    if not isinstance(grid, HashGrid):
        raise TypeError(f"grid must be a HashGrid, got {type(grid).__name__}")
    bridge.check_float("x", x, (None, 3))
    bridge.check_float(
        "table", table, (grid.n_rows, grid.n_features), dtype=x.dtype, device=x.device
    )
    bridge.check_float("features", features, (x.shape[0], grid.out_dim), x.dtype, x.device)
    return _HashEncodeGiven.apply(x.contiguous(), table.contiguous(), grid, features)


def hash_encode(
    x: torch.Tensor,  # [n, 3] points in [0, 1]^3 (clamped); NaN/Inf rows give NaN features
    table: torch.Tensor,  # [grid.n_rows, grid.n_features] learnable features
    grid: HashGrid,
    centred: bool = False,
) -> torch.Tensor:  # [n, grid.n_levels * grid.n_features], or [n, 3 + ...] when centred
    """Multiresolution hash-grid features of points (trilinear per level, levels concatenated).
    ``centred``: the rows start with the points' centred coordinates ``2 x - 1`` (of x as
    given, not clamped), what an SDF network reads beside the features: written by the same
    kernel, instead of a concatenation after it.

    Differentiable in ``table`` (hand-written scatter backward) and in ``x`` when it requires a
    gradient (hand-written, per point: the trilinear weights' derivatives; zero along an axis
    where x is outside [0, 1] and for non-finite points; plus 2 for the centred columns). Not
    twice differentiable.
    """
    if not isinstance(grid, HashGrid):
        raise TypeError(f"grid must be a HashGrid, got {type(grid).__name__}")
    bridge.check_float("x", x, (None, 3))
    bridge.check_float(
        "table", table, (grid.n_rows, grid.n_features), dtype=x.dtype, device=x.device
    )
    if x.shape[0] * grid.n_levels > bridge.INT32_MAX:  # one thread per (point, level)
        raise ValueError(
            f"{x.shape[0]} points x {grid.n_levels} levels exceed int32 thread indices: "
            "encode fewer points at once"
        )
    return _HashEncode.apply(x.contiguous(), table.contiguous(), grid, 3 if centred else 0)


def spherical_harmonics(d: torch.Tensor, degree: int = 4) -> torch.Tensor:
    """Real spherical harmonics of unit directions ``d`` [n, 3] up to ``degree`` (1..4):
    [n, degree^2] (the orthonormal basis, constants as in instant-ngp / tiny-cuda-nn). Pure
    torch (differentiable); shared by the fields and the twin of :func:`sh_concat`."""
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, 0.28209479177387814)]
    if degree > 1:
        out += [-0.48860251190291987 * y, 0.48860251190291987 * z, -0.48860251190291987 * x]
    if degree > 2:
        x2, y2, z2 = x * x, y * y, z * z
        out += [
            1.0925484305920792 * x * y,
            -1.0925484305920792 * y * z,
            0.94617469575755997 * z2 - 0.31539156525251999,
            -1.0925484305920792 * x * z,
            0.54627421529603959 * (x2 - y2),
        ]
    if degree > 3:
        out += [
            0.59004358992664352 * y * (3 * x2 - y2),
            2.8906114426405538 * x * y * z,
            0.45704579946446572 * y * (1 - 5 * z2),
            0.3731763325901154 * z * (5 * z2 - 3),
            0.45704579946446572 * x * (1 - 5 * z2),
            1.4453057213202769 * z * (x2 - y2),
            0.59004358992664352 * x * (x2 - 3 * y2),
        ]
    return torch.stack(out, -1)


class _ShConcat(torch.autograd.Function):
    @staticmethod
    def forward(ctx, features, directions, degree: int):
        from warpnerf.kernels import harmonics as K

        wp = bridge.load_warp()
        n, f = features.shape
        out = torch.empty(n, f + degree * degree, device=features.device, dtype=features.dtype)
        a = bridge.arr
        bridge.launch(K.sh_concat, n, [a(features), a(directions, wp.vec3), int(degree), a(out)],
                      features.device)  # fmt: skip
        ctx.f = f
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, v_out):
        return v_out[:, : ctx.f], None, None


def sh_concat(
    features: torch.Tensor,  # [n, F] float32
    directions: torch.Tensor,  # [n, 3] float32 unit directions, no gradient
    degree: int = 4,
) -> torch.Tensor:  # [n, F + degree^2]
    """``torch.cat([features, spherical_harmonics(directions, degree)], -1)`` in one kernel
    (a colour MLP's input); differentiable in ``features`` only. ValueError for directions that
    require a gradient (use :func:`spherical_harmonics`), other dtypes or shapes."""
    bridge.check_float("features", features, (None, None), torch.float32)
    n, dev = features.shape[0], features.device
    bridge.check_float("directions", directions, (n, 3), torch.float32, dev)
    degree = bridge.check_int("degree", degree, lo=1, hi=4)
    if directions.requires_grad:
        raise ValueError("sh_concat gives directions no gradient: use spherical_harmonics")
    return _ShConcat.apply(features.contiguous(), directions.contiguous(), degree)
