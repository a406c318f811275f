"""Integer inputs of the public ops (issue 15), the cases tests/test_index_checks.py leaves out:
packed layouts that are nearly right (swapped or shifted segments, an empty ray claiming a sample,
int64 values that would wrap to the right int32 ones or overflow an int64 sum), index tensors of
every dtype but int32/int64 on every op, float/bool sizes on every op, renderer and module that
takes one, rays whose march would not end, and fuzz of mutated valid layouts, of marching's
jitter/k_begin and of cell indices, each against an oracle written here. The cases that crash or
hang the old code run again in a child process, so a regression fails one test instead of killing
the run. The library's own layouts all pass the checks, and its renderers skip them."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import warpnerf
from warpnerf import reference
from warpnerf.fields.sdf_scene import torus_scene
from warpnerf.occupancy import OccupancyGrid
from warpnerf.ops import (
    HashGrid,
    generate_rays,
    importance_samples,
    packed_info_from_ray_indices,
    random_pixels,
    ray_aabb_intersect,
    render_packed,
    stratified_samples,
)
from warpnerf.ops import composite as C
from warpnerf.ops import occupancy as O
from warpnerf.ops.sampling import Samples
from warpnerf.ops.sphere_trace import sphere_trace
from warpnerf.reference import occupancy as R
from warpnerf.render import render_marched, render_nerf, render_rays

BOX = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]
I32_MAX = 2**31 - 1
FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
# values that wrap to small ones in a cast to int32, or overflow an int64 sum
EDGES = [I32_MAX, -(2**31), 2**31, 2**32, 2**32 + 1, 2**32 + 3, 2**62, 2**63 - 2, -(2**63)]


def _wrap32(values):
    """What a C cast to int32 makes of each value (int32 tensors cannot hold the others)."""
    return [(v + 2**31) % 2**32 - 2**31 for v in values]


def _layout(counts, device="cpu"):
    """Packed samples, ``counts[r]`` on ray r, t increasing along each ray: t_starts, t_ends,
    ray_indices [n] int64, sigmas [n], rgbs [n, 3] and the exact packed_info [n_rays, 2] int64."""
    c = torch.tensor(counts, dtype=torch.int64)
    ri = torch.repeat_interleave(torch.arange(len(counts)), c)
    n = ri.shape[0]
    g = torch.Generator().manual_seed(n)
    ts = torch.arange(n, dtype=torch.float32) * 0.1
    sig = torch.rand(n, generator=g) * 4
    rgb = torch.rand(n, 3, generator=g)
    info = torch.stack([torch.cumsum(c, 0) - c, c], -1)
    return tuple(x.to(device) for x in (ts, ts + 0.1, ri, sig, rgb, info))


def _cams(n=2):
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, 2, 3] = 3.0
    return c2w, torch.tensor([[20.0, 20.0, 8.0, 8.0]]).repeat(n, 1)


def _march_inputs(n=3, device="cpu"):
    """Rays along +z through the box (t in [2, 4]), and a res-4 grid with every cell occupied."""
    o = torch.tensor([[0.1, 0.2, -3.0]], device=device).repeat(n, 1)
    d = torch.tensor([[0.0, 0.0, 1.0]], device=device).repeat(n, 1)
    return o, d, torch.full((8,), 255, dtype=torch.uint8, device=device)


class _Ball(torch.nn.Module):
    """Density 30 in a ball of radius 0.5, colour from position: ``density``/``color`` for
    render_marched, ``forward`` (sigmas, rgbs) for render_nerf and render_rays."""

    def __init__(self):
        super().__init__()
        self.scale = torch.nn.Parameter(torch.tensor(1.0))

    def density(self, x):
        return self.scale * 30.0 * (x.norm(dim=-1) < 0.5).to(x.dtype), x

    def color(self, h, d):
        return torch.sigmoid(h * 3 + self.scale)

    def forward(self, x, d):
        sig, h = self.density(x)
        return sig, self.color(h, d)


# ------------------------------------------------------------------------------------------------
# packed layouts that are nearly right: render_packed and live_samples share the check

# (counts per ray, packed_info edits (row, col, value), ray_indices edits (pos, value), words)
LAYOUTS = {
    "swapped segments": ([3, 0, 2, 4], [(0, 0, 5), (0, 1, 4), (3, 0, 0), (3, 1, 3)], [],
                         "does not match"),
    "shifted boundary": ([3, 0, 2, 4], [(0, 1, 2), (2, 0, 2), (2, 1, 3)], [], "does not match"),
    "empty ray claims a sample": ([3, 0, 2, 4], [(1, 1, 1), (2, 0, 4), (2, 1, 1)], [],
                                  "does not match"),
    "no counts at all": ([3, 0, 2, 4], [(r, 1, 0) for r in range(4)], [], "does not match"),
    "negative count balanced": ([3, 0, 2, 4], [(1, 1, -1), (3, 1, 5)], [], "negative"),
    "start wrapping to the int32 one": ([3, 0, 2, 4], [(2, 0, 2**32 + 3)], [], "past the end"),
    "count wrapping to the int32 one": ([3, 0, 2, 4], [(3, 1, 2**32 + 4)], [], "past the end"),
    "start + count wrapping int64": ([3], [(0, 0, 2**63 - 2)], [], "past the end"),
    "count with no samples": ([0, 0], [(0, 1, 1)], [], "past the end"),
    "ray index of the next ray": ([3, 0, 2, 4], [], [(2, 1)], "does not match"),
    "ray index wrapping to the int32 one": ([3, 0, 2, 4], [], [(8, 2**32 + 3)], "ray_indices"),
}  # fmt: skip


@pytest.mark.parametrize("op", ["render_packed", "live_samples"])
@pytest.mark.parametrize("case", list(LAYOUTS))
def test_nearly_right_layouts_are_refused(device, case, op):
    counts, info_edits, ri_edits, words = LAYOUTS[case]
    ts, te, ri, sig, rgb, info = _layout(counts, device)
    for row, col, v in info_edits:
        info[row, col] = v
    for pos, v in ri_edits:
        ri[pos] = v
    tried = 0
    for dtype in (torch.int32, torch.int64):  # int32 too where the values fit
        values = info.reshape(-1).tolist() + ri.tolist()
        if dtype == torch.int32 and any(not -(2**31) <= v <= I32_MAX for v in values):
            continue
        tried += 1
        r, i = ri.to(dtype), info.to(dtype)
        with pytest.raises(ValueError, match=words):
            if op == "render_packed":
                render_packed(ts, te, r, sig, rgb, len(counts), packed_info=i)
            else:
                O.live_samples(Samples(ts, te, r, i), sig, 0.5)
    assert tried


# ------------------------------------------------------------------------------------------------
# index tensors of other dtypes, on every op that takes one


def _x():
    ts, te, ri, sig, rgb, info = _layout([2, 0, 1])
    o, d, bits = _march_inputs(2)
    smp = stratified_samples(torch.zeros(2), torch.ones(2), 2, packed=True)
    c2w, k = _cams(2)
    return SimpleNamespace(
        ts=ts, te=te, ri=ri, sig=sig, rgb=rgb, info=info, o=o, d=d, bits=bits, smp=smp,
        w=torch.ones(4), c2w=c2w, k=k, px=torch.full((2,), 1.0), cells=torch.tensor([0, 5]),
    )  # fmt: skip


def _march(x, **kw):
    return O.march_rays(x.o, x.d, 0.0, 6.0, x.bits, 4, BOX, 0.1, **kw)


def _importance(x, info=None, ri=None):
    s = x.smp
    s = Samples(s.t_starts, s.t_ends, s.ray_indices if ri is None else ri,
                s.packed_info if info is None else info)  # fmt: skip
    return importance_samples(s, x.w, 2)


DTYPES = {  # name: (argument named in the error, call)
    "render_packed ray_indices f16": ("ray_indices", lambda x: render_packed(
        x.ts, x.te, x.ri.half(), x.sig, x.rgb, 3)),
    "render_packed ray_indices bool": ("ray_indices", lambda x: render_packed(
        x.ts, x.te, x.ri.bool(), x.sig, x.rgb, 3, packed_info=x.info)),
    "render_packed ray_indices uint8": ("ray_indices", lambda x: render_packed(
        x.ts, x.te, x.ri.to(torch.uint8), x.sig, x.rgb, 3, packed_info=x.info)),
    "render_packed packed_info f64": ("packed_info", lambda x: render_packed(
        x.ts, x.te, x.ri, x.sig, x.rgb, 3, packed_info=x.info.double())),
    "render_packed packed_info int16": ("packed_info", lambda x: render_packed(
        x.ts, x.te, x.ri, x.sig, x.rgb, 3, packed_info=x.info.short())),
    "render_packed n_rays bool": ("n_rays", lambda x: render_packed(
        x.ts, x.te, x.ri, x.sig, x.rgb, True)),
    "render_packed n_rays numpy float": ("n_rays", lambda x: render_packed(
        x.ts, x.te, x.ri, x.sig, x.rgb, np.float64(3))),
    "packed_info_from_ray_indices bool": ("ray_indices", lambda x: packed_info_from_ray_indices(
        x.ri.bool(), 3)),
    "packed_info_from_ray_indices n_rays": ("n_rays", lambda x: packed_info_from_ray_indices(
        x.ri, 3.0)),
    "live_samples packed_info f32": ("packed_info", lambda x: O.live_samples(
        Samples(x.ts, x.te, x.ri, x.info.float()), x.sig, 0.5)),
    "live_samples ray_indices f32": ("ray_indices", lambda x: O.live_samples(
        Samples(x.ts, x.te, x.ri.float(), x.info), x.sig, 0.5)),
    "grid_cell_points cells int16": ("cells", lambda x: O.grid_cell_points(
        x.cells.short(), torch.rand(2, 3), 4, BOX)),
    "grid_cell_points cells bool": ("cells", lambda x: O.grid_cell_points(
        x.cells.bool(), torch.rand(2, 3), 4, BOX)),
    "grid_ema_update cells f32": ("cells", lambda x: O.grid_ema_update(
        torch.zeros(64), x.cells.float(), torch.ones(2), 0.5)),
    "march_rays k_begin f64": ("k_begin", lambda x: _march(x, k_begin=torch.zeros(2).double())),
    "march_rays k_begin bool": ("k_begin", lambda x: _march(
        x, k_begin=torch.zeros(2, dtype=torch.bool))),
    "generate_rays cam_idx bool": ("cam_idx", lambda x: generate_rays(
        x.c2w, x.k, cam_idx=torch.tensor([True, False]), px=x.px, py=x.px)),
    "generate_rays cam_idx f16": ("cam_idx", lambda x: generate_rays(
        x.c2w, x.k, cam_idx=torch.tensor([0.0, 1.0]).half(), px=x.px, py=x.px)),
    "importance_samples packed_info f64": ("packed_info", lambda x: _importance(
        x, info=x.smp.packed_info.double())),
    "importance_samples ray_indices f32": ("ray_indices", lambda x: _importance(
        x, ri=x.smp.ray_indices.float())),
}  # fmt: skip


@pytest.mark.parametrize("case", list(DTYPES))
def test_index_tensors_of_other_dtypes_are_refused(case):
    arg, call = DTYPES[case]
    with pytest.raises((TypeError, ValueError)) as e:
        call(_x())
    err = e.value  # IndexDtypeError: a TypeError and a ValueError, naming the argument
    assert type(err).__name__ == "IndexDtypeError", repr(err)
    assert isinstance(err, TypeError) and isinstance(err, ValueError)
    assert arg in str(err)


# ------------------------------------------------------------------------------------------------
# float and bool sizes, on every op, renderer and module that takes one


def _r():
    o = torch.tensor([[0.0, 0.0, -3.0], [0.2, 0.1, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    ball = _Ball()
    grid = OccupancyGrid(BOX, 4, dt=0.1, warmup=1)
    return SimpleNamespace(o=o, d=d, ball=ball, grid=grid)


def _marched(r, **kw):
    return render_marched(r.grid, r.ball, r.o, r.d, 0.0, 6.0, **kw)


SIZES = {  # name: (argument named in the error, call)
    "random_pixels width float": ("width", lambda r: random_pixels(1, 4.0, 4, 8)),
    "random_pixels n_cams bool": ("n_cams", lambda r: random_pixels(True, 4, 4, 8)),
    "random_pixels height 0": ("height", lambda r: random_pixels(1, 4, 0, 8)),
    "generate_rays width numpy float": ("width", lambda r: generate_rays(
        *_cams(1), np.float32(4), 4)),
    "stratified n_samples bool": ("n_samples", lambda r: stratified_samples(
        torch.zeros(2), torch.ones(2), True)),
    "stratified n_samples numpy float": ("n_samples", lambda r: stratified_samples(
        torch.zeros(2), torch.ones(2), np.float64(2.0))),
    "importance n_fine float": ("n_fine", lambda r: importance_samples(
        stratified_samples(torch.zeros(2), torch.ones(2), 2), torch.ones(2, 2), 2.0)),
    "march_rays max_samples float": ("max_samples", lambda r: O.march_rays(
        *_march_inputs(2)[:2], 0.0, 6.0, _march_inputs()[2], 4, BOX, 0.1, max_samples=2.0)),
    "march_rays max_samples bool": ("max_samples", lambda r: O.march_rays(
        *_march_inputs(2)[:2], 0.0, 6.0, _march_inputs()[2], 4, BOX, 0.1, max_samples=True)),
    "HashGrid n_levels float": ("n_levels", lambda r: HashGrid(n_levels=2.0)),
    "HashGrid n_features bool": ("n_features", lambda r: HashGrid(n_features=True)),
    "HashGrid log2_size float": ("log2_size", lambda r: HashGrid(log2_size=12.0)),
    "HashGrid base_res float": ("base_res", lambda r: HashGrid(base_res=16.0)),
    "HashGrid n_levels 65": ("n_levels", lambda r: HashGrid(n_levels=65)),
    "HashGrid table past int32": ("int32", lambda r: HashGrid(
        n_levels=16, n_features=8, log2_size=26)),
    "sphere_trace max_iters float": ("max_iters", lambda r: sphere_trace(
        r.o, r.d, torus_scene(), max_iters=2.5)),
    "sphere_trace max_iters bool": ("max_iters", lambda r: sphere_trace(
        r.o, r.d, torus_scene(), max_iters=True)),
    "render_rays chunk float": ("chunk", lambda r: render_rays(
        r.o, r.d, 0.0, 6.0, r.ball, n_samples=4, chunk=2.5)),
    "render_rays chunk 0": ("chunk", lambda r: render_rays(
        r.o, r.d, 0.0, 6.0, r.ball, n_samples=4, chunk=0)),
    "render_nerf chunk bool": ("chunk", lambda r: render_nerf(
        r.ball, r.o, r.d, 0.0, 6.0, n_coarse=4, chunk=True)),
    "render_nerf n_fine float": ("n_fine", lambda r: render_nerf(
        r.ball, r.o, r.d, 0.0, 6.0, fine=r.ball, n_coarse=4, n_fine=1.5)),
    "render_marched max_samples float": ("max_samples", lambda r: _marched(r, max_samples=2.0)),
    "render_marched round_samples -1": ("round_samples", lambda r: _marched(r, round_samples=-1)),
    "render_marched sample_budget float": ("sample_budget", lambda r: _marched(
        r, sample_budget=0.5)),
    "OccupancyGrid warmup float": ("warmup", lambda r: OccupancyGrid(BOX, 4, dt=0.1, warmup=1.5)),
    "OccupancyGrid warmup bool": ("warmup", lambda r: OccupancyGrid(BOX, 4, dt=0.1, warmup=True)),
    "OccupancyGrid update chunk 0": ("chunk", lambda r: r.grid.update(
        lambda p: r.ball.density(p)[0], chunk=0)),
    "OccupancyGrid update chunk float": ("chunk", lambda r: r.grid.update(
        lambda p: r.ball.density(p)[0], chunk=2.0)),
    "render_packed n_rays -1": ("n_rays", lambda r: render_packed(
        *_layout([])[:5], -1)),
    "packed_info_from_ray_indices n_rays -1": ("n_rays", lambda r: packed_info_from_ray_indices(
        torch.zeros(0, dtype=torch.int64), -1)),
}  # fmt: skip


@pytest.mark.parametrize("case", list(SIZES))
def test_sizes_must_be_ints(case):
    arg, call = SIZES[case]
    with pytest.raises(ValueError, match=arg):
        call(_r())


def test_integer_like_sizes_are_accepted():
    """NumPy ints and 0-dim integer tensors are ints (operator.index): same results as ints."""
    near, far = torch.zeros(3), torch.ones(3)
    for a, b in zip(stratified_samples(near, far, np.int64(3), packed=True),
                    stratified_samples(near, far, 3, packed=True)):  # fmt: skip
        assert torch.equal(a, b)
    c2w, k = _cams(1)
    for a, b in zip(generate_rays(c2w, k, np.int32(4), torch.tensor(3)),
                    generate_rays(c2w, k, 4, 3)):  # fmt: skip
        assert torch.equal(a, b)
    px = [random_pixels(np.int64(2), 4, 4, torch.tensor(5), torch.Generator().manual_seed(1)),
          random_pixels(2, 4, 4, 5, torch.Generator().manual_seed(1))]  # fmt: skip
    for a, b in zip(*px):
        assert torch.equal(a, b)
    grid = OccupancyGrid(BOX, 4, dt=0.1, warmup=np.int64(2))
    assert grid.warmup == 2 and type(grid.warmup) is int
    assert HashGrid(n_levels=np.int64(4)).n_levels == 4


# ------------------------------------------------------------------------------------------------
# boxes


def test_box_with_a_nan_max_or_nan_t_min_is_refused_and_a_flat_box_still_hits():
    o = torch.tensor([[0.0, 0.0, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]])
    for box in ([-1.0, -1, -1, 1, 1, float("nan")], [-float("inf"), -1, -1, 1, 1, 1]):
        with pytest.raises(ValueError, match="aabb"):
            ray_aabb_intersect(o, d, box)
        with pytest.raises(ValueError, match="aabb"):
            ray_aabb_intersect(o.double(), d.double(), torch.tensor(box))
    for t_min in (np.float32("nan"), torch.tensor(float("nan"))):
        with pytest.raises(ValueError, match="t_min"):
            ray_aabb_intersect(o, d, BOX, t_min=t_min)
    t0, t1, hit = ray_aabb_intersect(o, d, [-1.0, -1, 0, 1, 1, 0])  # flat: the plane z = 0
    assert bool(hit[0]) and float(t0[0]) == float(t1[0]) == 3.0


# ------------------------------------------------------------------------------------------------
# marching: rays whose lattice would not end, bad jitter and k_begin


def _bad_ray(case):
    o, d, bits = _march_inputs(3)
    kw = {}
    if case == "tiny direction":
        d[1] = torch.tensor([0.0, 0.0, 1e-30])
    elif case == "subnormal direction":
        d[1] = torch.tensor([0.0, 0.0, 1e-45])
    elif case == "tiny direction, empty grid":
        d[1] = torch.tensor([0.0, 0.0, 1e-30])
        bits = torch.zeros_like(bits)
    elif case == "float64 jitter rounding to 1":  # in [0, 1), but 1.0 in float32
        kw["jitter"] = torch.tensor([0.5, 1 - 1e-12, 0.5], dtype=torch.float64)
    elif case.endswith("jitter"):
        v = {"NaN jitter": float("nan"), "negative jitter": -1e-7, "unit jitter": 1.0}[case]
        kw["jitter"] = torch.tensor([0.5, v, 0.5])
    else:
        v, dtype = {
            "k_begin 2^31": (2**31, torch.int64),
            "k_begin -2^40": (-(2**40), torch.int64),
            "k_begin int32 min": (-(2**31), torch.int32),
        }[case]
        kw["k_begin"] = torch.tensor([0, v, 0], dtype=dtype)
    return (o, d, 0.0, float("inf"), bits, 4, BOX, 0.01), kw  # far: the box's exit


BAD_RAYS = {
    "tiny direction": "lattice steps",
    "subnormal direction": "lattice steps",
    "tiny direction, empty grid": "lattice steps",
    "NaN jitter": "jitter",
    "negative jitter": "jitter",
    "unit jitter": "jitter",
    "float64 jitter rounding to 1": "jitter",
    "k_begin 2^31": "k_begin",
    "k_begin -2^40": "k_begin",
    "k_begin int32 min": "k_begin",
}


@pytest.mark.parametrize("case", list(BAD_RAYS))
def test_march_rays_refuses_a_bad_ray_among_good_ones(case):
    args, kw = _bad_ray(case)
    with pytest.raises(ValueError, match=BAD_RAYS[case]):
        O.march_rays(*args, **kw)


def test_march_rays_accepts_the_edges_of_jitter_and_k_begin():
    """jitter 0 and the float32 just below 1, k_begin -1 (done) and 2^31 - 1 (past every ray's
    end) are valid: the same samples as the brute-force twin."""
    o, d, bits = _march_inputs(4)
    jit = torch.tensor([0.0, float(np.nextafter(np.float32(1), np.float32(0))), 0.0, 0.5])
    for dtype in (torch.int32, torch.int64):
        kb = torch.tensor([0, 3, -1, I32_MAX], dtype=dtype)
        args = (o, d, 0.0, 6.0, bits, 4, BOX, 0.05)
        s, k = O.march_rays(*args, jitter=jit, k_begin=kb)
        sr, kr = R.march_rays(*args, jitter=jit, k_begin=kb)
        assert s.packed_info[:, 1].tolist() == [40, 36, 0, 0]  # k in [3, 38]
        assert torch.equal(s.packed_info, sr.packed_info) and torch.equal(k, kr)
        torch.testing.assert_close(s.t_starts, sr.t_starts, rtol=0, atol=2e-6)


# ------------------------------------------------------------------------------------------------
# the cases that crash or hang the old code, in a child process

CHILD = textwrap.dedent(
    """
    import json, os, torch
    import warpnerf
    from warpnerf.ops import render_packed
    from warpnerf.ops import occupancy as O
    from warpnerf.ops.sampling import Samples

    BOX, inf = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], float("inf")
    ts = torch.arange(6, dtype=torch.float32) * 0.1
    ri = torch.tensor([0, 0, 0, 1, 1, 1], dtype=torch.int32)
    far_away = torch.tensor([[0, 3], [2**30, 3]], dtype=torch.int32)
    o = torch.tensor([[0.1, 0.2, -3.0]] * 2)
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1e-30]])
    full, empty = torch.full((8,), 255, dtype=torch.uint8), torch.zeros(8, dtype=torch.uint8)
    cases = {
        "render_packed start 2^30": lambda: render_packed(
            ts, ts + 0.1, ri, torch.ones(6), torch.ones(6, 3), 2, packed_info=far_away),
        "live_samples start 2^30": lambda: O.live_samples(
            Samples(ts, ts + 0.1, ri, far_away), torch.ones(6), 0.5),
        "grid_ema_update cell 2^30": lambda: O.grid_ema_update(
            torch.zeros(64), torch.tensor([2**30], dtype=torch.int32), torch.ones(1), 0.5),
        "march_rays dt 1e-12": lambda: O.march_rays(o[:1], d[:1], 0.0, inf, full, 4, BOX, 1e-12,
                                                    max_samples=2**24),
        "march_rays tiny direction": lambda: O.march_rays(o, d, 0.0, inf, full, 4, BOX, 0.01,
                                                          max_samples=2**24),
        "march_rays tiny direction, empty grid": lambda: O.march_rays(o, d, 0.0, inf, empty, 4,
                                                                      BOX, 0.01),
    }
    assert warpnerf.__file__.startswith(os.getcwd()), warpnerf.__file__
    for name, call in cases.items():
        try:
            call()
            got = "accepted"
        except Exception as e:
            got = type(e).__name__ + ": " + str(e)
        print(json.dumps([name, got]), flush=True)
    """
)


def test_crash_prone_cases_are_refused_in_a_child_process():
    """Out-of-bounds reads and writes and endless marches are refused with a ValueError, never a
    crash or a hang (the child runs in the folder of the warpnerf this test imported, and imports
    that one)."""
    root = Path(warpnerf.__file__).resolve().parents[1]
    try:
        p = subprocess.run([sys.executable, "-c", CHILD], cwd=root, capture_output=True,
                           text=True, timeout=240)  # fmt: skip
    except subprocess.TimeoutExpired as e:
        pytest.fail(f"the child hung; it had printed:\n{e.stdout}")
    got = dict(json.loads(line) for line in p.stdout.splitlines() if line.startswith("["))
    assert p.returncode == 0, f"exit {p.returncode}; results so far {got}\n{p.stderr[-2000:]}"
    assert len(got) == 6 and all(v.startswith("ValueError") for v in got.values()), got


# ------------------------------------------------------------------------------------------------
# property-based: works with the right result, or a ValueError; never a crash


def _layout_ok(ri: list, info: list, n_rays: int) -> bool:
    """The oracle: ray_indices sorted in [0, n_rays), every ray's count its number of samples,
    a ray with samples starting at its first one, an empty ray's start anywhere in [0, n]."""
    if ri != sorted(ri) or any(not 0 <= r < n_rays for r in ri):
        return False
    for ray, (start, count) in enumerate(info):
        mine = [i for i, r in enumerate(ri) if r == ray]
        if count != len(mine) or (mine and start != mine[0]) or not 0 <= start <= len(ri):
            return False
    return True


