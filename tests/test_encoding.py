"""Hash-grid encoding (kernels/encoding.py via warpnerf.ops.encoding) against its float64 PyTorch
twin: forward values, table gradients with random upstream gradients, gradcheck, the level layout
(dense and hashed levels, power-of-two hashed sizes), hard cases (cube faces and corners, points
outside the cube, NaN/Inf positions, heavy hash collisions, many points), input validation; and
the hash NeRF field built on it (spherical harmonics, zero density outside its box)."""

from __future__ import annotations

import math

import pytest
import torch

from warpnerf.fields.encoding import SphericalHarmonics
from warpnerf.fields.hash_nerf import HashNeRFField
from warpnerf.ops.encoding import HashGrid, hash_encode
from warpnerf.reference.encoding import hash_encode as ref_hash_encode

from ._twin import assert_matches_twin, gradcheck_op

F32, F64 = torch.float32, torch.float64
GRIDS = {
    "dense+hashed": HashGrid(n_levels=4, n_features=2, log2_size=10, base_res=3, max_res=40),
    "one_level": HashGrid(n_levels=1, n_features=1, log2_size=8, base_res=5, max_res=5),
    "collisions": HashGrid(n_levels=3, n_features=4, log2_size=4, base_res=2, max_res=30),
}


def _points(n, dtype, device, hard=True):
    x = torch.rand(n, 3, dtype=F64)
    if hard:
        x[:8] = torch.tensor([[(v >> k) & 1 for k in range(3)] for v in range(8)], dtype=F64)
        x[8] = torch.tensor([0.5, 0.25, 1.0 / 3.0])  # on vertices / faces of several levels
        x[9] = torch.tensor([1.5, -0.25, 0.5])  # outside: clamped to the cube
        x[10] = torch.tensor([1e9, -1e9, 0.0])
    return x.to(device, dtype)


def _table(grid, dtype, device):
    return torch.randn(grid.n_rows, grid.n_features, dtype=F64).to(device, dtype)


@pytest.mark.parametrize("name", list(GRIDS))
@pytest.mark.parametrize("dtype", [F32, F64])
def test_forward_and_table_gradient_match_twin(device, name, dtype):
    grid = GRIDS[name]
    # float32: x * res and the fraction round (res <= 40); gradients: 10x the outputs'.
    tol = {F64: {"rtol": 1e-12, "atol": 1e-12}, F32: {"rtol": 2e-5, "atol": 2e-5}}
    grad_tol = {F64: {"rtol": 1e-11, "atol": 1e-11}, F32: {"rtol": 2e-4, "atol": 2e-4}}
    r = assert_matches_twin(
        lambda x, table: hash_encode(x, table, grid),
        lambda x, table: ref_hash_encode(x, table, grid),
        {"x": _points(600, dtype, device), "table": _table(grid, dtype, device)},
        grad=["table"],
        tol=tol,
        grad_tol=grad_tol,
        twin_dtype=F64,
    )
    assert r.out["out"].shape == (600, grid.out_dim) and r.out["out"].dtype == dtype


def test_gradcheck_float64(device):
    grid = GRIDS["collisions"]
    x = _points(12, F64, device)
    gradcheck_op(
        lambda table: hash_encode(x, table, grid),
        {"table": _table(grid, F64, device)},
        ["table"],
        eps=1e-6,
    )


@pytest.mark.parametrize("name", list(GRIDS))
@pytest.mark.parametrize("dtype", [F32, F64])
def test_position_gradient_matches_twin(device, name, dtype):
    """d features / d x (pose refinement) against the twin's autograd, with the table's gradient
    in the same backward: cell faces and corners (one-sided, the forward's cell), points outside
    the cube (zero along the clamped axes)."""
    grid = GRIDS[name]
    tol = {F64: {"rtol": 1e-12, "atol": 1e-12}, F32: {"rtol": 2e-5, "atol": 2e-5}}
    # d/dx scales by res (<= 40) and sums levels x corners x features: float32 rounds more
    grad_tol = {F64: {"rtol": 1e-10, "atol": 1e-10}, F32: {"rtol": 1e-3, "atol": 1e-3}}
    assert_matches_twin(
        lambda x, table: hash_encode(x, table, grid),
        lambda x, table: ref_hash_encode(x, table, grid),
        {"x": _points(600, dtype, device), "table": _table(grid, dtype, device)},
        grad=["x", "table"],
        tol=tol,
        grad_tol=grad_tol,
        twin_dtype=F64,
    )


