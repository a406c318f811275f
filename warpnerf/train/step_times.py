"""Where a training run's time went, step by step, from its history's clock (``history["seconds"]``,
recorded after each step's sync): :func:`step_times`, which ``scripts/time_to_quality.py`` adds to
each row. A profiled step (``scripts/profile_train_step.py``) is a median of steady steps; a
run's mean also pays its warm-up, the occupancy grid's updates, the checkpoints' host copies and
new captured shapes, and this says how much of each."""

from __future__ import annotations

import statistics

__all__ = ["step_times"]


def step_times(seconds, grid_every: int = 0, ckpt_every: int = 0, warm: int = 50) -> dict:
    """Where a run's training time went, from its history's ``seconds`` (the training clock
    after each step, validation and snapshots excluded; one value a step from step 1): the
    mean and the median milliseconds a step, the 90th and 99th percentiles, and the mean's
    excess over the median (ms a step) split by the kind of step that paid it. The classes,
    first match wins: ``warm`` (the first ``warm`` steps: compilation, the first captures),
    ``checkpoint`` (the step after a periodic checkpoint, whose host copy that step's clock
    counts; before ``grid``: with grid_every 16 and ckpt_every 1000 every other checkpoint
    falls on a grid update, and the checkpoint costs far more), ``grid`` (the steps that
    update the occupancy grid: ``(done - 1) % grid_every == 0``), ``other`` (the rest: new
    captured shapes among them). Excess = the step's time
    minus the median, summed over the class, over all steps."""
    t = [float(v) for v in seconds]
    if not t:
        return {"steps": 0}
    dt = [1000.0 * (b - a) for a, b in zip([0.0] + t[:-1], t)]
    n = len(dt)
    order = sorted(dt)
    med = statistics.median(dt)

    def pct(q):
        return order[min(n - 1, int(q * (n - 1) + 0.5))]

    excess = dict.fromkeys(("warm", "checkpoint", "grid", "other"), 0.0)
    slow = dict.fromkeys(excess, 0)  # steps over twice the median, by class
    for i, d in enumerate(dt):
        done = i + 1
        if i < warm:
            k = "warm"
        elif ckpt_every > 0 and done > 1 and (done - 1) % ckpt_every == 0:
            k = "checkpoint"
        elif grid_every > 0 and (done - 1) % grid_every == 0:
            k = "grid"
        else:
            k = "other"
        excess[k] += d - med
        slow[k] += d > 2.0 * med
    return {
        "steps": n, "mean_ms": sum(dt) / n, "median_ms": med, "p90_ms": pct(0.9),
        "p99_ms": pct(0.99), "max_ms": order[-1],
        "excess_ms_per_step": {k: v / n for k, v in excess.items()},
        "slow_steps": slow, "warm": warm, "grid_every": grid_every, "ckpt_every": ckpt_every,
    }  # fmt: skip