_VALUE = st.integers(-2, 12) | st.sampled_from(EDGES)


@FUZZ
@given(
    counts=st.lists(st.integers(0, 3), min_size=1, max_size=5),
    edits=st.lists(st.tuples(st.integers(0, 4), st.integers(0, 1), _VALUE), max_size=3),
    ri_edit=st.none() | st.tuples(st.integers(0, 14), st.integers(-1, 5) | st.sampled_from(EDGES)),
    int32=st.booleans(),
)
def test_fuzz_nearly_right_layouts(counts, edits, ri_edit, int32):
    """Mutations of a valid layout through render_packed and live_samples: both accept exactly
    the layouts the oracle accepts, and then give what the exact layout gives."""
    ts, te, ri, sig, rgb, info = _layout(counts)
    n_rays, n = len(counts), ri.shape[0]
    for row, col, v in edits:
        info[row % n_rays, col] = v
    if ri_edit is not None and n:
        ri[ri_edit[0] % n] = ri_edit[1]
    if int32:
        info = torch.tensor(_wrap32(info.reshape(-1).tolist()), dtype=torch.int32).reshape(-1, 2)
        ri = torch.tensor(_wrap32(ri.tolist()), dtype=torch.int32)
    ok = _layout_ok(ri.tolist(), info.tolist(), n_rays)
    got = []
    for call in (
        lambda: render_packed(ts, te, ri, sig, rgb, n_rays, packed_info=info),
        lambda: O.live_samples(Samples(ts, te, ri, info), sig, 0.3),
    ):
        try:
            got.append(call())
        except ValueError:
            got.append(None)
    assert (got[0] is not None) == ok == (got[1] is not None), (ri.tolist(), info.tolist())
    if ok:
        exact = packed_info_from_ray_indices(ri, n_rays)
        for a, b in zip(got[0], render_packed(ts, te, ri, sig, rgb, n_rays, packed_info=exact)):
            assert torch.equal(a, b) and bool(torch.isfinite(a).all())
        for a, b in zip(got[1], O.live_samples(Samples(ts, te, ri, exact), sig, 0.3)):
            assert torch.equal(a, b)


