"""A first hour with the command line (issue 43, items 7, 9 and 12): `--resume` takes the flags
that started the run and refuses only changed ones, by name with both values; the Ctrl-C hint
spells the command that continues the run; the CPU note for GPU-sized settings gives the
measured first step and the checkpoint's size; `export cameras` and `eval` say where their
files went, and the demo's metrics.json carries the same provenance block as eval's."""

from __future__ import annotations

import json
import signal

import pytest

from warpnerf.cli.parser import main

# tiny `train nerf` / `train volsdf` / `train sdf` settings (tests/test_export.py, test_cli_demos)
NERF = ["--data", "builtin", "--field", "mlp", "--layers", "2", "--width", "16", "--samples", "8",
        "--builtin-size", "16", "--batch", "64", "--val-images", "0", "--quiet"]  # fmt: skip
VOLSDF = ["--data", "builtin", "--field", "hash_sdf", "--hash-levels", "3", "--hash-log2-size",
          "8", "--hash-max-res", "16", "--grid-res", "8", "--builtin-size", "16", "--batch", "64",
          "--val-images", "0", "--quiet"]  # fmt: skip
SDF = ["--points", "builtin", "--batch", "32", "--layers", "2", "--width", "32", "--pos-freqs",
       "2", "--resolution", "8", "--quiet"]  # fmt: skip


def _last_json(text: str) -> dict:
    return json.loads(text.strip().splitlines()[-1])


# ---- item 7: --resume with the original flags --------------------------------------------------


@pytest.fixture(scope="module")
def nerf_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("first_hour") / "r"
    assert main(["train", "nerf", *NERF, "--seed", "3", "--iters", "2", "--out", str(run)]) == 0
    return run


@pytest.mark.slow
def test_resume_accepts_the_flags_that_started_the_run(nerf_run, capsys):
    capsys.readouterr()
    code = main(["train", "nerf", *NERF, "--seed", "3", "--out", str(nerf_run), "--resume",
                 "--iters", "3"])  # fmt: skip
    out, err = capsys.readouterr()
    assert code == 0, err
    assert _last_json(out)["step"] == 3