@pytest.mark.parametrize("name", list(GRIDS))
@pytest.mark.parametrize("dtype", [F32, F64])
def test_centred_rows_match_twin(device, name, dtype):
    """``centred=True``: rows [2 x - 1, features] from the one kernel (an SDF network's input
    without a concatenation), values and the x and table gradients against the twin; the
    features are bit for bit the plain op's, the centred columns bit for bit 2 x - 1."""
    grid = GRIDS[name]
    tol = {F64: {"rtol": 1e-12, "atol": 1e-12}, F32: {"rtol": 2e-5, "atol": 2e-5}}
    grad_tol = {F64: {"rtol": 1e-10, "atol": 1e-10}, F32: {"rtol": 1e-3, "atol": 1e-3}}
    x, table = _points(600, dtype, device), _table(grid, dtype, device)
    r = assert_matches_twin(
        lambda x, table: hash_encode(x, table, grid, centred=True),
        lambda x, table: ref_hash_encode(x, table, grid, centred=True),
        {"x": x, "table": table},
        grad=["x", "table"],
        tol=tol,
        grad_tol=grad_tol,
        twin_dtype=F64,
    )
    out = r.out["out"]
    assert out.shape == (600, 3 + grid.out_dim)
    assert torch.equal(out[:, 3:], hash_encode(x, table, grid))
    assert torch.equal(out[:, :3], 2.0 * x - 1.0)


def test_centred_columns_keep_their_gradient_on_nonfinite_rows(device):
    """A NaN/Inf point: NaN features and no feature gradient, but its centred columns are
    2 x - 1 with gradient 2, as the twin's (and the concatenation's)."""
    grid = GRIDS["dense+hashed"]
    x = torch.tensor([[float("nan"), 0.5, 0.5], [float("inf"), 0.2, 0.3], [0.3, 0.4, 0.5]],
                     dtype=F64, device=device, requires_grad=True)  # fmt: skip
    out = hash_encode(x, _TABLE64.to(device), grid, centred=True)
    assert torch.isnan(out[:2, 3:]).all() and torch.isfinite(out[2]).all()
    v = torch.zeros_like(out)
    v[:, :3] = torch.tensor([1.0, -2.0, 0.5], dtype=F64)
    out.backward(v)
    assert torch.equal(x.grad[:2], 2.0 * v[:2, :3])
    xr = x.detach().clone().requires_grad_(True)
    ref_hash_encode(xr, _TABLE64.to(device), grid, centred=True).backward(v)
    assert torch.allclose(x.grad, xr.grad, rtol=1e-12, atol=1e-12)


def test_centred_gradcheck_float64(device):
    grid = GRIDS["collisions"]  # (a 64-row table: small enough for the numerical Jacobian)
    x = torch.rand(8, 3, dtype=F64, device=device) * 0.9 + 0.05
    gradcheck_op(
        lambda x, table: hash_encode(x, table, grid, centred=True),
        {"x": x, "table": _table(grid, F64, device)},
        ["x", "table"],
        eps=1e-7,
        atol=1e-5,
    )


