"""A NeRF training step with static shapes, captured once in a CUDA graph and replayed.

The eager step (:meth:`warpnerf.train.nerf.NeRFTask.loss`) sizes its buffers by what it marched:
two host reads of device counts per step, and about two hundred launches issued one by one from
Python, so the GPU waits for the host. Here every buffer of the step has a fixed size:

- ``rays`` ray slots, of which the step's ``batch`` are used (the others get no samples and no
  weight in the loss: a ray batch that changes from step to step needs no new graph);
- ``marched`` slots for the grid's samples and ``kept`` slots for those before each ray's
  transmittance drops below the threshold (:func:`warpnerf.render.render_marched_fixed`).

The capacities come from the previous step's counts (read by the loop at its one sync a step,
with the loss) times ``HEADROOM``, rounded up to one of eight sizes per octave. A set of sizes
is a *shape*, kept while it fits and is not far too large. Each shape is run eagerly ``WARM``
times (on a side stream: warm-up for the capture), then captured once: forward (rays,
marching, the field's two passes, compositing, the loss), backward, the divergence flags and
fused Adam. Later steps of that shape replay it: the host draws the batch's pixels (the same
generator calls as the eager step), copies them in, sets the learning rate and launches one
graph. At most ``MAX_GRAPHS`` shapes are kept (least recently used dropped). Samples that do
not fit are dropped deterministically (by ray order) and counted in the history
(``dropped_samples``); the next step's capacities grow.

The occupancy grid's update (every ``--grid-every`` steps) stays eager, before the step.
The same body runs without capture on CPU (``capture=False``), which is what the tests compare
with the eager step.
"""

from __future__ import annotations

import math
from collections import OrderedDict

import torch

from ..render import render_marched_fixed
from .divergence import nonfinite_flags
from .step_loss import step_loss, unsupported_terms
from .supersample import expand_rows, pixel_means, sub_rays

__all__ = ["GraphStep", "unsupported", "tier", "HEADROOM", "MAX_GRAPHS"]

# capacity over the previous step's count, scaled to this step's batch: (marched, kept). The
# kept samples stay near --target-samples (the batch adapts to them), the marched ones move
# with the grid's updates; every slot costs field work (forward only for the marched ones)
HEADROOM = (1.1, 1.06)
MAX_GRAPHS = 6  # captured shapes kept at once (each holds its own memory pool)
WARM = 2  # eager runs of a shape before it is captured
QUANTUM = 256  # capacities are multiples of this
PER_OCTAVE = 8  # capacity sizes per doubling (2^(1/8) = 1.09 apart)
# (rays, marched, kept): a new shape is SLACK sizes above what the step needs (room to grow),
# and stays in use while it is at most KEEP sizes above the need. Ray slots are cheap (per-ray
# work only), sample slots cost field work
SLACK = (3, 1, 0)
KEEP = (6, 2, 2)


def tier(n: int, up: int = 0) -> int:
    """The smallest capacity >= n of the form 256 * 2^(k/8), ``up`` sizes more, rounded up to a
    multiple of 256."""
    size = QUANTUM * 2 ** ((_tier_index(n) + up) / PER_OCTAVE)
    return int(math.ceil(size / QUANTUM - 1e-9) * QUANTUM)


def _tier_index(n: int) -> int:
    return math.ceil(PER_OCTAVE * math.log2(max(max(int(n), 1) / QUANTUM, 1.0)) - 1e-9)


def unsupported(cfg, model, task) -> str | None:
    """Why this run's step cannot have static shapes (None: it can)."""
    if getattr(model, "proposal", None) is not None:  # (fixed shapes, but its own step)
        return "--sampler proposal is not captured yet (its step runs eagerly)"
    if model.grid is None:
        return "it needs an occupancy grid"
    why = unsupported_terms(task.loss_settings, model, task.dist)  # (the loss's terms)
    if why is not None:
        return why
    if task.host_images:
        return "images kept in host memory (--images-on host) are not captured yet"
    if model.poses is not None:
        return "--pose-refine is not captured yet"
    if task.train.distortion is not None:
        return "lens distortion (a COLMAP/LLFF camera model with k1..p2) is not captured yet"
    return None