@FUZZ
@given(
    jit=st.none() | st.lists(st.floats(width=32) | st.sampled_from([1.0, -0.0, 0.99999994]),
                             min_size=3, max_size=3),
    kb=st.none() | st.lists(st.integers(-3, 44) | st.sampled_from(EDGES), min_size=3, max_size=3),
    int32=st.booleans(),
    seed=st.integers(0, 3),
)  # fmt: skip
def test_fuzz_march_rays_jitter_and_k_begin(jit, kb, int32, seed):
    """Accepted iff jitter lies in [0, 1) and k_begin in [-1, 2^31); then the brute-force twin's
    samples, in a layout the checks accept."""
    o, d, _ = _march_inputs(3)
    bits = O.grid_pack_bits(torch.rand(64, generator=torch.Generator().manual_seed(seed)), 0.4)
    jitter = None if jit is None else torch.tensor(jit, dtype=torch.float32)
    k_begin = None
    if kb is not None:
        dtype = torch.int32 if int32 else torch.int64
        k_begin = torch.tensor(_wrap32(kb) if int32 else kb, dtype=dtype)
    ok = jitter is None or all(0 <= j < 1 for j in jitter.tolist())
    ok &= k_begin is None or all(-1 <= k <= I32_MAX for k in k_begin.tolist())
    args = (o, d, 0.0, 6.0, bits, 4, BOX, 0.05)
    try:
        s, k = O.march_rays(*args, jitter=jitter, k_begin=k_begin, max_samples=64)
    except ValueError:
        assert not ok
        return
    assert ok
    sr, kr = R.march_rays(*args, jitter=jitter, k_begin=k_begin, max_samples=64)
    assert torch.equal(s.packed_info, sr.packed_info) and torch.equal(k, kr)
    torch.testing.assert_close(s.t_starts, sr.t_starts, rtol=0, atol=2e-6)
    assert bool(((s.t_starts >= 2.0 - 1e-5) & (s.t_ends <= 4.0 + 1e-5)).all())
    O.live_samples(s, torch.ones_like(s.t_starts), 0.5)  # check=True: the layout is exact