def test_centred_input_gives_hash_sdf_the_same_network(device, monkeypatch):
    """hash_sdf's SDF network reads [2 u - 1, features] from the centred kernel within
    ``encoding_kernels(centred=True)``: the same values and gradients as the concatenation."""
    import warpnerf.ops.encoding as enc_ops
    from warpnerf.fields.hash_sdf import HashSDFField
    from warpnerf.ops.encoding import centred_input, encoding_kernels

    torch.manual_seed(0)
    field = HashSDFField([-1.5] * 3 + [1.5] * 3, HashGrid(n_levels=4, log2_size=10, max_res=32))
    field = field.to(device)
    with torch.no_grad():
        for lin in (m for m in field.sdf_mlp if isinstance(m, torch.nn.Linear)):
            lin.weight.add_(0.05 * torch.randn_like(lin.weight))
        field.encoding.table.normal_(0.0, 0.1)
    p = (torch.rand(3000, 3) * 3.4 - 1.7).to(device)  # (some outside the box)
    params = [*field.sdf_mlp.parameters(), field.encoding.table]
    calls = []  # (the centred kernel really ran under the switch, the plain one without it)
    real = enc_ops.hash_encode

    def spy(*a, **k):
        calls.append(k.get("centred"))
        return real(*a, **k)

    monkeypatch.setattr(enc_ops, "hash_encode", spy)
    d0, f0 = field._geometry(p)
    g0 = torch.autograd.grad(d0.sum() + f0.sum(), params)
    assert not centred_input() and calls == [False]
    with encoding_kernels(centred=True):
        assert centred_input()
        with encoding_kernels(pairs=False):  # (None: the other switch stays)
            assert centred_input()
        d1, f1 = field._geometry(p)
        g1 = torch.autograd.grad(d1.sum() + f1.sum(), params)
    assert not centred_input() and calls == [False, True]
    assert torch.equal(d0, d1) and torch.equal(f0, f1)
    for a, b in zip(g0, g1):
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-7)


def test_position_gradient_gradcheck_float64(device):
    grid = GRIDS["dense+hashed"]
    x = torch.rand(10, 3, dtype=F64, device=device) * 0.9 + 0.05
    gradcheck_op(
        lambda x: hash_encode(x, _TABLE64.to(device), grid), {"x": x}, ["x"], eps=1e-7, atol=1e-5
    )


_TABLE64 = torch.randn(GRIDS["dense+hashed"].n_rows, 2, dtype=F64)


def test_position_gradient_hard_cases(device):
    """Outside the cube: zero along the clamped axes, finite elsewhere; non-finite points: zero
    (their NaN features already make the loss NaN); many points on a tiny table: float32 against
    the float64 twin."""
    grid = GRIDS["collisions"]
    x = _points(40, F32, device)
    x[12] = torch.tensor([2.0, 0.3, -1.0])
    x[13, 1] = float("nan")
    x[14, 2] = float("inf")
    x = x.requires_grad_(True)
    table = _table(grid, F32, device)
    out = hash_encode(x, table, grid)
    v = torch.randn_like(out).nan_to_num(0.0)
    (g,) = torch.autograd.grad(out, x, v)
    assert torch.isfinite(g).all()
    assert g[12, 0] == 0 and g[12, 2] == 0 and g[12, 1] != 0
    assert (g[13] == 0).all() and (g[14] == 0).all()
    assert (g[9, :2] == 0).all() and (g[10, :2] == 0).all()  # (1.5, -0.25, .5), (1e9, -1e9, 0)
    big = HashGrid(n_levels=2, n_features=2, log2_size=6, base_res=2, max_res=16)
    xs = torch.rand(20_000, 3, dtype=F64, device=device)
    t64 = _table(big, F64, device)
    x32 = xs.float().requires_grad_(True)
    (g32,) = torch.autograd.grad(hash_encode(x32, t64.float(), big).sum(), x32)
    x64 = xs.clone().requires_grad_(True)
    (g64,) = torch.autograd.grad(ref_hash_encode(x64, t64, big).sum(), x64)
    assert ((g32.double() - g64).abs() / g64.abs().clamp_min(1.0)).max() < 1e-3


def test_partition_of_unity_and_exact_vertices(device):
    """A table of ones gives 1 per level (weights sum to one); at a vertex of a dense level the
    feature is that vertex's row exactly."""
    grid = HashGrid(n_levels=2, n_features=1, log2_size=12, base_res=4, max_res=8)
    x = _points(300, F64, device)
    ones = torch.ones(grid.n_rows, 1, dtype=F64, device=device)
    torch.testing.assert_close(
        hash_encode(x, ones, grid), torch.ones(300, 2, dtype=F64, device=device)
    )
    table = torch.arange(grid.n_rows, dtype=F64, device=device).unsqueeze(-1)
    v = torch.tensor([[1 / 4, 2 / 4, 3 / 4]], dtype=F64, device=device)  # vertex (1, 2, 3) of res 4
    assert hash_encode(v, table, grid)[0, 0].item() == 1 + 5 * (2 + 5 * 3)


