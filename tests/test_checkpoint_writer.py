"""Periodic checkpoints written by a background thread (train/loop.py): a run that fails keeps
the last periodic checkpoint complete on disk and resumes from it exactly; a failed write stops
the run with its error; the state written is the step's, not a later one."""

import json

import pytest
import torch

from warpnerf.train import NeRFConfig, train_nerf
from warpnerf.train import loop as loop_mod
from warpnerf.train.nerf import NeRFTask

CFG = dict(batch=128, n_coarse=16, n_layers=2, width=16, skip=1, pos_freqs=3, dir_freqs=1,
           near=1.0, far=4.0, builtin_size=12, val_images=0, ckpt_every=2, lr=5e-3,
           lr_final=5e-4, lr_decay_steps=7)  # fmt: skip


def _quiet(*a, **k):
    pass


def test_a_failed_run_keeps_its_last_checkpoint_and_resumes_exactly(tmp_path, monkeypatch):
    straight = train_nerf(NeRFConfig(iters=7, **CFG), tmp_path / "a", progress=False, log=_quiet)
    real = NeRFTask.loss

    def failing(self, step):
        if step == 5:  # after the background checkpoints of steps 2 and 4
            raise RuntimeError("boom")
        return real(self, step)

    monkeypatch.setattr(NeRFTask, "loss", failing)
    with pytest.raises(RuntimeError, match="boom"):
        train_nerf(NeRFConfig(iters=7, **CFG), tmp_path / "b", progress=False, log=_quiet)
    ckpt = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=True)
    assert ckpt["step"] == 4 and ckpt["history"]["step"] == [1, 2, 3, 4]
    assert json.loads((tmp_path / "b" / "history.json").read_text())["step"] == [1, 2, 3, 4]
    monkeypatch.setattr(NeRFTask, "loss", real)
    resumed = train_nerf(NeRFConfig(iters=7), tmp_path / "b", resume=True, progress=False,
                         log=_quiet)  # fmt: skip
    assert resumed["loss"] == straight["loss"]
    a = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=True)
    b = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=True)
    for k, v in a["fields"]["coarse"].items():
        assert torch.equal(v, b["fields"]["coarse"][k]), k


def test_the_written_state_is_the_steps_own(tmp_path, monkeypatch):
    """The thread writes a copy: training that goes on while it writes (held back here until
    the run ends) does not leak into the file."""
    import threading

    gate = threading.Event()
    real = loop_mod.save_checkpoint
    written = {}

    def slow(path, state):
        if path.name == "checkpoint.pt" and state["step"] == 2:
            gate.wait(30)
            coarse = state["fields"]["coarse"]
            written["w"] = coarse[sorted(coarse)[0]].clone()
        real(path, state)

    monkeypatch.setattr(loop_mod, "save_checkpoint", slow)
    seen = {}
    real_after = NeRFTask.after_step

    def after(self, step, history):
        real_after(self, step, history)
        if step + 1 == 2:
            sd = self.model.coarse.state_dict()
            seen["w"] = sd[sorted(sd)[0]].detach().clone()
        if step + 1 == 4:
            gate.set()  # (by now two more steps changed the weights)

    monkeypatch.setattr(NeRFTask, "after_step", after)
    train_nerf(NeRFConfig(iters=5, **CFG), tmp_path / "r", progress=False, log=_quiet)
    assert torch.equal(written["w"], seen["w"])
    final = torch.load(tmp_path / "r" / "checkpoint.pt", weights_only=True)["fields"]["coarse"]
    assert not torch.equal(final[sorted(final)[0]], seen["w"])  # (training did go on)


def test_a_failed_background_write_stops_the_run(tmp_path, monkeypatch):
    real = loop_mod.save_checkpoint

    def failing(path, state):
        if state["step"] == 2:
            raise OSError(28, "No space left on device")
        real(path, state)

    monkeypatch.setattr(loop_mod, "save_checkpoint", failing)
    with pytest.raises(OSError, match="No space left"):
        train_nerf(NeRFConfig(iters=7, **CFG), tmp_path / "r", progress=False, log=_quiet)
    assert not (tmp_path / "r" / "checkpoint.pt").exists()  # nothing half-written
