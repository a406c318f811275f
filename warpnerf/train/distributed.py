"""Data-parallel training through ``torch.distributed`` (launched with ``torchrun``).

Every rank holds the whole model, draws the same global batch of pixels (the same CPU generator
and seed) and renders its contiguous share of the rays; the gradients are averaged over the ranks
(one all-reduce of all of them, flattened), so each rank applies the same update and the
occupancy grid, whose updates draw from a generator every rank advances identically, stays the
same everywhere. The loss each rank reports is its share's sum over the global batch size, so
the all-reduced loss is the global batch's mean, whatever the split. The random draws of a step
are the whole batch's: the grid's lattice jitter is drawn for all rays and sliced, stratified
and importance jitter are keyed by the global ray index (``ray_offset``), so N ranks follow the
loss curve of one process with the whole batch up to float rounding. Only rank 0 writes files
(config, checkpoints, history, logs) and validates; a checkpoint holds nothing rank-specific,
so a run resumes with any number of ranks. NCCL on CUDA, gloo on CPU.

A rank that dies (killed, out of memory, its machine gone) makes the others' next collective
fail (gloo and NCCL report the closed connection, or the timeout, ``WARPNERF_DIST_TIMEOUT``
seconds, default 600, when a peer hangs): every collective here turns that failure into a
:class:`PeerLost`, a :class:`~warpnerf.errors.UserError` (one line naming this rank and the
backend's message, exit status 2, no traceback); the run keeps its last checkpoint.
"""

from __future__ import annotations

import datetime
import os

import torch

from ..errors import UserError

__all__ = ["Dist", "PeerLost", "from_env"]


class PeerLost(UserError):
    """A collective of a data-parallel run failed: another rank died, hung past the timeout, or
    never joined."""


LOST = False  # set once a collective has failed: the process group is broken for good


def _lost(rank: int, world: int, e: BaseException) -> PeerLost:
    global LOST
    LOST = True
    first = next((ln.strip() for ln in str(e).splitlines() if ln.strip()), type(e).__name__)
    first = first if len(first) <= 200 else first[:197] + "..."
    return PeerLost(
        f"rank {rank} of {world}: the data-parallel run lost another rank ({first}); stopping. "
        "The run keeps its last checkpoint: continue it with --resume"
    )


class Dist:
    """This process's place in a data-parallel run (rank, world size) and its collectives."""

    def __init__(self, rank: int, world: int):
        self.rank, self.world = int(rank), int(world)

    @property
    def main(self) -> bool:
        return self.rank == 0

    def share(self, n: int) -> slice:
        """This rank's contiguous share of ``n`` items (the first ``n % world`` ranks get one
        more)."""
        base, extra = divmod(int(n), self.world)
        lo = self.rank * base + min(self.rank, extra)
        return slice(lo, lo + base + (1 if self.rank < extra else 0))

    def _collective(self, fn, *args, **kw):
        """``fn(*args, **kw)``, a collective; :class:`PeerLost` when it fails (a peer died or
        timed out: the backend raises a RuntimeError, torch's DistError included)."""
        try:
            return fn(*args, **kw)
        except RuntimeError as e:
            raise _lost(self.rank, self.world, e) from None

    def sum_(self, t: torch.Tensor) -> torch.Tensor:
        """In place: the sum over the ranks."""
        import torch.distributed as td

        self._collective(td.all_reduce, t, op=td.ReduceOp.SUM)
        return t

    def max_(self, t: torch.Tensor) -> torch.Tensor:
        """In place: the maximum over the ranks."""
        import torch.distributed as td

        self._collective(td.all_reduce, t, op=td.ReduceOp.MAX)
        return t

    def average_grads(self, params) -> None:
        """Every parameter's gradient replaced by its mean over the ranks (missing gradients
        count as zeros, so that every rank sends the same layout)."""
        grads = []
        for p in params:
            if p.grad is None:
                p.grad = torch.zeros_like(p)
            grads.append(p.grad)
        if not grads:
            return
        flat = torch.cat([g.reshape(-1) for g in grads])
        self.sum_(flat).div_(self.world)
        o = 0
        for g in grads:
            g.copy_(flat[o : o + g.numel()].view_as(g))
            o += g.numel()

    def barrier(self) -> None:
        import torch.distributed as td

        self._collective(td.barrier)

    def close(self) -> None:
        """Leaves the process group at the end of a run that finished on every rank (NCCL warns
        of, and may leak, a group still open at exit): all ranks meet first, so that none tears
        its group down while another still uses it (seen once with gloo: a rank aborted in its
        teardown). After an error the group is left to the process's exit: a peer may never
        arrive."""
        import torch.distributed as td

        if td.is_initialized():
            self._collective(td.barrier)
            td.destroy_process_group()


def from_env(device: str) -> tuple[Dist | None, str]:
    """(Dist, this rank's device) when started by ``torchrun`` with WORLD_SIZE > 1 (the process
    group is initialised: NCCL for cuda, gloo for cpu; a CUDA rank takes cuda:LOCAL_RANK), else
    (None, device)."""
    world = int(os.environ.get("WORLD_SIZE", "1") or 1)
    if world <= 1:
        return None, device
    import torch.distributed as td

    rank = int(os.environ.get("RANK", "0"))
    if device.startswith("cuda"):
        local = int(os.environ.get("LOCAL_RANK", "0"))
        torch.cuda.set_device(local)
        device = f"cuda:{local}"
    if not td.is_initialized():
        timeout = datetime.timedelta(seconds=float(os.environ.get("WARPNERF_DIST_TIMEOUT", 600)))
        try:
            td.init_process_group("nccl" if device.startswith("cuda") else "gloo", timeout=timeout)
        except RuntimeError as e:  # a peer that never came, a port taken (DistError included)
            raise _lost(rank, world, e) from None
    return Dist(rank, world), device