def test_level_layout():
    grid = HashGrid(n_levels=16, log2_size=19, base_res=16, max_res=2048)
    res = [r for r, _, _ in grid.levels]
    assert res[0] == 16 and res[-1] == 2048 and res == sorted(res)
    offset = 0
    for r, first, rows in grid.levels:
        assert first == offset and rows % 8 == 0
        dense = (r + 1) ** 3 <= rows
        assert dense or rows == 2**19  # hashed levels: power of two (the kernel masks)
        offset += rows
    assert grid.n_rows == offset and grid.out_dim == 32


def test_nonfinite_positions_give_nan_rows_and_no_gradient(device):
    grid = GRIDS["dense+hashed"]
    x = _points(50, F32, device)
    x[3, 0], x[4, 1], x[5, 2] = float("nan"), float("inf"), -float("inf")
    table = _table(grid, F32, device).requires_grad_(True)
    out = hash_encode(x, table, grid)
    bad = torch.zeros(50, dtype=torch.bool, device=device)
    bad[3:6] = True
    assert torch.isnan(out[bad]).all() and torch.isfinite(out[~bad]).all()
    v_out = torch.ones_like(out)
    v_out[bad] = 0.0
    (g,) = torch.autograd.grad(out, table, v_out)
    assert torch.isfinite(g).all()


def test_many_points_accumulate_like_float64(device):
    """50k points on a tiny table: heavy atomic accumulation, float32 vs float64 twin."""
    grid = HashGrid(n_levels=2, n_features=2, log2_size=6, base_res=2, max_res=16)
    x = _points(50_000, F64, device, hard=False)
    table = _table(grid, F32, device).requires_grad_(True)
    out = hash_encode(x.float(), table, grid)
    (g,) = torch.autograd.grad(out, table, torch.ones_like(out))
    t64 = table.detach().double().requires_grad_(True)
    (g64,) = torch.autograd.grad(ref_hash_encode(x, t64, grid).sum(), t64)
    assert ((g.double() - g64).abs() / g64.abs().clamp_min(1.0)).max() < 1e-4


def test_validation(device):
    grid = GRIDS["one_level"]
    x = _points(5, F32, device, hard=False)
    with pytest.raises(ValueError, match="table must have shape"):
        hash_encode(x, torch.zeros(3, 1, device=device), grid)
    with pytest.raises(ValueError, match="dtype"):
        hash_encode(x, _table(grid, F64, device), grid)
    with pytest.raises(ValueError, match="x must have shape"):
        hash_encode(x[:, :2], _table(grid, F32, device), grid)
    with pytest.raises(TypeError):
        hash_encode(x, _table(grid, F32, device), (1, 2))
    with pytest.raises(ValueError):
        HashGrid(base_res=64, max_res=32)
    x.requires_grad_(True)  # positions may require a gradient (pose refinement), once only
    out = hash_encode(x, _table(grid, F32, device).requires_grad_(True), grid)
    (gx,) = torch.autograd.grad(out.sum(), x, create_graph=True)
    with pytest.raises(RuntimeError):
        torch.autograd.grad(gx.sum(), x)


def test_spherical_harmonics_orthonormal_and_known_values():
    d = torch.nn.functional.normalize(torch.randn(400_000, 3, dtype=F64), dim=-1)
    y = SphericalHarmonics(4)(d)
    gram = y.T @ y / d.shape[0] * 4 * math.pi
    assert (gram - torch.eye(16, dtype=F64)).abs().max() < 0.03
    z = SphericalHarmonics(2)(torch.tensor([[0.0, 0.0, 1.0]], dtype=F64))[0]
    torch.testing.assert_close(
        z, torch.tensor([0.28209479177387814, 0, 0.4886025119029199, 0], dtype=F64)
    )