@FUZZ
@given(
    cells=st.lists(st.integers(-2, 65) | st.sampled_from(EDGES), max_size=8),
    int32=st.booleans(),
    decay=st.floats(0.0, 1.0),
)
def test_fuzz_cells_against_the_twins(cells, int32, decay):
    """grid_cell_points and grid_ema_update accept exactly the cells in [0, res^3), int32 or
    int64 (no value wrapped into range), and then equal their twins; a refused update has
    written nothing."""
    idx = torch.tensor(_wrap32(cells) if int32 else cells, dtype=torch.int64)
    idx = idx.to(torch.int32) if int32 else idx
    ok = all(0 <= c < 64 for c in idx.tolist())
    m = idx.shape[0]
    g = torch.Generator().manual_seed(m)
    jit, vals = torch.rand(m, 3, generator=g), torch.rand(m, generator=g) * 5
    density = torch.rand(64, generator=g)
    try:
        pts = O.grid_cell_points(idx, jit, 4, BOX)
    except ValueError:
        assert not ok
    else:
        assert ok
        torch.testing.assert_close(pts, R.grid_cell_points(idx, jit, 4, BOX))
    out = density.clone()
    try:
        O.grid_ema_update(out, idx, vals, decay)
    except ValueError:
        assert not ok and torch.equal(out, density)
    else:
        assert ok
        torch.testing.assert_close(out, R.grid_ema_update(density.clone(), idx, vals, decay))


