"""The one training loop: every trainer (NeRF and VolSDF, neural SDF from points, box fit) is a
:class:`Task` run by :func:`run_loop`.

The loop owns the duties every trainer shares, so no task re-implements them:

- step counting from 0 or from a checkpoint's step up to ``iters``;
- the learning rate, ``lr * (lr_final / lr) ** min(step / decay_steps, 1)``, set on every
  parameter group before each step;
- the optimiser (built by the task: its betas and eps are the task's), and its state across
  ``--resume``;
- the non-finite guard: the loss and every gradient are checked after ``backward()`` (one fused
  max-norm, no host sync of its own: the flags are read together with the loss at the step's one
  sync); the first non-finite value raises :class:`~warpnerf.errors.Diverged` and nothing of
  that step is saved, so the run keeps its last good checkpoint;
- history (``step``, ``loss``, ``seconds`` and the task's own terms), training time that excludes
  validation, ``--max-seconds`` (counted per invocation);
- periodic validation (every ``val_every`` steps, at the last step and when time runs out);
- SIGINT/SIGTERM (finish the step, checkpoint it, raise :class:`~warpnerf.errors.Interrupted`);
- atomic checkpoints and ``history.json`` every ``ckpt_every`` steps (written by a background
  thread from a host copy of the step's state), at the end and when stopping (written before the
  loop returns); a resumed run continues bit-exactly on CPU;
- snapshots for time-to-quality curves: at the first step whose training time reaches each of
  ``snapshot_seconds``, a copy of the checkpoint goes to ``snapshots/t<seconds>s.pt`` (writing it
  does not count as training time). With step-based schedules (learning rate, beta, grid) the
  state at a snapshot is the state a run stopped by ``--max-seconds`` at that time would end with,
  so one run gives the whole curve.
- provenance: ``run.json`` in the run folder gets one session per invocation (command line,
  start time and steps, software versions and git commit, device, world size; see
  :mod:`~warpnerf.train.provenance`), a resume appending its own.

A task provides the model side: its parameters and optimiser, one step's loss, what its
checkpoint holds besides the loop's keys, and optionally a validation and progress-bar text.
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from ..errors import Interrupted
from ..options import Settings, check_at_least, option, section_of
from ..outputs import (
    check_foreign,
    load_weights,
    make_folder,
    save_checkpoint,
    write_json,
)
from .divergence import nonfinite_flags, raise_if_diverged
from .provenance import finish_session, start_session
from .run_folder import BackgroundWriter, claim_run, lock_run, resume_checks, to_host

__all__ = [
    "Task", "LoopConfig", "LoopSettings", "run_loop", "lr_at", "lock_run", "resume_checks",
    "claim_run", "parse_snapshots", "snapshot_name", "SNAPSHOTS", "LoopHook", "set_lr",
    "bare_step", "one_step", "stop_requests",
    "read_terms", "nonfinite_flags", "to_host", "BackgroundWriter", "adam", "sync_sites",
]  # fmt: skip

# checkpoint keys the loop writes and reads (a task's state adds its own)
LOOP_KEYS = ("step", "optimizer", "history")


@contextlib.contextmanager
def stop_requests():
    """Yields a dict whose "signum" becomes the number of the first SIGINT/SIGTERM received;
    the previous handlers come back on exit. Outside the main thread nothing is installed
    (Python only delivers signals there)."""
    state = {"signum": None}
    if threading.current_thread() is not threading.main_thread():
        yield state
        return

    def handler(signum, frame):
        if state["signum"] is None:
            state["signum"] = signum

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield state
    finally:
        for s, h in old.items():
            signal.signal(s, h)


@dataclass
class LoopConfig(Settings):
    """The loop's section of every kind of run's config, declared once: each config class
    derives from it (``with_defaults(LoopConfig, iters=..., ...)`` for its own defaults); its
    flags are shown under TITLE, and :meth:`LoopSettings.of` reads exactly these fields.
    ``lr``/``lr_final`` None: resolved by the run (its field's defaults); ``lr_decay_steps`` 0:
    the first invocation's ``iters`` (saved)."""

    TITLE = "training loop"

    iters: int = option(20000, "total steps", check="positive")
    lr: float | None = option(None, "Adam's learning rate", check="positive")
    lr_final: float | None = option(
        None, "lr decays exponentially to this at lr_decay_steps (default lr/10)",
        check="positive",
    )  # fmt: skip
    lr_decay_steps: int = option(0, flag=None)
    max_seconds: float = option(
        0.0, "stop after this much training time in this invocation (a resume gets a fresh "
        "budget; 0: run all --iters)", check="nonnegative",
    )  # fmt: skip
    ckpt_every: int = option(1000, "steps between checkpoints", check="positive")
    seed: int = option(0, "random seed", check="seed")

    def check_section(self, fail) -> None:
        """The loop section's ranges; ``fail(name, rule)`` builds the error to raise."""
        import math

        check_at_least(self, fail, 1, "iters", "ckpt_every")
        check_at_least(self, fail, 0, "lr_decay_steps")
        if not (math.isfinite(self.max_seconds) and self.max_seconds >= 0):
            raise fail("max_seconds", f"must be finite and >= 0, got {self.max_seconds}")
        for name in ("lr", "lr_final"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise fail(name, f"must be finite and positive, got {v}")
        if not 0 <= self.seed < 2**31:
            raise fail("seed", f"must be an integer in [0, 2^31), got {self.seed}")


@dataclass
class LoopSettings:
    """The loop's settings at run time: a config's :class:`LoopConfig` section (resolved), the
    progress bar's text and the snapshot times."""

    iters: int
    lr: float
    lr_final: float
    lr_decay_steps: int = 0  # 0: decay over all ``iters``
    max_seconds: float = 0.0  # 0: no limit
    ckpt_every: int = 500
    val_every: int = 0  # 0: no periodic validation
    desc: str = "train"
    snapshot_seconds: tuple = ()  # training seconds at which to keep a copy of the checkpoint

    @classmethod
    def of(cls, cfg: LoopConfig, desc: str, snapshots: str = "", **override) -> LoopSettings:
        """The loop settings of a task config: its :class:`LoopConfig` section (``override``
        wins); ``snapshots``, "30,60,120", gives ``snapshot_seconds``."""
        loop = section_of(cfg, LoopConfig)
        kw = {k: getattr(loop, k) for k in ("iters", "lr", "lr_final", "lr_decay_steps",
                                            "max_seconds", "ckpt_every")}  # fmt: skip
        if snapshots:
            kw["snapshot_seconds"] = parse_snapshots(snapshots)
        return cls(**(kw | override), desc=desc)


SNAPSHOTS = "snapshots"  # the run's sub-folder of snapshot checkpoints
MAX_SNAPSHOTS = 64


def parse_snapshots(text: str) -> tuple:
    """Seconds from "5,15,30" (sorted, distinct, each in (0, 1e7], at most 64); ValueError
    otherwise."""
    import math

    try:
        vals = [float(t) for t in str(text).split(",") if t.strip()]
    except ValueError:
        msg = f"expected seconds separated by commas, e.g. 15,60,300; got {text!r}"
        raise ValueError(msg) from None
    if not vals or len(vals) > MAX_SNAPSHOTS:
        raise ValueError(f"expected 1 to {MAX_SNAPSHOTS} values, got {len(vals)}")
    if not all(math.isfinite(v) and 0 < v <= 1e7 for v in vals):
        raise ValueError(f"each value must be in (0, 1e7] seconds, got {text!r}")
    return tuple(sorted(set(vals)))


def snapshot_name(seconds: float) -> str:
    """The file (relative to the run) of the snapshot at ``seconds``: snapshots/t60s.pt."""
    return f"{SNAPSHOTS}/t{seconds:g}s.pt"


def set_lr(opt, lr: float) -> None:
    """Sets the step's learning rate on every parameter group (a group's ``lr_scale``, e.g. the
    pose corrections', scales it). A group whose rate is a tensor (an optimiser captured in a
    CUDA graph reads it from there) gets the value written into that tensor."""
    for group in opt.param_groups:
        value = lr * group.get("lr_scale", 1.0)
        if isinstance(group["lr"], torch.Tensor):
            group["lr"].fill_(value)
        else:
            group["lr"] = value


def lr_at(s: LoopSettings, step: int) -> float:
    """The learning rate of step ``step`` (0-based): exponential from lr to lr_final over
    ``lr_decay_steps`` steps, constant after."""
    decay = s.lr_decay_steps if s.lr_decay_steps > 0 else s.iters
    return s.lr * (s.lr_final / s.lr) ** min(step / max(decay, 1), 1.0)


class Task:
    """What a trainer plugs into :func:`run_loop`. Override :meth:`parameters`, :meth:`loss` and
    :meth:`state`; the other methods have defaults."""

    history_keys: tuple = ()  # the task's history lists, created empty for a new run
    validation_keys: tuple = ()  # the figures :meth:`validate` returns

    def parameters(self) -> list:
        """The trained tensors (each once)."""
        raise NotImplementedError

    def optimizer(self, params: list, lr: float) -> torch.optim.Optimizer:
        return adam(params, lr=lr)

    def loss(self, step: int) -> tuple:
        """(loss, terms) of step ``step`` (0-based): draws its batch, renders or evaluates, and
        returns the scalar loss to minimise and a dict of terms for the history (0-dim tensors,
        read at the step's one sync, or Python numbers)."""
        raise NotImplementedError

    def train_step(self, step: int, opt, params) -> tuple | None:
        """The whole step in one go, or None for the usual one (:meth:`loss`, then the loop's
        backward, divergence flags and optimiser step). A task that returns (loss, terms,
        flags) has done all of that itself (a step captured in a CUDA graph: the loss's
        backward, :func:`nonfinite_flags` of ``params`` and ``opt.step()`` are in it)."""
        return None

    def after_step(self, step: int, history: dict) -> None:
        """After the optimiser step of ``step`` and its history entry (projections such as
        clamping, logging); before any checkpoint."""

    def record(self, history: dict, terms: dict) -> None:
        """Appends this step's terms (host numbers) to the history (default: by name)."""
        for k, v in terms.items():
            history.setdefault(k, []).append(v)

    def validate(self, step: int) -> dict | None:
        """Validation figures after ``step`` steps (appended to the history by name), or None
        when the task has none."""
        return None

    def eval_weights(self):
        """A context manager: while open, the task's model holds the weights a saved run is
        shown with (NeRF with ``--ema``: the average), the trained ones restored exactly after
        (the live viewer's frames; default: the trained weights, nothing to do)."""
        return contextlib.nullcontext()

    def validation_text(self, history: dict) -> str:
        """The log line's text after a validation (default: the latest figures by name)."""
        return ", ".join(f"{k} {history[k][-1]:.2f}" for k in self.validation_keys)

    def state(self) -> dict:
        """What the checkpoint holds besides the loop's keys (weights, generators, config)."""
        raise NotImplementedError

    def postfix(self, history: dict) -> dict:
        """The progress bar's text after a step."""
        return {"loss": f"{history['loss'][-1]:.4g}"}


class LoopHook:
    """Something that watches a training from outside the task (TensorBoard logs, the live
    viewer): :func:`run_loop` calls it in the training thread, between steps, and the time it
    takes is not counted as training time (like validation). A hook must not change the task's
    state or draw from its random generators, so a run with hooks trains exactly as one
    without."""

    def on_start(self, task: Task, step: int) -> None:
        """Before the first step (``step``: the step the run starts or resumes from)."""

    def on_step(self, step: int, history: dict, lr: float) -> None:
        """After step ``step`` (1-based: steps done) has been recorded in ``history``."""

    def on_validation(self, step: int, figures: dict, task: Task) -> None:
        """After a validation at ``step`` with the figures it returned."""

    def close(self) -> None:
        """When the loop ends, however it ends (also on errors)."""


def read_terms(loss, terms: dict, flags, dist=None):
    """Host values of the loss, the tensor terms and the divergence flags, in one transfer (in a
    data-parallel run: the loss and terms averaged over the ranks, a flag set if any rank's
    is, in one all-reduce)."""
    names = [k for k, v in terms.items() if isinstance(v, torch.Tensor)]
    parts = [loss.detach().reshape(1)] + [terms[k].detach().reshape(1) for k in names]
    parts.append(flags)
    dev = loss.device
    vals = torch.cat([p.to(dev, torch.float64) for p in parts])
    if dist is not None:
        dist.sum_(vals)
        vals[: 1 + len(names)] /= dist.world
    vals = vals.tolist()
    out = {k: (v if not isinstance(v, torch.Tensor) else None) for k, v in terms.items()}
    for k, v in zip(names, vals[1 : 1 + len(names)]):
        out[k] = v
    return vals[0], out, vals[1 + len(names) :]


def _own_implementation(opt, saved):
    """The saved optimiser state with this optimiser's implementation flags (fused, foreach,
    capturable) in its groups: ``load_state_dict`` takes the groups' flags from the state, so a
    checkpoint of a CUDA run (fused Adam) would otherwise stay fused on CPU, and a CPU one
    unfused on CUDA; loading with the right flags also places Adam's step counters right."""
    if not isinstance(saved, dict) or not isinstance(saved.get("param_groups"), list):
        return saved  # (load_weights reports a malformed state)
    groups = []
    for g_saved, g_now in zip(saved["param_groups"], opt.param_groups):
        if isinstance(g_saved, dict):
            g_saved = dict(g_saved)
            for k in ("fused", "foreach", "capturable"):
                if k in g_now:
                    g_saved[k] = g_now[k]
            if isinstance(g_now.get("lr"), torch.Tensor) or isinstance(g_saved.get("lr"),
                                                                        torch.Tensor):  # fmt: skip
                # a captured optimiser reads its rate from its own tensor (set every step)
                g_saved["lr"] = g_now["lr"]
        groups.append(g_saved)
    groups += saved["param_groups"][len(groups) :]
    return {**saved, "param_groups": groups}


def run_loop(
    task: Task,
    s: LoopSettings,
    *,
    run: Path | None,
    checkpoint: str = "checkpoint.pt",
    resume_from: dict | None = None,
    progress: bool = False,
    log=print,
    where=None,
    hooks=(),
) -> dict:
    """Trains ``task`` up to ``s.iters`` steps; returns the history.

    ``run`` None: no files are written and signals keep their handlers. ``resume_from``: a
    checkpoint dict (the task has already restored its own state from it) whose optimiser state,
    history and step the loop continues from. ``where`` names the run in messages (default
    ``run``).
    """
    where = where if where is not None else (run if run is not None else "the fit")
    params = task.parameters()
    opt = task.optimizer(params, s.lr)
    history = {"step": [], "loss": [], **{k: [] for k in task.history_keys}, "seconds": []}
    start = 0
    if resume_from is not None:
        load_weights(opt, _own_implementation(opt, resume_from["optimizer"]),
                     Path(run) / checkpoint, "optimizer state")  # fmt: skip
        history, start = resume_from["history"], resume_from["step"]
    with contextlib.ExitStack() as closing:
        for hook in hooks:
            closing.callback(hook.close)
        return _loop(task, s, run, checkpoint, resume_from, progress, log, where, hooks,
                     params, opt, history, start)  # fmt: skip


def _loop(task, s, run, checkpoint, resume_from, progress, log, where, hooks, params, opt,
          history, start):  # fmt: skip
    elapsed0 = history["seconds"][-1] if history["seconds"] else 0.0
    t0, val_time = time.perf_counter(), 0.0  # training time excludes validation
    cuda = any(p.is_cuda for p in params)
    dist = getattr(task, "dist", None)  # data-parallel (train/distributed.py): rank 0 writes
    main = dist is None or dist.main
    hooks = hooks if main else ()
    bar = None
    if progress and main:
        from tqdm import tqdm

        bar = tqdm(total=s.iters, initial=start, desc=s.desc, unit="step", disable=None)

    writer = BackgroundWriter()

    def save(done, name=checkpoint, background=False):
        """The checkpoint (and history.json) of step ``done``; ``background``: a host copy
        written by a thread while training goes on (the periodic ones: their fsync'd writes
        cost 0.3 s each on the H100/H200 machines, 2-3 % of a lego run's time); otherwise written
        before this returns, after any background write (final, stopping, snapshots)."""
        state = {**task.state(), "step": done, "optimizer": opt.state_dict(), "history": history}
        path = Path(run) / name

        def write(state=state):
            save_checkpoint(path, state)
            if name == checkpoint:
                write_json(Path(run) / "history.json", state["history"])

        if background:
            writer.submit(write, to_host(state))
        else:
            writer.wait()
            write()

    pending = [b for b in s.snapshot_seconds if b > elapsed0] if run is not None and main else []
    if pending:  # before any work: refuse to replace files warpnerf did not write
        make_folder(Path(run) / SNAPSHOTS, "snapshots folder")
        check_foreign([Path(run) / snapshot_name(b) for b in pending])

    record = None  # RUN/run.json: how the run was made, one session per invocation
    if run is not None and main:
        device = params[0].device if params else "cpu"
        record = start_session(run, device, start, s.iters, dist, resume=resume_from is not None)
    tv = time.perf_counter()
    for hook in hooks:
        hook.on_start(task, start)
    val_time += time.perf_counter() - tv
    signals = stop_requests() if run is not None else contextlib.nullcontext({"signum": None})
    with writer, signals as stop:
        halt = None
        for step in range(start, s.iters):
            lr = lr_at(s, step)
            set_lr(opt, lr)
            # the last step's autograd graph must be gone before this step runs: a captured
            # step's gradients may not accumulate into nodes made on another stream
            loss = terms = flags = None
            loss, terms, flags = one_step(task, opt, params, step, dist)
            done = step + 1
            # the step's one host sync: the loss, the terms and the divergence flags (a step
            # that diverged is never saved: the run keeps its last good checkpoint)
            loss_v, values, bad = read_terms(loss, terms, flags, dist)
            raise_if_diverged(bad, done, loss_v, where, lr)
            if cuda:
                torch.cuda.synchronize()
            seconds = elapsed0 + time.perf_counter() - t0 - val_time
            # data-parallel: a stop is decided once a step, from this shared value (a handler
            # may set stop["signum"] at any moment; the ranks must all decide the same)
            halt = stop["signum"]
            if dist is not None:  # rank 0's clock, and a stop asked of any rank, for all
                shared = torch.tensor([seconds if main else 0.0, halt or 0],
                                      dtype=torch.float64, device=loss.device)  # fmt: skip
                seconds, signum = dist.max_(shared).tolist()
                halt = int(signum) or None
            history["step"].append(done)
            history["loss"].append(loss_v)
            task.record(history, values)
            history["seconds"].append(seconds)
            task.after_step(step, history)
            if hooks:  # (not training time)
                tv = time.perf_counter()
                for hook in hooks:
                    hook.on_step(done, history, lr)
                val_time += time.perf_counter() - tv
            if pending and seconds >= pending[0]:  # not counted as training time
                tv = time.perf_counter()
                while pending and seconds >= pending[0]:
                    save(done, snapshot_name(pending.pop(0)))
                val_time += time.perf_counter() - tv
            if bar is not None:
                bar.update(1)
                bar.set_postfix(task.postfix(history))
            out_of_time = s.max_seconds > 0 and seconds - elapsed0 >= s.max_seconds
            if main and s.val_every and (done % s.val_every == 0 or done == s.iters or out_of_time):
                tv = time.perf_counter()
                figures = task.validate(done)
                if figures is not None:
                    history.setdefault("val_step", []).append(done)
                    for k, v in figures.items():
                        history.setdefault(k, []).append(v)
                    for hook in hooks:
                        hook.on_validation(done, figures, task)
                val_time += time.perf_counter() - tv
                if figures is not None:
                    log(f"step {done}: {task.validation_text(history)}, {seconds:.0f} s")
            if dist is None:  # (one process: a signal during validation counts for this step)
                halt = stop["signum"]
            stopping = out_of_time or halt is not None
            last = done == s.iters or stopping
            if run is not None and main and (done % s.ckpt_every == 0 or last):
                save(done, background=not last)
            if out_of_time:
                log(f"stopping at step {done}: --max-seconds {s.max_seconds} reached")
                break
            if halt is not None:  # SIGINT/SIGTERM: the step is done and checkpointed
                break
    if bar is not None:
        bar.close()
    halt = halt if dist is not None else stop["signum"]
    if record is not None:
        outcome = "interrupted" if halt is not None else "finished"
        if halt is None and history["step"] and history["step"][-1] < s.iters:
            outcome = "stopped"  # --max-seconds
        finish_session(run, record, history["step"][-1] if history["step"] else start, outcome)
    if halt is not None:
        raise Interrupted(halt, history["step"][-1], run)
    return history


def adam(params, capturable: bool = False, cls=torch.optim.Adam, **kw) -> torch.optim.Adam:
    """Adam, fused (one multi-tensor kernel per step instead of a dozen launches: the hash-field
    step is host-bound) when every parameter is a floating CUDA tensor; PyTorch's default
    implementation otherwise (CPU runs). Both compute the same update and share the state dict
    layout, so a checkpoint resumes on either. ``capturable`` (CUDA): the step can be captured in
    a CUDA graph; its learning rate is then a device tensor (:func:`set_lr` writes into it).
    ``cls``: a subclass of Adam built the same way (``train.optim.LazyAdam``)."""
    params = list(params)
    tensors = [p for g in params for p in (g["params"] if isinstance(g, dict) else [g])]
    fused = bool(tensors) and all(p.is_cuda and p.is_floating_point() for p in tensors)
    if capturable and fused:
        kw["lr"] = torch.tensor(float(kw.get("lr", 1e-3)), device=tensors[0].device)
        return cls(params, fused=True, capturable=True, **kw)
    return cls(params, fused=fused or None, **kw)


def one_step(task: Task, opt, params: list, step: int, dist=None) -> tuple:
    """(loss, terms, divergence flags) of one optimisation step: the task's whole step
    (:meth:`Task.train_step`, e.g. a replayed CUDA graph) or its loss, backward (gradients
    averaged over the ranks of ``dist``), flags and the optimiser's step."""
    whole = task.train_step(step, opt, params)
    if whole is not None:
        return whole
    loss, terms = task.loss(step)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    if dist is not None:
        dist.average_grads(params)
    flags = nonfinite_flags(loss, params)
    opt.step()
    return loss, terms, flags


def bare_step(task: Task, opt, step: int, lr: float | None = None,
              history: dict | None = None) -> torch.Tensor:  # fmt: skip
    """One optimisation step of ``task`` without the loop's bookkeeping (no checks, files or
    syncs): what the profiling and measuring tools time. Returns the loss tensor. ``history``
    (a dict): the step's terms are read (the loop's one sync a step) and recorded there, as the
    loop records them (tasks that size the next step from this one's counts need it)."""
    if lr is not None:
        set_lr(opt, lr)
    loss, terms, _ = one_step(task, opt, task.parameters(), step)
    if history is not None:
        _, values, _ = read_terms(loss, terms, loss.new_zeros(2))
        task.record(history, values)
    return loss


def sync_sites(fn) -> dict:
    """Runs ``fn()`` on CUDA under ``torch.cuda.set_sync_debug_mode("warn")`` and returns how
    often each innermost warpnerf line (file:line) made a synchronising PyTorch call."""
    import collections
    import traceback
    import warnings

    sites = collections.Counter()

    def record(message, category, filename, lineno, file=None, line=None):
        if "synchronizing" not in str(message):  # (the debug mode's own notice)
            return
        frames = [f for f in traceback.extract_stack() if "/warpnerf/" in f.filename]
        names = [f"{f.filename.split('/warpnerf/')[-1]}:{f.lineno}" for f in frames[-3:]]
        sites[" < ".join(names[::-1]) or f"{filename}:{lineno}"] += 1

    torch.cuda.synchronize()
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = record
        torch.cuda.set_sync_debug_mode("warn")
        try:
            fn()
        finally:
            torch.cuda.set_sync_debug_mode(0)
    return dict(sites)