def test_hash_field_zero_outside_box_and_finite_gradients(device):
    grid = HashGrid(n_levels=4, log2_size=10, base_res=4, max_res=32)
    field = HashNeRFField([-1, -1, -1, 1, 1, 1], grid, hidden=16).to(device)
    p = torch.randn(500, 3, device=device) * 1.2
    d = torch.nn.functional.normalize(torch.randn(500, 3, device=device), dim=-1)
    sigma, rgb = field(p, d)
    outside = (p.abs() > 1).any(-1)
    assert outside.any() and (sigma[outside] == 0).all() and (sigma[~outside] > 0).all()
    assert ((rgb > 0) & (rgb < 1)).all()
    (sigma.sum() + rgb.sum()).backward()
    assert all(torch.isfinite(q.grad).all() for q in field.parameters())
    assert field.encoding.table.grad.abs().sum() > 0


@pytest.mark.parametrize("n_features", [2, 4])
def test_paired_atomics_sum_as_single_atomics(device, n_features):
    """The float32 table gradient with two features per atomic (sm_90; one by one elsewhere)
    equals the one-atomic-per-feature kernel's: bitwise on the CPU, within float32 summation
    order on CUDA; points crowded onto a thin shell (many per cell, as a training step's)."""
    from warpnerf.ops.encoding import encoding_kernels

    grid = HashGrid(n_levels=6, n_features=n_features, log2_size=12, base_res=4, max_res=128)
    u = torch.nn.functional.normalize(torch.randn(20_000, 3), dim=-1)
    x = (0.5 + 0.3 * u).to(device)
    table = _table(grid, F32, device).requires_grad_()
    v = torch.randn(x.shape[0], grid.out_dim).to(device)
    v[::7] = 0.0  # rows of zero gradient (a fixed-capacity buffer's unused slots) add nothing
    grads = []
    for pairs in (True, False):
        with encoding_kernels(pairs=pairs):
            (g,) = torch.autograd.grad(hash_encode(x, table, grid), table, v)
        grads.append(g)
    if device.type == "cpu":
        assert torch.equal(grads[0], grads[1])
    else:
        torch.testing.assert_close(grads[0], grads[1], rtol=1e-4, atol=1e-4)  # (order of sums)


def test_given_features_carry_the_encodings_gradients(device):
    """hash_encode_given (a renderer's second pass reusing its first pass's features) returns
    those features and the same table and position gradients as hash_encode."""
    from warpnerf.ops.encoding import hash_encode_given

    grid = GRIDS["dense+hashed"]
    x = _points(500, F32, device).requires_grad_()
    table = _table(grid, F32, device).requires_grad_()
    v = torch.randn(500, grid.out_dim).to(device)
    out = hash_encode(x, table, grid)
    want = torch.autograd.grad(out, (x, table), v)
    with torch.no_grad():
        first = hash_encode(x, table, grid)
    again = hash_encode_given(x, table, grid, first)
    assert torch.equal(again.detach(), out.detach())
    got = torch.autograd.grad(again, (x, table), v)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)  # (CUDA: atomics order)
    with pytest.raises(ValueError, match="features"):
        hash_encode_given(x, table, grid, first[:10])


def test_fused_linear_relu_matches_the_modules(device):
    """The hash field's MLPs with Linear + ReLU fused in the matrix product's epilogue (CUDA
    only; the CPU runs the modules themselves) give the modules' outputs and gradients; the
    fused op's hand-written gradient passes gradcheck in float64."""
    from torch import nn

    from warpnerf.fields.mlp import _LinearReLU, run_mlp

    x = torch.randn(7, 5, dtype=F64, requires_grad=True)
    w = torch.randn(4, 5, dtype=F64, requires_grad=True)
    b = torch.randn(4, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(_LinearReLU.apply, (x, w, b))
    mlp = nn.Sequential(nn.Linear(32, 64), nn.ReLU(), nn.Linear(64, 64), nn.ReLU(),
                        nn.Linear(64, 3)).to(device)  # fmt: skip
    x = torch.randn(3000, 32, device=device, requires_grad=True)
    v = torch.randn(3000, 3, device=device)
    outs = []
    for fn in (run_mlp, lambda m, t: m(t)):
        y = fn(mlp, x)
        grads = torch.autograd.grad(y, (x, *mlp.parameters()), v)
        outs.append((y, *grads))
    for a, c in zip(*outs):
        torch.testing.assert_close(a, c, rtol=1e-5, atol=1e-5)
