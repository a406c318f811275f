"""--snapshots: copies of the checkpoint at given training seconds (time-to-quality curves)."""

from __future__ import annotations

import pytest
import torch

from warpnerf.cli.parser import main
from warpnerf.train.loop import parse_snapshots, snapshot_name
from warpnerf.train.nerf import load_run

TINY = ["--data", "builtin", "--field", "hash", "--hash-levels", "2", "--hash-log2-size", "8",
        "--hash-max-res", "16", "--grid-res", "8", "--builtin-size", "16", "--batch", "64",
        "--val-images", "0", "--quiet"]  # fmt: skip


def test_parse_snapshots():
    assert parse_snapshots("60, 5,15,5") == (5.0, 15.0, 60.0)
    for bad in ("", "a,b", "0", "-1", "nan", "inf", ",".join(["1"] * 65 + ["2"] * 0) + ",x"):
        with pytest.raises(ValueError):
            parse_snapshots(bad)
    assert snapshot_name(60.0) == "snapshots/t60s.pt" and snapshot_name(0.5) == "snapshots/t0.5s.pt"


def test_snapshots_are_the_state_at_their_time(tmp_path):
    """A snapshot due at a tiny time is written after the first step (its own step and history,
    weights that differ from the end's); one never reached is not written; eval loads either;
    bad values are one-line user errors."""
    run = tmp_path / "r"
    assert main(["train", "nerf", *TINY, "--iters", "6", "--out", str(run),
                 "--snapshots", "1e-6,1e6"]) == 0  # fmt: skip
    assert (run / "snapshots" / "t1e-06s.pt").is_file()
    assert not (run / "snapshots" / "t1e+06s.pt").exists()
    _, early, ck = load_run(run, snapshot=1e-6)
    _, final, ck_final = load_run(run)
    assert ck["step"] == 1 and len(ck["history"]["step"]) == 1 and ck_final["step"] == 6
    a = dict(early.coarse.named_parameters())
    b = dict(final.coarse.named_parameters())
    assert any(not torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(Exception, match="no snapshot at 30 s"):
        load_run(run, snapshot=30)
    assert main(["train", "nerf", *TINY, "--iters", "1", "--out", str(tmp_path / "b"),
                 "--snapshots", "1,x"]) == 2  # fmt: skip
    assert not (tmp_path / "b" / "checkpoint.pt").exists()


def test_snapshots_never_replace_foreign_files(tmp_path):
    run = tmp_path / "r"
    (run / "snapshots").mkdir(parents=True)
    (run / "snapshots" / "t1e-06s.pt").write_bytes(b"mine")
    assert main(["train", "nerf", *TINY, "--iters", "2", "--out", str(run),
                 "--snapshots", "1e-6"]) == 2  # fmt: skip
    assert (run / "snapshots" / "t1e-06s.pt").read_bytes() == b"mine"
