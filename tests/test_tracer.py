"""The rendering tracer (kernels/tracer.py, :func:`warpnerf.render_traced.render_traced`): the
same image as the rounds path of ``render_marched`` and as the float64 twin, whatever the
rounds' step counts; hard rays (misses, near == far, huge densities, many samples, axis-parallel
rays, non-finite inputs); the field's sample budget; the dispatch from ``render_marched``."""

from __future__ import annotations

import pytest
import torch

from warpnerf.fields.hash_nerf import HashNeRFField
from warpnerf.occupancy import OccupancyGrid
from warpnerf.ops import HashGrid
from warpnerf.ops import occupancy as O
from warpnerf.ops.tracer import COLOR_WEIGHT_EPS
from warpnerf.reference import tracer as R
from warpnerf.render import render_marched
from warpnerf.render_traced import render_traced

BOX = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]
KEYS = ("rgb", "depth", "opacity")


class Ball(torch.nn.Module):
    """Density ``sigma`` in a ball (plus ``everywhere``), colour from position and direction."""

    def __init__(self, radius=0.6, sigma=30.0, everywhere=0.0):
        super().__init__()
        self.radius, self.sigma, self.everywhere = radius, sigma, everywhere

    def density(self, x):
        inside = (x.norm(dim=-1) < self.radius).to(x.dtype)
        return self.sigma * inside + self.everywhere + 0.0 * x[:, 0], x

    def color(self, h, d):
        return torch.sigmoid(h * 3 + d)


def rays(n, device, seed=0):
    """Rays aimed near the box, axis-parallel ones, ones starting inside and ones missing it."""
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(n, 3, generator=g) * 3
    d = -o + torch.randn(n, 3, generator=g) * 0.5
    o[:4], d[:4] = torch.tensor([-3.0, 0.1, 0.2]), torch.tensor([1.0, 0.0, 0.0])  # axis-parallel
    o[4:8] = torch.rand(4, 3, generator=g) - 0.5  # inside the box
    o[8:10], d[8:10] = torch.tensor([0.0, 5.0, 0.0]), torch.tensor([0.0, 1.0, 0.0])  # away: miss
    d = d / d.norm(dim=-1, keepdim=True)
    return o.to(device), d.to(device)


def ball_grid(field, device, res=16, dt=0.02):
    grid = OccupancyGrid(BOX, res, dt=dt, warmup=4).to(device)
    gen = torch.Generator(device=device).manual_seed(0)
    for _ in range(4):
        grid.update(lambda x: field.density(x)[0], gen)
    return grid


def rounds(grid, field, o, d, near=0.0, far=9.0, **kw):
    """The rounds path; by default with the tracer's colour rule (samples under
    COLOR_WEIGHT_EPS black), so that the two compare up to float error."""
    kw = {"color_eps": COLOR_WEIGHT_EPS, "color_fill": "black", **kw}
    with torch.no_grad():
        return render_marched(grid, field, o, d, near, far, tracer="rounds", **kw)


def twin(grid, field, o, d, near=0.0, far=9.0, *, colors="weighted", background=1.0,
         t_threshold=1e-4):  # fmt: skip
    """The float64 twin on the same grid (rays and field in float64)."""

    def density_fn(pos, dirs):
        sig, h = field.density(pos)
        return sig, (h, dirs)

    def color_fn(ctx, idx):
        h, dirs = ctx
        return field.color(h, dirs) if idx is None else field.color(h[idx], dirs[idx])

    return R.trace_rays(o.double(), d.double(), near, far, grid.bits, grid.res, grid.box, grid.dt,
                        density_fn, color_fn, contract=grid.contract, cone=grid.cone,
                        color_all=colors == "all", background=background,
                        t_threshold=t_threshold)  # fmt: skip


def close(a, b, atol, keys=KEYS):
    for k in keys:
        torch.testing.assert_close(a[k].double(), b[k].double(), rtol=0, atol=atol, msg=k)