@FUZZ
@given(
    ri=st.lists(st.integers(-1, 5) | st.sampled_from(EDGES), max_size=8),
    n_rays=st.integers(-1, 5) | st.sampled_from([2.0, True, np.float32(3)]),
    dtype=st.sampled_from([torch.int32, torch.int64, torch.float32, torch.bool]),
    presort=st.booleans(),
)
def test_fuzz_packed_info_from_ray_indices(ri, n_rays, dtype, presort):
    """Accepted iff int32/int64 indices, sorted in [0, n_rays), and an int n_rays >= 0; then the
    bincount layout. Float or bool indices or n_rays are IndexDtypeErrors (ValueErrors too)."""
    vals = sorted(ri) if presort else ri
    vals = _wrap32(vals) if dtype == torch.int32 else vals
    if dtype in (torch.float32, torch.bool):
        vals = [v for v in vals if -5 <= v <= 5]  # exact in float32
    t = torch.tensor(vals, dtype=dtype)
    ok = dtype in (torch.int32, torch.int64) and type(n_rays) is int and n_rays >= 0
    ok = ok and vals == sorted(vals) and all(0 <= r < n_rays for r in vals)
    try:
        info = packed_info_from_ray_indices(t, n_rays)
    except ValueError:
        assert not ok
        return
    assert ok and info.dtype == torch.int32
    counts = [vals.count(r) for r in range(n_rays)]
    assert info[:, 1].tolist() == counts
    assert info[:, 0].tolist() == [sum(counts[:r]) for r in range(n_rays)]


