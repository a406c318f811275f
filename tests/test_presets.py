"""`--preset cpu` (train/presets.py): the preset sets its values, flags given explicitly win (also
when they equal the default), `default`/`gpu` are today's defaults, config.json records the
preset and configs from before it still load, and a CPU run with GPU-sized settings prints one
line suggesting the preset (not with the preset, not on CUDA)."""

from __future__ import annotations

import dataclasses
import json

import pytest

from warpnerf.cli import main
from warpnerf.cli.parser import build_parser
from warpnerf.cli.train import nerf_config_from_args
from warpnerf.train.nerf_config import NeRFConfig, VolSDFConfig
from warpnerf.train.presets import NERF_PRESETS, SDF_PRESETS, cpu_hint, step_seconds
from warpnerf.train.sdf import SDFConfig


def _nerf(*argv, model="nerf"):
    args = build_parser().parse_args(["train", model, "--data", "builtin", "--out", "x", *argv])
    return nerf_config_from_args(args)


def _sdf_kwargs(monkeypatch, *argv) -> dict:
    """The SDFConfig `train sdf` builds from ``argv`` (the trainer replaced by a recorder)."""
    import warpnerf.train.sdf as sdf

    seen = {}

    def record(cfg, *a, **kw):
        seen["cfg"] = cfg
        keys = ("step", "seconds", "chamfer", "vertices", "faces")
        return {**dict.fromkeys(keys, 0), "eikonal_residual_box": {"mean": 0.0}}

    monkeypatch.setattr(sdf, "train_sdf", record)
    assert main(["train", "sdf", "--points", "builtin", "--out", "unused", *argv]) == 0
    return seen["cfg"]


@pytest.mark.parametrize("field", ["mlp", "hash"])
def test_cpu_preset_sets_its_values(field):
    cfg = _nerf("--preset", "cpu", "--field", field)
    want = NERF_PRESETS["cpu"][field]
    assert want and {k: getattr(cfg, k) for k in want} == want
    assert cfg.preset == "cpu"
    # every other setting stays the default
    base = NeRFConfig(field=field, device=cfg.device)
    others = {f.name for f in dataclasses.fields(NeRFConfig)} - set(want) - {"preset"}
    assert {k: getattr(cfg, k) for k in others} == {k: getattr(base, k) for k in others}


@pytest.mark.parametrize("field", ["volsdf", "hash_sdf"])
def test_cpu_preset_volsdf(field):
    cfg = _nerf("--preset", "cpu", "--field", field, model="volsdf")
    want = NERF_PRESETS["cpu"][field]
    assert {k: getattr(cfg, k) for k in want} == want
    assert isinstance(cfg, VolSDFConfig) and cfg.pos_freqs == (want.get("pos_freqs") or 6)
    if field == "volsdf":  # the fine samples come from the preset, --fine-samples wins
        assert cfg.n_fine == want["n_fine"]
        assert _nerf("--preset", "cpu", "--fine-samples", "40", model="volsdf").n_fine == 40
    assert _nerf("--field", field, model="volsdf").n_fine == 64  # (no preset: the default)


def test_explicit_flags_win_even_at_the_default_value():
    cfg = _nerf("--preset", "cpu", "--field", "hash", "--batch", "1024", "--hash-log2-size",
                "15", "--iters", "7", "--grid-res", "64")  # fmt: skip
    assert (cfg.batch, cfg.hash_log2_size, cfg.iters, cfg.grid_res) == (1024, 15, 7, 64)
    assert cfg.hash_levels == NERF_PRESETS["cpu"]["hash"]["hash_levels"]  # not given: preset


@pytest.mark.parametrize("preset", [None, "default", "gpu"])
def test_default_and_gpu_presets_are_the_defaults(preset):
    """On a CPU the default preset is the configs' defaults; gpu is them with the measured GPU
    recipe of its table (the default on CUDA, tests/test_recipe_losses.py)."""
    argv = ["--field", "hash"] + (["--preset", preset] if preset else [])
    cfg = _nerf(*argv)
    want = dataclasses.replace(NeRFConfig(field="hash", device=cfg.device), preset=cfg.preset)
    if preset == "gpu":
        want = dataclasses.replace(want, **NERF_PRESETS["gpu"]["hash"])
    assert cfg == want
    assert cfg.preset == (preset or "default")