@pytest.mark.parametrize("colors", ["weighted", "all"])
def test_traced_equals_rounds_and_the_twin(device, colors):
    """Rounds path (t_threshold 0: every sample composited) and twin (float64): the same image
    up to float error and the colour-skip rule (samples under 1e-5 of weight, black in the
    rounds path: "all" differs by at most their summed weight)."""
    field = Ball()
    grid = ball_grid(field, device)
    assert 0.0 < grid.occupancy() < 0.5
    o, d = rays(48, device)
    with torch.no_grad():
        new = render_traced(grid, field, o, d, 0.0, 9.0, background=0.3, t_threshold=0.0,
                            colors=colors)  # fmt: skip
        ref = twin(grid, field, o, d, background=0.3, t_threshold=0.0, colors=colors)
    old = rounds(grid, field, o, d, background=0.3, t_threshold=0.0)
    assert new["n_marched"] == old["n_marched"] == ref["n_marched"] > 0
    close(new, old, 1e-5 if colors == "weighted" else 2e-4)
    close(new, ref, 2e-6, ("rgb", "opacity"))
    close(new, ref, 2e-5, ("depth",))
    assert torch.equal(new["rgb"][8:10], torch.full((2, 3), 0.3, device=device))  # misses
    assert float(new["opacity"][8:10].abs().max()) == 0.0


def test_early_termination_equals_the_twin_and_stays_near_the_rounds_path(device):
    """With t_threshold the tracer stops each ray at the compositing kernels' sample; the rounds
    path composites its (one) round whole: the difference is below the threshold's weight."""
    field = Ball(sigma=200.0)
    grid = ball_grid(field, device)
    o, d = rays(48, device, seed=1)
    with torch.no_grad():
        new = render_traced(grid, field, o, d, 0.0, 9.0, t_threshold=1e-3)
        ref = twin(grid, field, o, d, t_threshold=1e-3)
    old = rounds(grid, field, o, d, t_threshold=1e-3)
    close(new, ref, 2e-6, ("rgb", "opacity"))
    close(new, ref, 2e-5, ("depth",))
    close(new, old, 2e-3, ("rgb", "opacity"))
    close(new, old, 2e-3 * 9.0, ("depth",))  # (the weight left, at t < far)
    assert new["n_marched"] < old["n_marched"]  # nothing marched behind the opaque ball


def test_color_eps_skips_light_samples_within_their_weight(device):
    """The rounds path's ``color_eps``: a larger one colours fewer samples, and each pixel moves
    by at most the weight of the samples it no longer colours (counted black); densities,
    opacity and depth are untouched; 0 colours every sample; outside [0, 1) it refuses."""
    field = Ball(sigma=8.0, everywhere=0.3)  # soft: many light samples before the ball
    grid = ball_grid(field, device)
    o, d = rays(48, device, seed=3)
    out = {e: rounds(grid, field, o, d, background=0.0, color_eps=e) for e in (0.0, 1e-5, 1e-2)}
    n = [out[e]["n_colored"] for e in (0.0, 1e-5, 1e-2)]
    assert n[0] >= n[1] > n[2] > 0, n
    assert n[0] == out[0.0]["n_kept"]  # (every composited sample, weightless ones too)
    for e in (1e-5, 1e-2):
        close(out[e], out[0.0], 0.0, ("opacity", "depth"))
        gap = (out[0.0]["rgb"] - out[e]["rgb"]).double()  # (sigmoid colours < 1: darker)
        assert float(gap.min()) >= -1e-6
    ws = []  # each ray's weight in samples lighter than 1e-2: the bound of its colour change
    with torch.no_grad():
        render_marched(grid, field, o, d, 0.0, 9.0, tracer="rounds", color_eps=0.0,
                       on_weights=lambda ri, t0, t1, w: ws.append((ri, w)))  # fmt: skip
    light = torch.zeros(o.shape[0], dtype=torch.float64, device=device)
    for ri, w in ws:
        light.index_add_(0, ri.long(), torch.where(w < 1e-2, w, 0.0).double())
    gap = (out[0.0]["rgb"] - out[1e-2]["rgb"]).double().amax(-1)
    assert bool((gap <= light + 1e-6).all()) and float(gap.max()) > 0
    for bad in (-1e-3, 1.0, float("nan")):
        with pytest.raises(ValueError, match="color_eps"):
            rounds(grid, field, o, d, color_eps=bad)


class GreyBall(Ball):
    """Ball with one colour everywhere."""

    def color(self, h, d):
        return torch.full_like(h, 0.25)