# ------------------------------------------------------------------------------------------------
# valid inputs: the library's own layouts pass, and its renderers skip the checks


def test_library_layouts_pass_the_checks(device):
    """Marched (misses, a sample cap, no samples at all, no rays), stratified (empty rays) and
    importance layouts: render_packed with the check equals it without and the pure-torch
    twin; live_samples too."""
    g = torch.Generator().manual_seed(0)
    bits = O.grid_pack_bits(torch.rand(8**3, generator=g).to(device), 0.5)
    o = (torch.rand(12, 3, generator=g) * 2 - 1).to(device)
    o[:, 2] = -3.0
    d = torch.tensor([0.1, -0.05, 1.0], device=device).expand(12, 3).contiguous()
    o[:3, 0] = 5.0  # these miss the box
    marched, _ = O.march_rays(o, d, 0.0, 9.0, bits, 8, BOX, 0.05)
    capped, _ = O.march_rays(o, d, 0.0, 9.0, bits, 8, BOX, 0.05, max_samples=3)
    missed, _ = O.march_rays(o[:3], d[:3], 0.0, 9.0, bits, 8, BOX, 0.05)
    none, _ = O.march_rays(o[:0], d[:0], 0.0, 9.0, bits, 8, BOX, 0.05)
    near = torch.rand(6, generator=g).to(device)
    far = near + torch.tensor([1.0, 0.0, 2.0, -1.0, 1.0, 0.5], device=device)  # two empty rays
    strat = stratified_samples(near, far, 5, packed=True)
    fine = importance_samples(strat, torch.rand(strat.t_starts.shape[0], generator=g).to(device), 3)
    assert missed.t_starts.numel() == 0 and int(capped.packed_info[:, 1].max()) == 3
    for s in (marched, capped, missed, none, strat, fine):
        n, n_rays = s.t_starts.shape[0], s.packed_info.shape[0]
        sig = (torch.rand(n, generator=g) * 5).to(device)
        rgb = torch.rand(n, 3, generator=g).to(device)
        args = (s.t_starts, s.t_ends, s.ray_indices, sig, rgb, n_rays, 1.0)
        kw = dict(packed_info=s.packed_info, t_threshold=1e-3, return_weights=True)
        a = render_packed(*args, **kw)
        b = render_packed(*args, **kw, check=False)
        ref = reference.render_packed(*args, **kw)
        for x, y, z in zip(a, b, ref):
            assert torch.equal(x, y)
            torch.testing.assert_close(x, z, rtol=1e-5, atol=1e-6)
        keep, n_live = O.live_samples(s, sig, 1e-3)
        keep2, n_live2 = O.live_samples(s, sig, 1e-3, check=False)
        assert torch.equal(keep, keep2) and torch.equal(n_live, n_live2)