@pytest.mark.slow
def test_resume_refuses_changed_flags_by_name_with_both_values(nerf_run, capsys):
    capsys.readouterr()
    code = main(["train", "nerf", *NERF, "--seed", "3", "--width", "32", "--lr", "0.01",
                 "--out", str(nerf_run), "--resume", "--iters", "9"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert "--lr (saved 0.0005, given 0.01)" in err and "--width (saved 16, given 32)" in err
    for same in ("--data", "--field", "--layers", "--samples", "--batch", "--seed"):
        assert f"{same} " not in err.split("drop", 1)[1].split("(only", 1)[0], (same, err)


@pytest.mark.slow
def test_resume_refuses_a_flag_given_at_its_default_that_the_run_changed(nerf_run, capsys):
    """--seed 0 is the parser's default; the run was started with --seed 3: given on the command
    line, it differs from the saved config and is refused (not silently replaced by 3)."""
    capsys.readouterr()
    code = main(["train", "nerf", "--seed", "0", "--out", str(nerf_run), "--resume", "--iters",
                 "9"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "--seed (saved 3, given 0)" in err


@pytest.mark.slow
def test_resume_with_the_preset_and_its_values(tmp_path, capsys):
    """A --preset cpu run resumes with --preset cpu (and any value the preset set, given
    explicitly); a preset value changed is refused with the saved one."""
    run = str(tmp_path / "p")
    base = ["--data", "builtin", "--field", "mlp", "--preset", "cpu", "--builtin-size", "16",
            "--val-images", "0", "--quiet"]  # fmt: skip
    assert main(["train", "nerf", *base, "--iters", "1", "--out", run]) == 0
    capsys.readouterr()
    assert main(["train", "nerf", *base, "--batch", "512", "--width", "64", "--out", run,
                 "--resume", "--iters", "2"]) == 0  # fmt: skip
    assert _last_json(capsys.readouterr().out)["step"] == 2
    assert main(["train", "nerf", *base, "--batch", "256", "--out", run, "--resume", "--iters",
                 "3"]) == 2  # fmt: skip
    assert "--batch (saved 512, given 256)" in capsys.readouterr().err
    assert main(["train", "nerf", "--data", "builtin", "--out", run, "--resume", "--iters", "3",
                 "--preset", "gpu"]) == 2  # fmt: skip
    assert "--preset (saved cpu, given gpu)" in capsys.readouterr().err


@pytest.mark.slow
def test_resume_accepts_the_original_flags_of_volsdf_and_sdf(tmp_path, capsys):
    v, s = str(tmp_path / "v"), str(tmp_path / "s")
    assert main(["train", "volsdf", *VOLSDF, "--iters", "1", "--out", v]) == 0
    assert main(["train", "volsdf", *VOLSDF, "--iters", "2", "--out", v, "--resume"]) == 0
    assert main(["train", "sdf", *SDF, "--iters", "1", "--out", s]) == 0
    assert main(["train", "sdf", *SDF, "--iters", "2", "--out", s, "--resume"]) == 0
    capsys.readouterr()
    assert main(["train", "sdf", *SDF, "--width", "16", "--iters", "3", "--out", s,
                 "--resume"]) == 2  # fmt: skip
    assert "--width (saved 32, given 16)" in capsys.readouterr().err


@pytest.mark.slow
def test_resume_accepts_the_original_flags_of_box(tmp_path, capsys):
    from tests._scene import write_box_folder

    write_box_folder(tmp_path / "bl", n_views=4, size=16)
    run, data = str(tmp_path / "b"), str(tmp_path / "bl")
    flags = ["--data", data, "--frames", "0", "--quiet", "--lr", "0.02"]
    assert main(["train", "box", *flags, "--iters", "1", "--out", run]) == 0
    assert main(["train", "box", *flags, "--iters", "2", "--out", run, "--resume"]) == 0
    capsys.readouterr()
    assert main(["train", "box", "--data", str(tmp_path / "other"), "--out", run, "--resume",
                 "--iters", "3"]) == 2  # fmt: skip
    assert "--data (saved " in capsys.readouterr().err


# ---- item 7: the Ctrl-C hint spells the command ------------------------------------------------


@pytest.mark.parametrize(
    "kind, module, name, flags",
    [
        ("nerf", "warpnerf.train.nerf", "train_nerf", NERF),
        ("volsdf", "warpnerf.train.nerf", "train_nerf", VOLSDF),
        ("sdf", "warpnerf.train.sdf", "train_sdf", SDF),
        ("box", "warpnerf.train.box_fit", "run_box_fit_on_folder", ["--data", "bl", "--quiet"]),
    ],
)
def test_the_ctrl_c_hint_names_the_train_command(kind, module, name, flags, tmp_path,
                                                 monkeypatch, capsys):  # fmt: skip
    """The trainer replaced by one interrupted at step 1: the message on stderr is the command
    that continues the run, with its subcommand and the --iters it was aiming at."""
    import importlib

    from warpnerf.errors import Interrupted

    def interrupted(*a, **kw):
        raise Interrupted(signal.SIGINT, 1, "r")

    monkeypatch.setattr(importlib.import_module(module), name, interrupted)
    monkeypatch.chdir(tmp_path)
    assert main(["train", kind, *flags, "--iters", "7", "--out", "r"]) == 128 + signal.SIGINT
    err = capsys.readouterr().err
    assert f"`warpnerf train {kind} --out r --resume --iters 7`" in err, err
    assert "..." not in err


# ---- item 9: the CPU note from a measured first step, with the checkpoint's size ---------------


def test_cpu_note_gives_the_measured_first_step_and_the_checkpoint_size(tmp_path, monkeypatch,
                                                                        capsys):  # fmt: skip
    """GPU-sized settings on the CPU: after the first step, one line with that step's time, the
    time for all --iters from it, and the checkpoint's size (the model's state and Adam's two
    moments of each parameter). The trainer is replaced by a recorder (a real step at these sizes
    takes seconds): a task of 1000 float32 parameters, a first step of 26 s."""
    import torch

    import warpnerf.train.nerf as nerf

    class Task:
        model = torch.nn.Linear(999, 1)  # 1000 parameters: 4 kB, + 8 kB of Adam's moments

        def parameters(self):
            return list(self.model.parameters())

    def record(cfg, *a, **kw):
        for hook in kw.get("hooks", []):
            hook.on_start(Task(), 0)
        assert "note" not in capsys.readouterr().err  # (nothing before the first step)
        for hook in kw.get("hooks", []):
            hook.on_step(1, {"step": [1], "seconds": [26.0]}, 1e-3)
        return {"step": [1], "psnr": [0.0], "val_psnr": [], "seconds": [26.0]}

    monkeypatch.setattr(nerf, "train_nerf", record)
    monkeypatch.chdir(tmp_path)
    assert main(["train", "nerf", "--data", "builtin", "--field", "hash", "--iters", "2",
                 "--out", "a", "--quiet"]) == 0  # fmt: skip
    lines = [x for x in capsys.readouterr().err.splitlines() if "note" in x]
    assert len(lines) == 1, lines
    line = lines[0]
    assert "the first step took 26 s" in line and "about 52 s for --iters 2" in line, line
    assert "each checkpoint is about 12 kB" in line and "--preset cpu" in line, line


@pytest.mark.slow
def test_checkpoint_size_estimate_matches_a_real_checkpoint(tmp_path):
    """The size the note gives is the size of the checkpoint training writes (within 10 %)."""
    from warpnerf.cli.parser import nerf_task_from_argv
    from warpnerf.train.presets import checkpoint_bytes

    flags = ["--data", "builtin", "--field", "hash", "--hash-levels", "4", "--hash-log2-size",
             "12", "--builtin-size", "16", "--batch", "64", "--val-images", "0",
             "--quiet"]  # fmt: skip
    _, task, _ = nerf_task_from_argv(["train", "nerf", *flags])
    guess = checkpoint_bytes(task)
    assert main(["train", "nerf", *flags, "--iters", "1", "--out", str(tmp_path / "r")]) == 0
    real = (tmp_path / "r" / "checkpoint.pt").stat().st_size
    assert abs(guess - real) < 0.1 * real, (guess, real)


def test_cpu_note_durations_read_in_the_right_unit():
    from warpnerf.train.nerf_config import NeRFConfig
    from warpnerf.train.presets import cpu_hint

    line = cpu_hint(NeRFConfig(field="hash", iters=2))  # the rule of thumb, before any step
    assert " 0 min" not in line and "for --iters 2" in line
    line = cpu_hint(NeRFConfig(field="hash", iters=30000), first_step=4.2, checkpoint=155e6)
    assert "the first step took 4.2 s, so about 35 h for --iters 30000" in line
    assert "each checkpoint is about 155 MB" in line


# ---- item 12: where the outputs went ---------------------------------------------------------


@pytest.fixture(scope="module")
def volsdf_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("first_hour_out") / "r"
    assert main(["train", "volsdf", *VOLSDF, "--iters", "2", "--out", str(run)]) == 0
    return run


@pytest.mark.slow
def test_export_cameras_says_where_the_images_went(volsdf_run, tmp_path, capsys):
    out = tmp_path / "ns" / "transforms.json"
    out.parent.mkdir()
    capsys.readouterr()
    assert main(["export", str(volsdf_run), "cameras", "--out", str(out)]) == 0
    res = _last_json(capsys.readouterr().out)
    assert res["images_written"] > 0 and res["images_folder"] == str(out.parent / "images")
    assert len(list((out.parent / "images").glob("*.png"))) == res["images_written"]


@pytest.mark.slow
def test_eval_says_where_metrics_json_went(volsdf_run, tmp_path, capsys):
    capsys.readouterr()
    assert main(["eval", str(volsdf_run), "--split", "train", "--max-images", "1"]) == 0
    res = _last_json(capsys.readouterr().out)
    where = volsdf_run / "eval_train" / "metrics.json"
    assert res["metrics_json"] == str(where) and where.is_file()
    assert res["out"] == str(volsdf_run / "eval_train")
    assert main(["eval", str(volsdf_run), "--split", "train", "--max-images", "1", "--out",
                 str(tmp_path / "e")]) == 0  # fmt: skip
    res = _last_json(capsys.readouterr().out)
    assert res["metrics_json"] == str(tmp_path / "e" / "metrics.json")
    assert (tmp_path / "e" / "metrics.json").is_file()


@pytest.mark.slow
def test_demo_metrics_have_the_provenance_block_of_eval(tmp_path):
    from warpnerf.box_demo import run_demo

    m = run_demo(tmp_path / "d", iters=2, size=16, frames=2, video_size=16, progress=False)
    saved = json.loads((tmp_path / "d" / "metrics.json").read_text())
    prov = saved["provenance"]
    assert prov == json.loads(json.dumps(m["provenance"]))
    for key in ("command", "time", "versions", "git", "device", "device_name"):
        assert key in prov, key
    for key in ("warpnerf", "python", "torch", "warp"):
        assert prov["versions"][key], key
