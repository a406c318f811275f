"""Configs drive the command line (warpnerf.options): every flag's default is its config field's
default, every flag reaches its field, config.json round-trips, and the demos' flags come from
the same fields."""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import sys
from pathlib import Path

import pytest

from warpnerf.cli.parser import build_parser
from warpnerf.cli.train import nerf_config_from_args
from warpnerf.fields.settings import VOLSDF
from warpnerf.options import add_flags, flag_of, from_flags, option
from warpnerf.train.box_fit import BoxFitConfig
from warpnerf.train.nerf_config import GRID, NeRFConfig, VolSDFConfig
from warpnerf.train.presets import NERF_PRESETS, SDF_PRESETS, preset_fields
from warpnerf.train.sdf import SDFConfig

ROOT = Path(__file__).resolve().parents[1]

# command -> (config class, its flag groups, the fields whose flag defaults to None (not given):
# those a --preset sets too, train/presets.py)
_NERF_UNSET = ("data", "iters", "device", *preset_fields(NERF_PRESETS))
COMMANDS = {
    "nerf": (NeRFConfig, GRID, (*_NERF_UNSET, "field")),  # (--field not given: auto)
    "volsdf": (VolSDFConfig, VOLSDF, _NERF_UNSET),
    "sdf": (SDFConfig, (), ("points", "iters", "device", *preset_fields(SDF_PRESETS))),
    "box": (BoxFitConfig, (), ("iters",)),
}

# flags whose help a command rewrites (train nerf --field lists only the fields it trains; see
# tests/test_cli_first_hour.py): their help names each choice the command offers
OWN_HELP = {("nerf", "field")}


def _subparser(model):
    args = build_parser().parse_args(["train", model, "--out", "x"])
    return args, args.subparser


def _flag_fields(cls, groups):
    return [
        f
        for f in dataclasses.fields(cls)
        if f.metadata.get("flag") is not None and (not f.metadata["groups"] or
                                                   set(f.metadata["groups"]) & set(groups))
    ]  # fmt: skip


@pytest.mark.parametrize("model", COMMANDS)
def test_flag_defaults_are_the_config_defaults(model):
    cls, groups, unset = COMMANDS[model]
    args, sub = _subparser(model)
    actions = {a.dest: a for a in sub._actions}
    fields = _flag_fields(cls, groups)
    assert fields
    for f in fields:
        assert f.name in actions, f"{cls.__name__}.{f.name} has no flag on `train {model}`"
        a = actions[f.name]
        want = None if f.name in unset else f.default
        assert a.default == want, (model, f.name, a.default, f.default)
        assert (f.metadata["negate"] or flag_of(f)) in a.option_strings
        if (model, f.name) in OWN_HELP:  # the command writes this flag's help itself
            assert all(c in a.help for c in a.metavar.strip("{}").split(",")), a.help
        else:
            assert f.metadata["help"] and f.metadata["help"] in a.help
    # the parsed defaults build exactly the config's defaults
    kw = from_flags(cls, args, groups=groups)
    cfg = cls(**kw)
    assert cfg == cls(), model


@pytest.mark.parametrize("model", COMMANDS)
def test_every_flag_reaches_its_field(model):
    cls, groups, _ = COMMANDS[model]
    fields = _flag_fields(cls, groups)
    argv, want = ["train", model, "--out", "x"], {}
    for i, f in enumerate(fields):
        kind = f.type.replace(" | None", "")
        if kind == "bool":
            if f.metadata["negate"]:
                argv.append(f.metadata["negate"])
                want[f.name] = False
            else:
                argv.append(flag_of(f) if not f.default else "--no-" + flag_of(f)[2:])
                want[f.name] = not f.default
            continue
        if f.metadata["choices"]:
            v = [c for c in f.metadata["choices"] if c != f.default][-1]
        elif f.name == "device":
            v = "cuda"
        elif kind == "str":
            v = f"value{i}"
        elif kind == "int":
            v = (f.default or 0) + 2 + 2 * i  # even (grid_res), positive, distinct
        else:
            v = (f.default or 0.0) + 0.25 + i
        argv += [flag_of(f), str(v)]
        want[f.name] = v
    args = build_parser().parse_args(argv)
    got = from_flags(cls, args, groups=groups)
    assert got == want


