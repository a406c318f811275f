"""train/step_times.py: a run's per-step clock split into the median step and what the slower
steps add (warm-up, grid updates, checkpoints, the rest)."""

import pytest

from warpnerf.train.step_times import step_times


def _clock(dts_ms):
    t, out = 0.0, []
    for d in dts_ms:
        t += d / 1000.0
        out.append(t)
    return out


def test_the_excess_lands_in_its_class():
    warm, grid_every, ckpt_every, n = 5, 16, 100, 400
    dts = []
    for i in range(n):
        done = i + 1
        d = 10.0
        if i < warm:
            d = 500.0
        elif (done - 1) % grid_every == 0:
            d = 30.0
        elif done > 1 and (done - 1) % ckpt_every == 0:
            d = 210.0
        dts.append(d)
    dts[201] = 60.0  # one other slow step (done 202 is neither a grid nor a checkpoint step)
    r = step_times(_clock(dts), grid_every, ckpt_every, warm)
    assert r["steps"] == n and r["median_ms"] == pytest.approx(10.0)
    assert r["mean_ms"] == pytest.approx(sum(dts) / n)
    ex = r["excess_ms_per_step"]
    n_grid = sum(1 for i in range(warm, n) if i % grid_every == 0)
    n_ckpt = sum(1 for i in range(warm, n) if i % grid_every and i % ckpt_every == 0 and i)
    assert ex["warm"] == pytest.approx(warm * 490.0 / n)
    assert ex["grid"] == pytest.approx(n_grid * 20.0 / n)
    assert ex["checkpoint"] == pytest.approx(n_ckpt * 200.0 / n)
    assert ex["other"] == pytest.approx(50.0 / n)
    # the classes add up to the mean's excess over the median
    assert sum(ex.values()) == pytest.approx(r["mean_ms"] - r["median_ms"])
    assert r["slow_steps"] == {"warm": warm, "grid": n_grid, "checkpoint": n_ckpt, "other": 1}
    assert r["max_ms"] == 500.0 and r["p90_ms"] == pytest.approx(10.0)


def test_empty_and_gridless_histories():
    assert step_times([]) == {"steps": 0}
    r = step_times(_clock([10.0, 20.0, 10.0]), grid_every=0, ckpt_every=0, warm=0)
    assert r["steps"] == 3 and r["median_ms"] == pytest.approx(10.0)
    assert r["excess_ms_per_step"]["other"] == pytest.approx(10.0 / 3)
    assert r["excess_ms_per_step"]["grid"] == 0.0


def test_a_checkpoint_on_a_grid_step_counts_as_the_checkpoint():
    """With grid_every 16 and ckpt_every 32 every checkpoint's step is a grid step too: the
    (far larger) checkpoint cost is what the class names."""
    dts = []
    for i in range(200):
        done = i + 1
        d = 10.0
        if done > 1 and (done - 1) % 32 == 0:
            d = 110.0
        elif (done - 1) % 16 == 0:
            d = 12.0
        dts.append(d)
    r = step_times(_clock(dts), grid_every=16, ckpt_every=32, warm=0)
    n_ckpt = sum(1 for i in range(1, 200) if i % 32 == 0)
    n_grid = sum(1 for i in range(200) if i % 16 == 0) - n_ckpt
    assert r["slow_steps"]["checkpoint"] == n_ckpt and r["slow_steps"]["grid"] == 0
    assert r["excess_ms_per_step"]["checkpoint"] == pytest.approx(n_ckpt * 100.0 / 200)
    assert r["excess_ms_per_step"]["grid"] == pytest.approx(n_grid * 2.0 / 200)
