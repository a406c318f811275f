"""Rendering a grid run's rays with static shapes, captured once in a CUDA graph and replayed.

:func:`warpnerf.render.render_marched` renders without gradients in rounds
(``_render_rounds``); with one round (the default) a call marches every ray's samples, runs the
density MLP on them, composites their weights, runs the colour MLP on the samples whose weight
reaches ``COLOR_WEIGHT_EPS`` and adds their colours. Each call reads two sample counts back to
the host and issues about fifty launches from Python. Here the same computation runs on fixed
buffers: ``marched`` slots for the samples, ``seen`` slots for the coloured ones (compacted
on the device), so a frame is one graph replay and one host read (of a flag).

The flag says whether the frame is exactly what ``_render_rounds`` gives: no sample dropped for
want of capacity, no ray left unfinished after the one round, no ray refused. When it is not,
the caller renders the chunk the usual way (so images never lose samples), and the next
capacities grow. Capacities cover the densest chunk seen so far (samples marched and coloured
per ray, 1.3x, rounded up to one of eight sizes per octave; the first chunk is rendered the
usual way to measure them); a shape runs eagerly twice, then is captured. At most
``MAX_GRAPHS`` shapes are kept per grid.
"""

from __future__ import annotations

from collections import OrderedDict

import torch

__all__ = ["FrameGraphs"]

MAX_GRAPHS = 4
WARM = 2
HEADROOM = 1.3


class _Shape:
    def __init__(self, key, device, dtype):
        n = key[0]
        self.key, self.runs, self.graph, self.out = key, 0, None, None
        self.o = torch.zeros(n, 3, device=device, dtype=dtype)
        self.d = torch.zeros(n, 3, device=device, dtype=dtype)
        self.d[:, 2] = 1.0  # (finite unit directions before the first copy)
        self.near = torch.zeros(n, device=device, dtype=dtype)
        self.far = torch.zeros(n, device=device, dtype=dtype)
        self.bg = torch.zeros(n, 3, device=device, dtype=dtype)  # the background, per ray


class FrameGraphs:
    """The captured frame renderers of one occupancy grid (kept on it as ``grid._frames``)."""

    def __init__(self):
        self.shapes: OrderedDict = OrderedDict()
        self.rates = None  # most samples marched and coloured per ray seen so far
        self.stream = None
        self.replays = self.captures = self.fallbacks = 0

    @staticmethod
    def of(grid) -> FrameGraphs:
        frames = getattr(grid, "_frames", None)
        if frames is None:
            frames = grid._frames = FrameGraphs()
        return frames

    def observe(self, n_rays: int, n_marched: int, n_seen: int) -> None:
        """Counts of a chunk rendered (either way): the capacities cover the densest chunk."""
        rm, rs = n_marched / max(n_rays, 1), n_seen / max(n_rays, 1)
        self.rates = (rm, rs) if self.rates is None else (max(self.rates[0], rm),
                                                          max(self.rates[1], rs))  # fmt: skip

    def key(self, n_rays: int, half: bool, cap: int, t_threshold: float) -> tuple:
        from .train.graph_step import tier

        marched = tier(int(self.rates[0] * n_rays * HEADROOM) + 1)
        seen = tier(int(self.rates[1] * n_rays * HEADROOM) + 1)
        return (n_rays, marched, seen, bool(half), int(cap), float(t_threshold))

    def render(self, grid, field, o, d, near, far, background, t_threshold, cap, half,
               sample_budget):  # fmt: skip
        """The chunk's dict (as ``_render_rounds`` returns), or None when the caller must render
        it the usual way (no counts yet, or the static frame was not exact)."""
        if self.rates is None or not o.is_cuda:
            return None
        n, dev, dt = o.shape[0], o.device, o.dtype
        key = self.key(n, half, cap, t_threshold)
        if key[1] > sample_budget:
            return None
        shape = self.shapes.pop(key, None)
        if shape is None:
            shape = _Shape(key, dev, dt)
            while len(self.shapes) >= MAX_GRAPHS:
                self.shapes.popitem(last=False)
        self.shapes[key] = shape
        shape.o.copy_(o)
        shape.d.copy_(d)
        for buf, v in ((shape.near, near), (shape.far, far)):
            if isinstance(v, torch.Tensor):
                buf.copy_(v.expand(n))
            else:
                buf.fill_(float(v))
        if isinstance(background, torch.Tensor):
            shape.bg.copy_(background.to(dt).expand(n, 3) if background.dim() < 2 else background)
        else:
            shape.bg.fill_(float(background))
        if self.stream is None:
            self.stream = torch.cuda.Stream(dev)
        if shape.runs < WARM:
            self.stream.wait_stream(torch.cuda.current_stream(dev))
            with torch.cuda.stream(self.stream):
                out = _frame(grid, field, shape, t_threshold, cap, half)
            torch.cuda.current_stream(dev).wait_stream(self.stream)
        else:
            if shape.graph is None:
                graph = torch.cuda.CUDAGraph()
                with torch.cuda.graph(graph, stream=self.stream,
                                      capture_error_mode="thread_local"):  # fmt: skip
                    shape.out = _frame(grid, field, shape, t_threshold, cap, half)
                shape.graph = graph
                self.captures += 1
            shape.graph.replay()
            self.replays += 1
            out = shape.out
        shape.runs += 1
        exact, n_marched, n_seen = out["flags"].tolist()  # the one host read
        self.observe(n, n_marched, n_seen)
        if not exact:
            self.fallbacks += 1
            return None
        return {k: out[k].clone() for k in ("rgb", "depth", "opacity")} | {
            "n_marched": int(n_marched),
            "n_kept": int(n_marched),
            "n_seen": int(n_seen),
        }