class _Shape:
    """One set of capacities: its static input buffers, and its graph once captured."""

    def __init__(self, key: tuple, device, random_bg: bool, near: float, far: float,
                 pixel_jitter: bool = False, spp: int = 1):  # fmt: skip
        rays = key[0]  # pixel slots (--train-spp: spp rays each, pixel i's at i*spp ..)
        self.key, self.runs, self.graph, self.out = key, 0, None, None
        # constants of the step (made once, not filled again in every step): the slots'
        # indices and the near and far planes
        self.slots = torch.arange(rays, device=device)
        self.near = torch.full((rays * spp,), near, device=device)
        self.far = torch.full((rays * spp,), far, device=device)
        # the batch's flat pixel indices (unused slots: 0), then the number of rays used
        self.inputs = torch.zeros(rays + 1, device=device, dtype=torch.int64)
        self.flat, self.n_active = self.inputs[:rays], self.inputs[rays]
        self.jitter = torch.zeros(rays * spp, device=device, dtype=torch.float32)
        self.bg = torch.zeros(rays, 3, device=device) if random_bg else None
        # --pixel-jitter: each ray's point in its pixel (else the pixel's centre)
        self.pix = torch.full((rays, 2), 0.5, device=device) if pixel_jitter else None
        self.box = None  # an SDF field's eikonal points in [0, 1)^3 [batch, 3] (drawn per step)


