"""TensorBoard event files beside history.json: read back with TensorBoard's own reader, the
same numbers as the history, continued without overlap on resume, off with --no-tensorboard,
and a run folder whose `tensorboard` is not warpnerf's refused before anything is written."""

from __future__ import annotations

import json
import os

import pytest

from warpnerf.cli.parser import main
from warpnerf.train.logs import TENSORBOARD_DIR, TensorBoardLog

pytest.importorskip("tensorboard", reason="the dev extra's tensorboard reads the event files")

TINY = ["--data", "builtin", "--batch", "64", "--samples", "8", "--layers", "2", "--width", "16",
        "--builtin-size", "16", "--quiet"]  # fmt: skip


def _scalars(logdir) -> dict:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    ea = EventAccumulator(str(logdir), size_guidance={"scalars": 0, "images": 0})
    ea.Reload()
    tags = ea.Tags()
    out = {t: [(e.step, e.value) for e in ea.Scalars(t)] for t in tags["scalars"]}
    out["images"] = tags["images"]
    return out


def test_training_logs_what_the_history_holds(tmp_path):
    run = tmp_path / "r"
    assert main(["train", "nerf", *TINY, "--iters", "6", "--val-every", "3", "--val-images", "1",
                 "--log-every", "1", "--out", str(run)]) == 0  # fmt: skip
    hist = json.loads((run / "history.json").read_text())
    s = _scalars(run / TENSORBOARD_DIR)
    assert [st for st, _ in s["train/loss"]] == hist["step"] == list(range(1, 7))
    assert [v for _, v in s["train/loss"]] == pytest.approx(hist["loss"], rel=1e-6)
    assert [v for _, v in s["train/psnr"]] == pytest.approx(hist["psnr"], rel=1e-6)
    assert [st for st, _ in s["val/val_psnr"]] == [3, 6]
    assert [v for _, v in s["val/val_psnr"]] == pytest.approx(hist["val_psnr"], rel=1e-6)
    assert len(s["train/lr"]) == 6 and len(s["train/step_ms"]) == 5
    assert set(s["images"]) == {"val/rgb", "val/depth"}
    # a resumed run continues the curves: steps 1..9 once each
    assert (
        main(
            [
                "train",
                "nerf",
                "--out",
                str(run),
                "--resume",
                "--iters",
                "9",
                "--quiet",
                "--log-every",
                "1",
            ]
        )
        == 0
    )
    s = _scalars(run / TENSORBOARD_DIR)
    assert [st for st, _ in s["train/loss"]] == list(range(1, 10))
    assert len(os.listdir(run / TENSORBOARD_DIR)) == 2


def test_a_resume_purges_what_was_logged_past_the_checkpoint(tmp_path):
    """Steps logged after the last checkpoint (an interrupted run) are replaced, not doubled."""

    def log(first, last, start, value):
        h = TensorBoardLog(tmp_path, log_every=1)
        h.on_start(None, start)
        hist = {"step": [], "loss": [], "seconds": []}
        for st in range(first, last + 1):
            hist["step"].append(st), hist["loss"].append(value), hist["seconds"].append(st)
            h.on_step(st, hist, 1e-3)
        h.close()

    log(1, 6, 0, 1.0)  # logged up to 6, checkpointed at 4
    log(5, 8, 4, 2.0)  # resumed from step 4
    s = _scalars(tmp_path / TENSORBOARD_DIR)["train/loss"]
    assert s == [(1, 1.0), (2, 1.0), (3, 1.0), (4, 1.0), (5, 2.0), (6, 2.0), (7, 2.0), (8, 2.0)]


def test_no_tensorboard_and_foreign_folders(tmp_path, capsys):
    run = tmp_path / "r"
    assert main(["train", "nerf", *TINY, "--iters", "2", "--val-images", "0", "--no-tensorboard",
                 "--out", str(run)]) == 0  # fmt: skip
    assert not (run / TENSORBOARD_DIR).exists()
    bad = tmp_path / "b"
    bad.mkdir()
    (tmp_path / "elsewhere").mkdir()
    (bad / TENSORBOARD_DIR).symlink_to(tmp_path / "elsewhere")
    rc = main(["train", "nerf", *TINY, "--iters", "2", "--val-images", "0", "--out", str(bad)])
    assert rc == 2 and "is not a folder warpnerf made" in capsys.readouterr().err
    assert sorted(os.listdir(bad)) == [TENSORBOARD_DIR]  # nothing written
    assert os.listdir(tmp_path / "elsewhere") == []


def test_scalars_every_n_steps(tmp_path):
    """--log-every N (default 10): one record every N steps, step_ms the mean since the last."""
    run = tmp_path / "r"
    assert main(["train", "nerf", *TINY, "--iters", "25", "--val-images", "0",
                 "--out", str(run)]) == 0  # fmt: skip
    hist = json.loads((run / "history.json").read_text())
    s = _scalars(run / TENSORBOARD_DIR)
    assert [st for st, _ in s["train/loss"]] == [10, 20]
    assert [v for _, v in s["train/loss"]] == pytest.approx([hist["loss"][9], hist["loss"][19]])
    sec = hist["seconds"]
    assert s["train/step_ms"][0][1] == pytest.approx(1e3 * (sec[19] - sec[9]) / 10, rel=1e-5)