def test_library_renderers_skip_the_checks_and_still_work(monkeypatch):
    """render_marched (training and rendering paths), render_nerf (coarse + fine) and
    render_rays composite their own samples with check=False: the layout check is never called,
    and the outputs are finite; a public call still checks."""

    def refuse(*a, **kw):
        raise AssertionError("a library renderer re-checked its own packed_info")

    ball = _Ball()
    grid = OccupancyGrid(BOX, 8, dt=0.05, warmup=1)
    grid.update(lambda p: ball.density(p)[0], torch.Generator().manual_seed(0))
    o = torch.tensor([[0.0, 0.0, -3.0], [0.3, 0.1, -3.0], [4.0, 4.0, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]]).expand(3, 3).contiguous()
    monkeypatch.setattr(C, "check_packed_info", refuse)
    out = render_marched(grid, ball, o, d, 0.0, 6.0, perturb=True,
                         generator=torch.Generator().manual_seed(1))  # fmt: skip
    out["rgb"].sum().backward()
    assert torch.isfinite(ball.scale.grad) and out["n_kept"] > 0
    with torch.no_grad():
        outs = [out, render_marched(grid, ball, o, d, 0.0, 6.0, round_samples=4)]
        outs.append(render_nerf(ball, o, d, 0.5, 5.0, fine=ball, n_coarse=8, n_fine=4,
                                aabb=BOX))  # fmt: skip
        outs.append(render_rays(o, d, 0.5, 5.0, ball, n_samples=8, chunk=2))
    for r in outs:
        assert r["rgb"].shape == (3, 3) and r["depth"].shape == (3,)
        assert all(bool(torch.isfinite(r[k]).all()) for k in ("rgb", "depth", "opacity"))
    assert 0.5 < float(outs[1]["opacity"][0]) and float(outs[1]["opacity"][2]) == 0.0
    ts, te, ri, sig, rgb, info = _layout([2, 1])
    with pytest.raises(AssertionError, match="re-checked"):
        render_packed(ts, te, ri, sig, rgb, 2, packed_info=info)