@pytest.mark.parametrize(
    "argv, flag",
    [
        (["train", "nerf", "--out", "x", "--samples", "0"], "--samples"),
        (["train", "nerf", "--out", "x", "--seed", str(2**40)], "--seed"),
        (["train", "nerf", "--out", "x", "--near", "nan"], "--near"),
        (["train", "nerf", "--out", "x", "--field", "tree"], "--field"),
        (["train", "volsdf", "--out", "x", "--beta", "-1"], "--beta"),
        (["train", "sdf", "--out", "x", "--layers", "x"], "--layers"),
        (["train", "box", "--out", "x", "--max-seconds", "-5"], "--max-seconds"),
    ],
)
def test_bad_flag_values_are_refused_by_name(argv, flag, capsys):
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(argv)
    assert e.value.code == 2
    assert flag in capsys.readouterr().err


def test_volsdf_defaults_and_groups():
    _, sub = _subparser("volsdf")
    dests = {a.dest for a in sub._actions}
    assert {"beta", "beta_min", "learn_beta", "eikonal_weight", "c2f_every"} <= dests
    assert "grid_res" in dests  # the occupancy grid of --field hash_sdf
    _, sub = _subparser("nerf")
    assert "beta" not in {a.dest for a in sub._actions}
    args = build_parser().parse_args(["train", "volsdf", "--data", "builtin", "--out", "x"])
    assert (args.field, args.coarse_fine) == ("volsdf", True)
    # (--pos-freqs and --fine-samples are "not given" on the command line: a preset may set them)
    cfg = nerf_config_from_args(args)
    assert (cfg.field, cfg.pos_freqs, cfg.n_fine) == ("volsdf", 6, 64)
    assert VolSDFConfig().n_fine == 64 and NeRFConfig().n_fine == 0


@pytest.mark.parametrize("cls", [NeRFConfig, VolSDFConfig, SDFConfig, BoxFitConfig])
def test_config_json_round_trips(cls):
    cfg = cls()
    again = cls.from_dict(cfg.to_dict(), where="config.json")
    assert again.to_dict() == cfg.to_dict()


def test_volsdf_run_config_loads_as_nerf_config():
    d = VolSDFConfig().to_dict()
    assert NeRFConfig.from_dict(d, where="config.json").to_dict() == d


def test_resume_names_the_flag_not_the_field(tmp_path, capsys):
    from warpnerf.cli.parser import main

    code = main(["train", "nerf", "--out", str(tmp_path / "r"), "--resume", "--iters", "5",
                 "--samples", "8", "--layers", "2"])  # fmt: skip
    assert code == 2
    err = capsys.readouterr().err
    assert "drop --layers, --samples" in err and "n_coarse" not in err