def test_mean_fill_is_exact_for_one_colour_and_nearer_than_black(device):
    """``color_fill="mean"`` (the rounds path's default, with ``RENDER_COLOR_EPS``): a ray's
    skipped samples take its coloured samples' mean colour, so one colour everywhere renders
    exactly as colouring every sample; with colours that vary, the image is nearer the full one
    than black's on average (a ray none of whose samples is coloured stays black)."""
    o, d = rays(48, device, seed=4)
    for field, exact in ((GreyBall(sigma=8.0), True),  # (every ray that meets it colours some)
                         (Ball(sigma=8.0, everywhere=0.3), False)):  # fmt: skip
        grid = ball_grid(field, device)
        full = rounds(grid, field, o, d, background=0.0, color_eps=0.0)
        mean = rounds(grid, field, o, d, background=0.0, color_eps=1e-2, color_fill="mean")
        black = rounds(grid, field, o, d, background=0.0, color_eps=1e-2)
        assert mean["n_colored"] == black["n_colored"] < full["n_colored"]
        e_mean = (mean["rgb"] - full["rgb"]).abs().mean().item()  # (over rays: a ray with
        e_black = (black["rgb"] - full["rgb"]).abs().mean().item()  # none coloured is black)
        if exact:  # (rays whose samples all weigh under eps stay black: none here)
            assert e_mean < 1e-5 < e_black, (e_mean, e_black)
        else:
            assert e_mean < 0.5 * e_black, (e_mean, e_black)
        with torch.no_grad():  # the defaults: the mean fill
            dflt = render_marched(grid, field, o, d, 0.0, 9.0, tracer="rounds", background=0.0)
        assert dflt["n_colored"] <= full["n_colored"]
        close(dflt, full, 5e-3 if not exact else 1e-5, ("rgb",))  # (measured 2.3e-3 in fog)
    one = rounds(grid, field, o, d, color_eps=1e-2, color_fill="mean", t_threshold=0.0)
    full = rounds(grid, field, o, d, color_eps=0.0, t_threshold=0.0)
    err = (one["rgb"] - full["rgb"]).abs().max().item()
    for rs in (1, 4):  # (the mean is the ray's over all its rounds; a later round's heaviest
        # sample is lighter, so rounds colour at least as many: no farther from the full image)
        split = rounds(grid, field, o, d, color_eps=1e-2, color_fill="mean", t_threshold=0.0,
                       round_samples=rs)  # fmt: skip
        assert split["n_colored"] >= one["n_colored"]
        assert (split["rgb"] - full["rgb"]).abs().max().item() <= err + 1e-6
    with pytest.raises(ValueError, match="color_fill"):
        rounds(grid, field, o, d, color_fill="grey")


def test_the_default_colours_a_fog_of_light_samples(device):
    """A thin fog (every sample under 1e-3 of weight in the image at this step, opacity about
    0.4 along a ray) keeps its colour by default: the threshold is relative to each ray's
    heaviest sample, so a ray of many light samples colours them."""
    field = Ball(sigma=0.0, everywhere=0.19)
    grid = OccupancyGrid(BOX, 8, dt=0.005).to(device)  # all occupied
    o, d = rays(24, device, seed=5)
    full = rounds(grid, field, o, d, background=0.0, color_eps=0.0, t_threshold=0.0)
    with torch.no_grad():
        dflt = render_marched(grid, field, o, d, 0.0, 9.0, tracer="rounds", background=0.0,
                              t_threshold=0.0)  # fmt: skip
    assert float(full["opacity"].max()) > 0.3
    close(dflt, full, 1e-4, ("rgb", "opacity"))


@pytest.mark.parametrize("steps", [(1, 1), (1, 8), (3, 5), (64, 64)])
def test_step_counts_per_round_do_not_change_the_image(device, steps):
    field = Ball(sigma=5.0, everywhere=0.2)
    grid = OccupancyGrid(BOX, 8, dt=0.03).to(device)  # all occupied: long rays, many rounds
    o, d = rays(24, device, seed=2)
    with torch.no_grad():
        one = render_traced(grid, field, o, d, 0.0, 9.0)
        new = render_traced(grid, field, o, d, 0.0, 9.0, min_steps=steps[0], max_steps=steps[1])
    close(new, one, 2e-6, ("rgb", "opacity"))
    close(new, one, 2e-5, ("depth",))  # (per-round partial sums: float32 rounding)
    assert new["n_marched"] == one["n_marched"]
    if steps == (1, 1):
        assert new["n_rounds"] > 60  # every sample a round of its own (rays up to ~115 samples)


def test_many_samples_per_ray_beyond_max_samples(device):
    """Rays of ~1000 samples: the rounds path (marching max_samples=64 per round) and the tracer
    composite all of them (t_threshold 0); the twin agrees."""
    field = Ball(sigma=0.0, everywhere=0.05)
    grid = OccupancyGrid(BOX, 8, dt=0.003).to(device)
    o = torch.tensor([[-3.0, 0.01, 0.02], [0.02, -3.0, 0.01]], device=device)
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], device=device)
    with torch.no_grad():
        new = render_traced(grid, field, o, d, 0.0, 9.0, t_threshold=0.0)
        ref = twin(grid, field, o, d, t_threshold=0.0)
    old = rounds(grid, field, o, d, t_threshold=0.0, max_samples=64)
    assert new["n_marched"] == old["n_marched"] == ref["n_marched"] > 1300
    close(new, old, 1e-5)
    close(new, ref, 1e-5, ("rgb", "opacity"))
    close(new, ref, 2e-4, ("depth",))


