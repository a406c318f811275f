"""Run folders written by main at 986359d (before the method registry: a NeRF run's config.json
had no ``model`` key) load, evaluate, show, mesh and resume unchanged; each kind of run is found
by the registry of methods (warpnerf/train/methods.py), which a test extends with a toy method.

The fixtures in tests/data/runs_986359d were written by that tree on the CPU:
``train nerf --data builtin`` (mlp; hash with an 8^3 grid), ``train sdf --points builtin`` and
``train box`` on a 3-image Blender folder ``bl`` (made again here by ``make_blender``)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

from warpnerf.cli import main
from warpnerf.errors import UserError
from warpnerf.train.methods import (
    METHODS,
    LoadedRun,
    Method,
    method_of_config,
    method_of_run,
    method_of_task,
    register_method,
)  # fmt: skip

from .test_datasets import make_blender

FIXTURES = Path(__file__).parent / "data" / "runs_986359d"
KINDS = {"nerf_mlp": "nerf", "nerf_hash": "nerf", "sdf_mlp": "neural_sdf", "box": "box"}


@pytest.fixture
def runs(tmp_path, monkeypatch):
    """The fixtures copied into a fresh folder (the working directory, with the box's data)."""
    for name in KINDS:
        shutil.copytree(FIXTURES / name, tmp_path / name)
    make_blender(tmp_path / "bl", n=3, w=12, h=8)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _config(run) -> dict:
    return json.loads((Path(run) / "config.json").read_text())


def test_the_registry_finds_each_kind_of_old_run(runs):
    assert "model" not in _config(runs / "nerf_mlp")  # (written before the registry)
    for name, kind in KINDS.items():
        assert method_of_run(runs / name).name == kind
    with pytest.raises(UserError, match="not a kind of run warpnerf knows"):
        method_of_config({"model": "teapot"})
    with pytest.raises(UserError, match="no such run folder"):
        method_of_run(runs / "nothing")


@pytest.mark.parametrize("name", ["nerf_mlp", "nerf_hash"])
def test_old_nerf_runs_evaluate_show_mesh_and_resume(runs, name, capsys):
    from warpnerf.train import evaluate_run
    from warpnerf.viewer import load_scene

    run = runs / name
    assert evaluate_run(run, max_images=1)["psnr"] > 0
    scene = load_scene(run)
    assert scene.title.endswith(_config(run)["field"])
    mesh = ["mesh", str(run), "--resolution", "12", "--out", str(runs / f"{name}.ply"),
            "--no-screenshot"]  # fmt: skip
    capsys.readouterr()
    if main(mesh) != 0:  # three steps of training: the density's level set is where the tool says
        level = re.search(r"try --level ([0-9.e+-]+)", capsys.readouterr().err).group(1)
        assert main(mesh + ["--level", level]) == 0
    assert (runs / f"{name}.ply").is_file()
    capsys.readouterr()
    steps = json.loads((run / "history.json").read_text())["step"]
    assert main(["train", "nerf", "--out", str(run), "--resume", "--iters", "5", "--quiet"]) == 0
    after = json.loads((run / "history.json").read_text())["step"]
    assert after[: len(steps)] == steps and after[-1] == 5
    assert _config(run)["model"] == "nerf"  # the resumed run's config names its method


def test_old_sdf_and_box_runs_show_mesh_and_resume(runs, capsys):
    from warpnerf.viewer import load_scene

    assert "neural SDF" in load_scene(runs / "sdf_mlp").title
    assert "box fit" in load_scene(runs / "box").title
    assert main(["mesh", "sdf_mlp", "--resolution", "12", "--out", "s.ply",
                 "--no-screenshot"]) == 0  # fmt: skip
    capsys.readouterr()  # a box has no learned surface to extract
    assert main(["mesh", "box", "--resolution", "12", "--out", "b.ply", "--no-screenshot"]) != 0
    assert "box fit run has no surface" in capsys.readouterr().err
    assert main(["train", "sdf", "--out", "sdf_mlp", "--resume", "--iters", "5", "--quiet"]) == 0
    assert main(["train", "box", "--out", "box", "--resume", "--iters", "5", "--quiet",
                 "--frames", "0"]) == 0  # fmt: skip
    for name in ("sdf_mlp", "box"):
        assert json.loads((runs / name / "history.json").read_text())["step"][-1] == 5


def test_a_new_kind_of_run_is_one_registry_entry(runs, capsys):
    """A toy method in one registry entry: `train toy` exists with its config's flags, a run
    folder whose config.json names it is opened by its own loader for the viewer (here as a
    box: the fixture's volume), its live task is found by the task's class attribute, and the
    NeRF tools refuse it by name."""
    from dataclasses import asdict, dataclass

    from warpnerf.options import option
    from warpnerf.viewer import load_scene

    @dataclass
    class ToyConfig:
        iters: int = option(3, "toy steps", check="positive")
        size: float = option(1.0, "the toy's size", check="positive")

    def train_toy(cfg, out, resume=False, progress=True):
        Path(out).mkdir(exist_ok=True)
        (Path(out) / "config.json").write_text(json.dumps({"model": "toy", **asdict(cfg)}))
        return {"steps": cfg.iters, "resume": resume}

    box = METHODS["box"]
    toy = register_method(Method("toy", ("toy",), "toy fit", "box",
                                 open_run=lambda run, device=None: box.open_run(runs / "box"),
                                 open_task=lambda task: LoadedRun(None, task.volume),
                                 config=ToyConfig, train=train_toy))  # fmt: skip
    try:
        # `train toy` exists with the config's flags
        capsys.readouterr()
        assert main(["train", "toy", "--out", "t", "--iters", "5", "--size", "2", "--quiet"]) == 0
        assert json.loads(capsys.readouterr().out) == {"steps": 5, "resume": False}
        assert _config(runs / "t") == {"model": "toy", "iters": 5, "size": 2.0}
        assert method_of_run(runs / "t") is toy
        with pytest.raises(SystemExit):
            main(["train", "toy", "--help"])
        assert "the toy's size" in capsys.readouterr().out
        shutil.copytree(runs / "box", runs / "toy")
        cfg = _config(runs / "toy")
        (runs / "toy" / "config.json").write_text(json.dumps({**cfg, "model": "toy"}))
        assert method_of_run(runs / "toy") is toy
        assert load_scene(runs / "toy").title.endswith("box fit")
        with pytest.raises(ValueError, match="registered already"):
            register_method(toy)

        @dataclass
        class OutConfig:  # a field named like the generated command's --out
            out: str = option("x", "where")

        METHODS["toy2"] = Method(
            "toy2",
            ("toy2",),
            "toy 2",
            "box",
            open_run=toy.open_run,
            open_task=toy.open_task,
            config=OutConfig,
            train=train_toy,
        )
        try:
            with pytest.raises(ValueError, match=r"method 'toy2' \(OutConfig\) has fields "
                               "named like `train toy2`'s own flags: out"):  # fmt: skip
                main(["train", "toy", "--help"])
        finally:
            METHODS.pop("toy2", None)

        class ToyTask:
            method = "toy"
            volume = object()

        assert method_of_task(ToyTask()) is toy
        capsys.readouterr()  # it does not render through the NeRF pipeline's tools
        for cmd in (["eval", "toy"], ["render", "toy"], ["export", "toy", "cameras", "--out",
                                                          "c.json"]):  # fmt: skip
            assert main(cmd) != 0
            assert "a toy fit run" in capsys.readouterr().err
    finally:
        METHODS.pop("toy", None)