def _demo_args():
    spec = importlib.util.spec_from_file_location("_nerf_args", ROOT / "demos" / "_nerf_args.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("_nerf_args", mod)
    spec.loader.exec_module(mod)
    return mod


def test_demo_flags_come_from_the_config():
    na = _demo_args()
    p = na.parser("demo", "out/x")
    args = p.parse_args([])
    for name, v in na.DEFAULTS.items():
        assert getattr(args, name) == v
    cfg = na.config(args)
    assert (cfg.iters, cfg.n_coarse, cfg.n_layers, cfg.width, cfg.skip) == (500, 32, 4, 64, 2)
    assert cfg.data == NeRFConfig.data and cfg.batch == NeRFConfig.batch
    args = p.parse_args(["--samples", "7", "--layers", "6", "--lr", "0.5"])
    cfg = na.config(args)
    assert (cfg.n_coarse, cfg.n_layers, cfg.skip, cfg.lr) == (7, 6, 3, 0.5)


def test_option_machinery_on_a_small_config():
    @dataclasses.dataclass
    class Small:
        steps: int = option(3, "steps", check="positive")
        rate: float | None = option(None, "a rate", check="positive")
        mode: str = option("a", "mode", choices=("a", "b"))
        on: bool = option(True, "on", negate="--off")
        hidden: int = option(7, flag=None)
        extra: int = option(1, "extra", groups=("x",))

    p = argparse.ArgumentParser()
    add_flags(p, Small, unset=("steps",))
    a = p.parse_args([])
    assert (a.steps, a.rate, a.mode, a.on) == (None, None, "a", True)
    assert not hasattr(a, "hidden") and not hasattr(a, "extra")
    assert Small(**from_flags(Small, a)) == Small()
    a = p.parse_args(["--steps", "9", "--rate", "0.5", "--mode", "b", "--off"])
    assert Small(**from_flags(Small, a)) == Small(steps=9, rate=0.5, mode="b", on=False)
    p = argparse.ArgumentParser()
    add_flags(p, Small, groups=("x",), defaults={"extra": 5})
    assert p.parse_args([]).extra == 5


# the tools that take a run: command line -> (config class, the library function each field
# feeds, as {field: (function, its parameter)})
def _tools():
    from warpnerf.cli.tool_configs import EvalConfig, ExportConfig, MeshConfig, RenderConfig
    from warpnerf.export import export_pointcloud
    from warpnerf.train.nerf_eval import evaluate_geometry, evaluate_run, render_run

    ev = {
        "split": (evaluate_run, "split"),
        "max_images": (evaluate_run, "max_images"),
        "renderer": (evaluate_run, "renderer"),
        "device": (evaluate_run, "device"),
        "mesh_resolution": (evaluate_geometry, "resolution"),
        "geometry_points": (evaluate_geometry, "points"),
        "geometry_views": (evaluate_geometry, "views"),
        "clean": (evaluate_geometry, "clean"),
        "level": (evaluate_geometry, "level"),
    }
    rd = {
        "path": (render_run, "path"),
        "frames": (render_run, "frames"),
        "size": (render_run, "size"),
        "device": (render_run, "device"),
        "renderer": (render_run, "renderer"),
    }
    ex = {
        "views": (export_pointcloud, "views"),
        "stride": (export_pointcloud, "stride"),
        "min_opacity": (export_pointcloud, "min_opacity"),
        "device": (export_pointcloud, "device"),
    }
    return {
        ("eval", "RUN"): (EvalConfig, ev),
        ("render", "RUN"): (RenderConfig, rd),
        ("mesh", "RUN", "--out", "m.ply"): (MeshConfig, {}),
        ("export", "RUN", "cameras", "--out", "c.json"): (ExportConfig, ex),
    }  # fmt: skip


@pytest.mark.parametrize("argv", list(_tools()), ids=lambda a: a[0])
def test_run_tools_flags_come_from_their_configs(argv):
    """eval, render, mesh and export: every flag is a config field's, with its default and help,
    and the library function behind a field defaults to the same value."""
    import inspect

    cls, feeds = _tools()[argv]
    args = build_parser().parse_args(list(argv))
    fields = _flag_fields(cls, ())
    assert fields
    sub = {
        a.dest: a for a in build_parser()._subparsers._group_actions[0].choices[argv[0]]._actions
    }
    for f in fields:
        a = sub[f.name]
        assert f.metadata["help"] in a.help and flag_of(f) in a.option_strings
        if not f.metadata.get("required"):
            assert getattr(args, f.name) == f.default, (argv[0], f.name)
        if f.name in feeds:
            fn, param = feeds[f.name]
            assert inspect.signature(fn).parameters[param].default == f.default, (fn, param)
    flags = {s for a in sub.values() for s in a.option_strings} - {"-h", "--help"}
    assert flags == {flag_of(f) for f in fields}  # no hand-written flag beside the config's
    assert cls(**{k: v for k, v in vars(args).items() if k in {f.name for f in fields}})