def test_sdf_preset(monkeypatch):
    cfg = _sdf_kwargs(monkeypatch, "--preset", "cpu", "--field", "hash", "--batch", "4096")
    want = dict(SDF_PRESETS["cpu"]["hash"], batch=4096)
    assert {k: getattr(cfg, k) for k in want} == want
    assert cfg.preset == "cpu" and cfg.n_random == 4096
    cfg = _sdf_kwargs(monkeypatch, "--preset", "cpu")  # mlp
    want = SDF_PRESETS["cpu"]["mlp"]
    assert {k: getattr(cfg, k) for k in want} == want
    assert cfg.skip == max(1, want["n_layers"] // 2) and cfg.n_random == want["batch"]
    assert _sdf_kwargs(monkeypatch) == SDFConfig(n_random=SDFConfig.batch)


def test_old_configs_without_the_field_load():
    d = NeRFConfig(preset="cpu").to_dict()
    assert d["preset"] == "cpu" and NeRFConfig.from_dict(d).preset == "cpu"
    del d["preset"]
    assert NeRFConfig.from_dict(d).preset == "default"
    s = SDFConfig().to_dict()
    del s["preset"]
    assert SDFConfig.from_dict(s).preset == "default"
    with pytest.raises(Exception, match="preset"):
        NeRFConfig.from_dict({**d, "preset": "tpu"}, where="config.json")


def test_config_json_records_the_preset_and_no_hint(tmp_path, monkeypatch, capsys):
    """A real (tiny) run with --preset cpu: config.json says so, the run loads without the field
    too, and no CPU hint is printed."""
    from warpnerf.train.nerf import load_run

    monkeypatch.chdir(tmp_path)
    rc = main(["train", "nerf", "--data", "builtin", "--out", "r", "--preset", "cpu",
               "--iters", "1", "--builtin-size", "8", "--batch", "16", "--samples", "4",
               "--layers", "2", "--width", "16", "--val-images", "0", "--quiet",
               "--no-tensorboard"])  # fmt: skip
    assert rc == 0
    err = capsys.readouterr().err
    assert "--preset cpu" not in err
    saved = json.loads((tmp_path / "r" / "config.json").read_text())
    assert saved["preset"] == "cpu" and saved["batch"] == 16 and saved["lr"] == 5e-3
    # a run written before the field existed
    del saved["preset"]
    (tmp_path / "r" / "config.json").write_text(json.dumps(saved))
    cfg, _, _ = load_run(tmp_path / "r")
    assert cfg.preset == "default"


def test_resume_refuses_a_preset(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "config.json").write_text(json.dumps(NeRFConfig().to_dict()))
    rc = main(["train", "nerf", "--out", "r", "--resume", "--iters", "5", "--preset", "cpu"])
    err = capsys.readouterr().err
    assert rc == 2 and "--preset" in err and "Traceback" not in err


def test_cpu_hint_rule():
    for field in ("mlp", "hash"):
        line = cpu_hint(NeRFConfig(field=field))  # today's defaults on the CPU
        assert line and "--preset cpu" in line and "\n" not in line
        assert step_seconds(NeRFConfig(field=field)) > 1
        assert cpu_hint(NeRFConfig(field=field, preset="cpu")) is None
        assert cpu_hint(NeRFConfig(field=field, device="cuda")) is None
        small = _nerf("--preset", "cpu", "--field", field)
        assert step_seconds(small) < 1
        assert cpu_hint(dataclasses.replace(small, preset="gpu")) is None  # small: no line
    assert cpu_hint(VolSDFConfig(field="hash_sdf")) is not None


def test_cli_prints_the_hint_once_on_stderr(tmp_path, monkeypatch, capsys):
    """GPU-sized defaults on the CPU: one line on stderr after the first step (the trainer replaced
    by a recorder: a real step at these sizes takes seconds); none with --preset cpu."""
    import warpnerf.train.nerf as nerf

    def record(cfg, *a, **kw):
        for hook in kw.get("hooks", []):  # (the loop's start: config and data checked)
            hook.on_start(None, 0)
        for hook in kw.get("hooks", []):  # (the note speaks after the first step)
            hook.on_step(1, {"step": [1], "seconds": [5.0]}, 1e-3)
        print(json.dumps({"preset": cfg.preset}))
        return {"step": [1], "psnr": [0.0], "val_psnr": [], "seconds": [0.0]}

    monkeypatch.setattr(nerf, "train_nerf", record)
    monkeypatch.chdir(tmp_path)
    for quiet in ([], ["--quiet"]):
        assert main(["train", "nerf", "--data", "builtin", "--field", "hash", "--out", "a",
                     *quiet]) == 0  # fmt: skip
        out, err = capsys.readouterr()
        lines = [x for x in err.splitlines() if "--preset cpu" in x]
        assert len(lines) == 1 and lines[0].startswith("warpnerf: note: --device cpu"), err
        assert "Traceback" not in err and "Warning" not in err
    assert main(["train", "nerf", "--data", "builtin", "--field", "hash", "--out", "b",
                 "--preset", "cpu"]) == 0  # fmt: skip
    assert "--preset cpu" not in capsys.readouterr().err


def test_step_estimate_follows_the_surface_fields_differences():
    """hash_sdf's CPU step estimate: forward differences (its default since 2026-12-03) cost the
    measured 0.58x of central ones; the cpu preset keeps the default, and the flag overrides it."""
    from warpnerf.fields.hash_sdf import FORWARD_DIFFERENCES_COST

    central = VolSDFConfig(field="hash_sdf", device="cpu", sdf_gradient="central")
    forward = VolSDFConfig(field="hash_sdf", device="cpu", sdf_gradient="forward")
    default = VolSDFConfig(field="hash_sdf", device="cpu")
    assert step_seconds(forward) == pytest.approx(FORWARD_DIFFERENCES_COST * step_seconds(central))
    assert step_seconds(default) == pytest.approx(step_seconds(forward))
    preset = _nerf("--preset", "cpu", "--field", "hash_sdf", model="volsdf")
    assert preset.resolve().sdf_gradient == "forward"
    assert _nerf("--preset", "cpu", "--field", "hash_sdf", "--sdf-gradient", "central",
                 model="volsdf").sdf_gradient == "central"  # fmt: skip