def test_hard_rays(device):
    """Huge densities stop a ray after its first sample; near == far and far < near give no
    samples (background); a ray missing the box too."""
    field = Ball(sigma=1e8)
    grid = ball_grid(field, device)
    o = torch.tensor([[-3.0, 0.0, 0.0]] * 4, device=device)
    d = torch.tensor([[1.0, 0.0, 0.0]] * 3 + [[0.0, 1.0, 0.0]], device=device)
    near = torch.tensor([0.0, 2.0, 2.5, 0.0], device=device)
    far = torch.tensor([9.0, 2.0, 1.0, 9.0], device=device)
    with torch.no_grad():
        out = render_traced(grid, field, o, d, near, far, background=0.25)
    hit_first = field.color(o[:1] + d[:1] * 2.4, d[:1])  # any point of the first sample: ~same
    assert float(out["opacity"][0]) == 1.0
    torch.testing.assert_close(out["rgb"][0], hit_first[0], atol=0.05, rtol=0)
    assert torch.equal(out["rgb"][1:], torch.full((3, 3), 0.25, device=device))
    assert torch.equal(out["opacity"][1:], torch.zeros(3, device=device))
    assert out["n_rounds"] == 1  # the opaque ball: T = 0 after its first sample, the ray stops


def test_non_finite_inputs(device):
    """NaN/Inf origins, NaN near and zero directions are refused (the marchers' ValueError);
    a NaN density makes its ray NaN (it propagates, as compositing does) and no other."""
    field = Ball()
    grid = ball_grid(field, device)
    o, d = rays(12, device)
    for bad in ("nan_o", "inf_d", "zero_d", "nan_near"):
        oo, dd, near = o.clone(), d.clone(), torch.zeros(12, device=device)
        if bad == "nan_o":
            oo[3, 0] = float("nan")
        elif bad == "inf_d":
            dd[3, 1] = float("inf")
        elif bad == "zero_d":
            dd[3] = 0.0
        else:
            near[3] = float("nan")
        with torch.no_grad(), pytest.raises(ValueError, match="finite|non-zero"):
            render_traced(grid, field, oo, dd, near, 9.0)

    class NaNField(Ball):
        def density(self, x):
            sig, h = super().density(x)
            # NaN on the side of the axis-parallel rays (y = 0.1): they hit the ball on every
            # device (the grid's cells come from the device's generator: on CUDA no ray that
            # reaches x > 0.3 was sampled, so the old region gave no NaN ray there)
            return torch.where(x[:, 1] > 0.05, float("nan"), sig), h

    with torch.no_grad():
        out = render_traced(grid, NaNField(), o, d, 0.0, 9.0)
        ok = render_traced(grid, Ball(), o, d, 0.0, 9.0)
    nan_rays = torch.isnan(out["rgb"]).any(-1)
    assert bool(nan_rays.any()) and bool((~nan_rays).any())
    close({k: v[~nan_rays] for k, v in out.items() if k in KEYS},
          {k: v[~nan_rays] for k, v in ok.items() if k in KEYS}, 0.0)  # fmt: skip


def test_hash_field_with_a_trained_grid(device):
    """A tiny hash field (random weights) and its occupancy grid: the tracer's image equals the
    rounds path's, with the default threshold within its weight."""
    torch.manual_seed(0)
    field = HashNeRFField(BOX, HashGrid(4, 2, 10, 4, 32), hidden=16).to(device)
    with torch.no_grad():
        field.density_mlp[-1].bias[0] = 3.0  # dense enough to stop some rays
    grid = OccupancyGrid(BOX, 16, dt=0.02, warmup=1).to(device)
    with torch.no_grad():
        grid.update(lambda x: field.density(x)[0], torch.Generator(device=device).manual_seed(0))
        keep = torch.rand(16**3, generator=torch.Generator().manual_seed(3)) < 0.4
        grid.bits.copy_(O.grid_pack_bits(grid.density * keep.to(device), grid.threshold()))
    assert 0.0 < grid.occupancy() < 0.6
    o, d = rays(48, device, seed=3)
    for thr, atol in ((0.0, 1e-5), (1e-4, 3e-4)):
        with torch.no_grad():
            new = render_traced(grid, field, o, d, 0.0, 9.0, t_threshold=thr)
            new_all = render_traced(grid, field, o, d, 0.0, 9.0, t_threshold=thr, colors="all")
        old = rounds(grid, field, o, d, t_threshold=thr)
        close(new, old, atol, ("rgb", "opacity"))
        close(new_all, old, atol + 5e-4, ("rgb", "opacity"))
        close(new, old, 10 * atol, ("depth",))  # (the weight left, at t < 9; float32 sums)
        if thr:
            assert float(old["opacity"].max()) > 0.99  # some rays do terminate