def _frame(grid, field, shape, t_threshold, cap, half):
    """One round of ``_render_rounds`` on the shape's buffers, with no host sync."""
    from .ops import render_packed
    from .ops.occupancy import compact_mask
    from .render import COLOR_WEIGHT_EPS

    n, marched, seen = shape.key[:3]
    o, d = shape.o, shape.d
    dev, dt = o.device, o.dtype
    with torch.no_grad():
        smp, k_next, mstats = grid.march(o, d, shape.near, shape.far, max_samples=cap,
                                         capacity=marched)  # fmt: skip
        ri = smp.ray_indices
        pos = o[ri] + d[ri] * smp.midpoints().unsqueeze(-1)
        with torch.autocast("cuda", dtype=torch.float16, enabled=half):
            sig, feats = field.density(pos)
        sig = sig.to(dt)
        _, z, op, w = render_packed(
            smp.t_starts, smp.t_ends, ri, sig, sig.new_zeros(1, 3).expand(marched, 3), n,
            packed_info=smp.packed_info, return_weights=True, check=False,
        )  # fmt: skip
        n_marched = mstats[0].clamp_max(marched)
        used = torch.arange(marched, device=dev) < n_marched
        src, n_seen = compact_mask((w >= COLOR_WEIGHT_EPS) & used, seen)
        rs = ri[src]
        with torch.autocast("cuda", dtype=torch.float16, enabled=half):
            col = field.color(feats[src], d[rs])
        keep = (torch.arange(seen, device=dev) < n_seen).to(dt)
        c = torch.zeros(n, 3, device=dev, dtype=dt)
        c.index_add_(0, rs.long(), (w[src] * keep).unsqueeze(-1) * col.to(dt))
        trans = 1.0 - op
        rgb = c + trans.unsqueeze(-1) * shape.bg
        unfinished = ((k_next >= 0) & (trans >= t_threshold)).any()
        exact = ~unfinished & (mstats[1] == 0) & (mstats[2] == 0) & (n_seen <= seen)
        flags = torch.stack([exact.to(torch.int64), mstats[0], n_seen])
        return {"rgb": rgb, "depth": z, "opacity": 1.0 - trans, "flags": flags}