class GraphStep:
    """The static-shape step of a :class:`~warpnerf.train.nerf.NeRFTask` (see the module's
    text). ``capture``: use CUDA graphs (CUDA only); False runs the same body eagerly."""

    def __init__(self, task, capture: bool):
        self.task, self.capture = task, bool(capture)
        self.shapes: OrderedDict = OrderedDict()
        self.last = None  # (batch, samples marched, live samples) of the previous step
        self.current = None  # the key of the shape in use
        self.captures = self.replays = 0  # graphs captured and replayed so far (tests, tools)
        self.force = None  # tests: a fixed key (rays, marched, kept) instead of the sizing rule
        self.failed = None  # why a capture failed (the task then goes on eagerly)
        dev = torch.device(task.cfg.device)
        self.device = dev
        self._staging = None  # pinned host buffer of the batch's pixel indices (CUDA)
        self._box_staging = None  # the same for an SDF field's eikonal points
        self._field_state = None  # what of the field's schedule a graph holds (open levels)
        self._copied = None  # the event after the last copy out of it
        self.stream = torch.cuda.Stream(dev) if self.capture else None

    def restore(self, saved) -> None:
        """The sizes a checkpoint saved (``state()["static_shape"]``), so that a resumed run
        continues with the shapes it had; anything malformed is ignored (the first step then
        runs eagerly and measures them again)."""
        if not isinstance(saved, dict):
            return
        last, cur = saved.get("last"), saved.get("current")

        def ints(v, n):
            ok = isinstance(v, (list, tuple)) and len(v) == n
            return ok and all(isinstance(x, int) and 0 <= x < 2**31 for x in v)

        if ints(last, 3):
            self.last = tuple(last)
            self.current = tuple(cur) if ints(cur, 3) and all(x > 0 for x in cur) else None

    # --- sizes -----------------------------------------------------------------------------

    def key(self, batch: int) -> tuple:
        """(rays, marched, kept) for a step of ``batch`` rays, from the previous step's counts;
        the shape in use is kept while it fits and is at most two sizes too large."""
        if self.force is not None:
            return self.force
        b0, marched0, live0 = self.last
        scale = batch / max(b0, 1)
        need = (batch, int(marched0 * scale * HEADROOM[0]) + 1,
                int(live0 * scale * HEADROOM[1]) + 1)  # fmt: skip
        cur = self.current
        if cur is not None and all(
            c >= n and _tier_index(c) - _tier_index(n) <= k for c, n, k in zip(cur, need, KEEP)
        ):
            return cur
        return tuple(tier(n, up) for n, up in zip(need, SLACK))

    def _shape(self, key) -> _Shape:
        shape = self.shapes.pop(key, None)
        if shape is None:
            cfg = self.task.cfg
            shape = _Shape(key, self.device, self.task.random_bg, float(cfg.near), float(cfg.far),
                           bool(getattr(cfg, "pixel_jitter", False)),
                           self.task.train_spp)  # fmt: skip
            while len(self.shapes) >= MAX_GRAPHS:
                self.shapes.popitem(last=False)  # least recently used (its graph and pool go)
        self.shapes[key] = shape
        self.current = key
        return shape

    # --- one step --------------------------------------------------------------------------

    def run(self, step: int, opt, params) -> tuple | None:
        """Loss, terms and divergence flags of one step (the optimiser has stepped); None when
        a capture failed (``failed`` says why; the step's random draws are made, nothing else)."""
        task = self.task
        batch = task.batch
        state = getattr(task.model.coarse, "open_levels", None)  # (an SDF's finite-difference
        if state != self._field_state:  # step follows its open levels: a host number that a
            self.shapes.clear()  # graph holds as a constant)
            self._field_state = state
        shape = self._shape(self.key(batch))
        if batch > shape.key[0]:
            raise RuntimeError(f"a batch of {batch} rays in a shape of {shape.key[0]} slots")
        self._inputs(shape, batch)
        if not self.capture:
            out = self._body(shape, opt, params)
        elif shape.runs < WARM:  # eager, on the side stream the capture will use
            self.stream.wait_stream(torch.cuda.current_stream(self.device))
            with torch.cuda.stream(self.stream):
                out = self._body(shape, opt, params)
            torch.cuda.current_stream(self.device).wait_stream(self.stream)
        else:
            if shape.graph is None:
                try:
                    self._capture(shape, opt, params)
                except RuntimeError as e:  # (torch's AcceleratorError is one)
                    self.failed = " ".join(str(e).split())[:200]
                    self.shapes.clear()
                    torch.cuda.synchronize(self.device)
                    return None
            shape.graph.replay()
            self.replays += 1
            out = shape.out
        shape.runs += 1
        loss, terms, flags = out
        return loss, dict(terms, batch=batch), flags

    def _inputs(self, shape: _Shape, batch: int) -> None:
        """The step's random draws, as the eager step makes them, into the shape's buffers."""
        task, dev = self.task, self.device
        n_pix = task.n_img * task.w * task.h
        host = torch.randint(0, n_pix, (batch,), generator=task.gen, device="cpu")
        rays = shape.key[0]
        if self._copied is not None:  # the last step's copies out of the pinned buffers (long
            self._copied.synchronize()  # finished: the loop read that step's loss since)
        if dev.type == "cuda":
            if self._staging is None or self._staging.numel() < rays + 1:
                self._staging = torch.zeros(max(rays + 1, 1 << 16), dtype=torch.int64,
                                            pin_memory=True)  # fmt: skip
            stage = self._staging[: rays + 1]
            stage[:batch] = host
            stage[batch:rays] = 0
            stage[rays] = batch
            shape.inputs.copy_(stage, non_blocking=True)
        else:
            shape.inputs.zero_()
            shape.inputs[:batch] = host
            shape.inputs[rays] = batch
        if task.grid is not None:  # the lattice jitter (and backgrounds): the eager step's draws
            m = batch * task.train_spp  # (the rays of the batch's pixels)
            torch.rand(m, device=dev, generator=task.grid_gen, out=shape.jitter[:m])
            if shape.bg is not None:
                torch.rand(batch, 3, device=dev, generator=task.grid_gen, out=shape.bg[:batch])
            if shape.pix is not None:
                torch.rand(batch, 2, device=dev, generator=task.grid_gen, out=shape.pix[:batch])
        if task.model.kind == "sdf":  # the eikonal term's box points, as the eager step draws
            box = torch.rand(task.cfg.batch, 3, generator=task.gen)
            if shape.box is None:
                shape.box = torch.zeros(box.shape, device=dev)
            if dev.type == "cuda":
                if self._box_staging is None:
                    self._box_staging = torch.empty(box.shape, pin_memory=True)
                self._box_staging.copy_(box)
                shape.box.copy_(self._box_staging, non_blocking=True)
            else:
                shape.box.copy_(box)
        if dev.type == "cuda":
            self._copied = torch.cuda.Event()
            self._copied.record()

    def _capture(self, shape: _Shape, opt, params) -> None:
        opt.zero_grad(set_to_none=True)  # (the graph allocates its own gradients)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, stream=self.stream, capture_error_mode="thread_local"):
            shape.out = self._body(shape, opt, params)
        shape.graph = graph
        self.captures += 1

    def _body(self, shape: _Shape, opt, params) -> tuple:
        """Everything of a step after the draws, with no host sync: what the graph holds."""
        task = self.task
        cfg, model = task.cfg, task.model
        _, marched, kept = shape.key
        flat, w = shape.flat, task.w
        cam = flat // (w * task.h)
        rem = flat % (w * task.h)
        if shape.pix is None:
            py = (rem // w).to(torch.float32) + 0.5
            px = (rem % w).to(torch.float32) + 0.5
        else:  # --pixel-jitter
            py = (rem // w).to(torch.float32) + shape.pix[:, 1]
            px = (rem % w).to(torch.float32) + shape.pix[:, 0]
        spp, bg = task.train_spp, shape.bg
        active = shape.slots < shape.n_active
        active_rays = active
        if spp > 1:  # --train-spp: each pixel's sub-rays (its background, its activity)
            cam, px, py = sub_rays(cam, px, py, task.sub_offsets)
            bg = None if bg is None else expand_rows(bg, spp)
            active_rays = expand_rows(active, spp)
        o, d = task.batch_rays(cam, px, py)
        near = shape.near
        far = torch.where(active_rays, shape.far, near)  # unused slots: no samples
        opt.zero_grad(set_to_none=True)
        with task.mlp_precision():
            out = render_marched_fixed(
                task.grid, model.coarse, o, d, near, far, marched=marched, kept=kept,
                jitter=shape.jitter, background=cfg.background if bg is None else bg,
                t_threshold=cfg.t_threshold, max_samples=cfg.max_samples,
                ray_images=cam if cfg.appearance_dim else None,
                distortion_s=task.distortion_map(), near_t=task.near_distances(o),
            )  # fmt: skip
        if spp > 1:  # the pixels' renders: the means of their sub-rays'
            out = pixel_means(out, shape.slots.shape[0], spp)
        target, alpha = task.pixels(flat)
        weight = active.to(out["rgb"].dtype)
        n_active = shape.n_active.to(out["rgb"].dtype)
        loss, terms = step_loss(task.loss_settings, model, out, target, alpha, shape.bg, weight,
                                n_active, box=shape.box)  # fmt: skip
        stats = out["stats"]
        terms.update({
            "samples_per_ray": stats[3].to(torch.float64) / shape.n_active.to(torch.float64),
            "dropped_samples": stats[1] + stats[4],
            "_marched": stats[0],
            "_live": stats[3],
        })  # fmt: skip
        loss.backward()
        flags = nonfinite_flags(loss, params)
        flags = torch.stack([flags[0] | (stats[2] > 0), flags[1]])  # a refused ray: loudly
        opt.step()
        return loss, terms, flags