def test_contracted_grid(device):
    """An unbounded scene's contracted grid (cone steps): the tracer equals the rounds path."""
    a = 1.0
    field = Ball(radius=1.5, sigma=3.0)
    grid = OccupancyGrid([-2 * a] * 3 + [2 * a] * 3, 8, dt=0.05, contract=a, cone=1 / 16)
    grid = grid.to(device)
    o, d = rays(24, device, seed=4)
    o = o * 0.2  # cameras inside the inner cube
    with torch.no_grad():
        new = render_traced(grid, field, o, d, 0.0, 50.0, t_threshold=0.0)
    old = rounds(grid, field, o, d, 0.0, 50.0, t_threshold=0.0)
    assert new["n_marched"] == old["n_marched"] > 0
    close(new, old, 1e-5)


def test_sample_budget_bounds_field_calls(device):
    field = Ball(sigma=5.0)
    grid = OccupancyGrid(BOX, 8, dt=0.02).to(device)
    o, d = rays(32, device, seed=5)
    calls, density = [], field.density

    def counting(x):
        calls.append(x.shape[0])
        return density(x)

    with torch.no_grad():
        one = render_traced(grid, field, o, d, 0.0, 9.0)
        field.density = counting
        for colors in ("weighted", "all"):
            r = render_traced(grid, field, o, d, 0.0, 9.0, sample_budget=50, colors=colors)
            close(r, one, 1e-6 if colors == "weighted" else 2e-4)
    assert len(calls) > 10 and max(calls) <= 50


def test_render_marched_dispatch(device):
    """Without gradients render_marched takes the rounds path by default (measured faster on a
    GPU, issue 47) and traces on request (tracer="traced"); with gradients the tracer plays no
    part."""
    field = Ball()
    grid = ball_grid(field, device)
    o, d = rays(16, device)
    with torch.no_grad():
        assert "n_rounds" not in render_marched(grid, field, o, d, 0.0, 9.0)
        assert "n_rounds" in render_marched(grid, field, o, d, 0.0, 9.0, tracer="traced",
                                            round_samples=4)  # fmt: skip
        assert "n_rounds" not in render_marched(grid, field, o, d, 0.0, 9.0, round_samples=4)
        assert "n_rounds" not in render_marched(grid, field, o, d, 0.0, 9.0, tracer="rounds")
        with pytest.raises(ValueError, match="tracer"):
            render_marched(grid, field, o, d, 0.0, 9.0, tracer="fast")
        with pytest.raises(ValueError, match="colors"):
            render_marched(grid, field, o, d, 0.0, 9.0, colors="some")
    assert "n_rounds" not in render_marched(grid, field, o, d, 0.0, 9.0)


def test_marching_primitive_is_shared(device):
    """The tracer marches with the grid marchers' own rule: its samples are march_rays'."""
    bits = O.grid_pack_bits((torch.rand(8**3, generator=torch.Generator().manual_seed(1)) < 0.3)
                            .float().to(device), 0.5)  # fmt: skip
    o, d = rays(32, device, seed=6)
    seen = []

    def density_fn(pos, dirs):
        seen.append(pos)
        return torch.zeros(pos.shape[0], device=device), None

    from warpnerf.ops.tracer import trace_rays

    out = trace_rays(o, d, 0.0, 9.0, bits, 8, BOX, 0.05, density_fn, lambda c, i: None,
                     t_threshold=0.0)  # fmt: skip
    smp, _ = O.march_rays(o, d, 0.0, 9.0, bits, 8, BOX, 0.05, max_samples=10**6)
    assert out["n_marched"] == smp.t_starts.shape[0]
    ri = smp.ray_indices.long()
    want = o[ri] + d[ri] * (0.5 * (smp.t_starts + smp.t_ends)).unsqueeze(-1)
    got = torch.cat(seen)
    # every marched position appears among the slots (unused slots hold ray origins)
    dist = torch.cdist(want.double(), got.double()).amin(1)
    assert float(dist.max()) < 1e-5
