"""Run configs are built from sections declared once (warpnerf.options.with_defaults,
section_of, section_declaring): the loop's section is shared by every kind of run, the fields'
sections live with the fields and are registered in their traits, each section checks its own
values and shows its flags under its title, and config.json keeps the flat keys older runs
have."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from warpnerf.cli.parser import build_parser
from warpnerf.errors import UserError
from warpnerf.fields.model import FIELD_TRAITS, FIELDS, FieldTraits, register_field
from warpnerf.fields.settings import HashConfig, MLPConfig, SDFDensityConfig
from warpnerf.options import (
    check_at_least,
    option,
    section_declaring,
    section_of,
    with_defaults,
)
from warpnerf.train.box_fit import BoxFitConfig
from warpnerf.train.loop import LoopConfig, LoopSettings
from warpnerf.train.nerf_config import (
    SECTIONS,
    CaptureConfig,
    DataConfig,
    NeRFConfig,
    ProposalConfig,
    SamplingConfig,
    SceneConfig,
    ValidationConfig,
    VolSDFConfig,
)
from warpnerf.train.recipe import LEGACY as RECIPE_LEGACY
from warpnerf.train.recipe import RecipeConfig
from warpnerf.train.sdf import SDFConfig

OLD_RUNS = Path(__file__).parent / "data" / "runs_986359d"
LOOP = [f.name for f in dataclasses.fields(LoopConfig)]
RUNS = {NeRFConfig: 20000, VolSDFConfig: 20000, SDFConfig: 2000, BoxFitConfig: 400}


@pytest.mark.parametrize("cls", list(RUNS))
def test_every_kind_of_run_takes_the_one_loop_section(cls):
    """The loop's fields are declared once (LoopConfig) and only their defaults differ."""
    assert issubclass(cls, LoopConfig)
    for k in cls.__mro__:
        if k.__module__ != LoopConfig.__module__ and "with_defaults" not in k.__qualname__:
            own = set(vars(k).get("__annotations__", {}))
            # a run's own class body re-declares none of them (with_defaults changes defaults)
            assert not own & set(LOOP) or k.__name__ == "LoopConfig", (k, own & set(LOOP))
    cfg = cls()
    assert cfg.iters == RUNS[cls]
    assert section_declaring(cls, "iters") is LoopConfig
    s = LoopSettings.of(cfg, "t", lr=1.0, lr_final=0.5)
    assert (s.iters, s.ckpt_every, s.max_seconds) == (cfg.iters, cfg.ckpt_every, cfg.max_seconds)
    with pytest.raises(UserError, match="'ckpt_every' must be >= 1, got 0"):
        cls.from_dict({**cfg.to_dict(), "ckpt_every": 0}, where="config.json")


def test_with_defaults_keeps_help_and_checks():
    @dataclasses.dataclass
    class Part:
        TITLE = "part"
        n: int = option(3, "how many", check="positive")
        name: str = option("a", "a name")

    Mine = with_defaults(Part, n=7, name=option("b", "another help", flag=None))
    f = {x.name: x for x in dataclasses.fields(Mine)}
    assert Mine().n == 7 and f["n"].metadata["help"] == "how many"
    assert f["n"].metadata["check"] == "positive" and f["name"].metadata["flag"] is None
    assert section_declaring(Mine, "n") is Part and Part().n == 3
    with pytest.raises(TypeError, match="no fields nope"):
        with_defaults(Part, nope=1)
    assert section_of(Mine(n=9), Part) == Part(n=9, name="b")

    class Cfg:
        n, m = 0, 5

    def fail(name, rule):
        return ValueError(f"{name} {rule}")

    check_at_least(Cfg, fail, 0, "n", "m")
    with pytest.raises(ValueError, match="m must be >= 6, got 5"):
        check_at_least(Cfg, fail, 6, "m", "n")


def test_nerf_config_is_its_sections_and_saves_the_old_flat_keys():
    names = [f.name for f in dataclasses.fields(NeRFConfig)]
    assert len(names) == len(set(names))
    for section in SECTIONS:
        assert issubclass(NeRFConfig, section)
        for f in dataclasses.fields(section):
            assert f.name in names
    # config.json: the keys a run written by 986359d has, plus the kind of run, field options
    # and the training recipe's section (issue 44), which an old run reads as it trained
    recipe = {f.name for f in dataclasses.fields(RecipeConfig)}
    assert recipe == set(RECIPE_LEGACY)
    proposal = {f.name for f in dataclasses.fields(ProposalConfig)}
    for run in ("nerf_mlp", "nerf_hash"):
        old = json.loads((OLD_RUNS / run / "config.json").read_text())
        # (+ render_tracer, issue 47: the no-grad renderer, auto for a run written before it;
        # issue 48's fog options, off or the old coordinate for a run written before them)
        fog = {"distortion_space", "near_loss", "near_loss_frac"}
        # (+ sdf_gradient, 2026-12-03: hash_sdf's finite differences, central before it)
        new = {"model", "field_options", "render_tracer", "sdf_gradient"} | recipe | proposal | fog
        assert set(NeRFConfig().to_dict()) == set(old) | new
        loaded = NeRFConfig.from_dict(old, "config.json")
        assert (loaded.distortion_space, loaded.near_loss) == ("scene", 0.0)
        assert loaded.sdf_gradient == "central"
        assert {k: getattr(loaded, k) for k in recipe} == RECIPE_LEGACY
        assert loaded.sampler == "grid"  # (proposal sampling, issue 48: an old run marched)
        assert loaded.render_tracer == "auto"
    cfg = NeRFConfig(field="hash", hash_levels=8, hash_max_res=256)
    assert section_of(cfg, HashConfig).grid_kwargs() == dict(
        n_levels=8, log2_size=19, base_res=16, max_res=256
    )
    own = {f.name for f in dataclasses.fields(NeRFConfig)}
    for s in (*SECTIONS, MLPConfig, HashConfig, SDFDensityConfig):
        own -= {f.name for f in dataclasses.fields(s)}
    assert own == {"preset", "batch", "field", "view_dependence", "tf32", "device", "model",
                   "field_options"}  # fmt: skip


@pytest.mark.parametrize(
    "section, bad, message",
    [
        (DataConfig, {"holdout": 1}, "'holdout' must be 0"),
        (SceneConfig, {"background": 2.0}, "'background' must be in"),
        (SamplingConfig, {"grid_res": 64, "grid_every": 0}, "'grid_every' must be >= 1"),
        (CaptureConfig, {"depth_rays": 0}, "'depth_rays' must be in"),
        (ValidationConfig, {"snapshots": "x"}, "'snapshots' expected seconds"),
        (MLPConfig, {"pos_freqs": 65}, "'pos_freqs' must be at most 64"),
        (HashConfig, {"field": "hash", "hash_levels": 0}, "'hash_levels' must be >= 1"),
        (SDFDensityConfig, {"beta_min": 1.0}, "'beta_min' must be in"),
        (SDFDensityConfig, {"field": "mlp", "sdf_density": "x"}, "'sdf_density' must be one"),
        (LoopConfig, {"seed": -1}, "'seed' must be an integer"),
    ],
)
def test_each_section_checks_its_own_values_in_a_saved_config(section, bad, message):
    """Every section's checks run on a saved config (untrusted), whichever field reads it."""
    assert all(k in {f.name for f in dataclasses.fields(section)} or k == "field" for k in bad)
    d = {**NeRFConfig().to_dict(), **bad}
    with pytest.raises(UserError, match=f"run/config.json: field {message}"):
        NeRFConfig.from_dict(d, where="run/config.json")


def _groups(model):
    args = build_parser().parse_args(["train", model, "--out", "x"])
    return {g.title: [a.dest for a in g._group_actions] for g in args.subparser._action_groups}


def test_help_shows_each_section_under_its_title():
    groups = _groups("volsdf")
    assert groups["training loop"][:2] == ["iters", "lr"]
    assert "hash_levels" in groups["hash-grid encoding (--field hash, hash_sdf)"]
    assert "width" in groups["MLP network (--field mlp, volsdf)"]
    assert "beta" in groups["SDF density (--field volsdf, hash_sdf)"]
    assert "grid_res" in groups["sampling and the occupancy grid"]
    assert "field" in groups["options"] and "iters" not in groups["options"]
    assert list(_groups("sdf")["training loop"]) == ["iters", "lr", "max_seconds", "ckpt_every",
                                                     "seed"]  # fmt: skip
    assert "iters" in _groups("box")["training loop"]


def test_a_field_registers_the_sections_it_reads():
    """The traits' ``config`` names the sections a field's builder reads; --help says which
    fields read each section, for an added field too."""
    assert FIELD_TRAITS["hash_sdf"].config == (HashConfig, SDFDensityConfig)
    assert FIELD_TRAITS["mlp"].config == (MLPConfig,)
    register_field("toy_hash", FieldTraits(in_box=True, config=(HashConfig,)))(lambda cfg: None)
    try:
        assert "hash-grid encoding (--field hash, hash_sdf, toy_hash)" in _groups("nerf")
    finally:
        FIELDS.pop("toy_hash", None)
        FIELD_TRAITS.pop("toy_hash", None)


def _config(*argv):
    from warpnerf.cli.train import nerf_config_from_args

    return nerf_config_from_args(build_parser().parse_args(["train", *argv, "--out", "x"]))


@pytest.mark.parametrize(
    "argv, message",
    [
        (["nerf", "--field", "mlp", "--hash-levels", "8"], "--hash-levels: hash-grid encoding "
         "settings, read by --field hash, hash_sdf, not by --field mlp"),
        (["nerf", "--field", "hash", "--width", "64", "--layers", "3"], "--layers, --width: MLP"),
        (["volsdf", "--field", "hash_sdf", "--pos-freqs", "4"], "--pos-freqs: MLP network"),
        (["volsdf", "--field", "volsdf", "--hidden", "32"], "--hidden: hash-grid encoding"),
    ],
)  # fmt: skip
def test_a_section_the_field_does_not_read_is_refused_on_the_command_line(argv, message):
    """Flags of a field section the chosen field does not read would be saved and ignored."""
    with pytest.raises(UserError, match=message):
        _config(argv[0], "--data", "builtin", *argv[1:])


def test_the_sections_a_field_reads_are_accepted():
    assert _config("nerf", "--data", "builtin", "--field", "hash", "--hash-levels", "8",
                   "--hidden", "32").hash_levels == 8  # fmt: skip
    cfg = _config("volsdf", "--data", "builtin", "--field", "volsdf", "--fixed-beta",
                  "--width", "48")  # fmt: skip
    assert (cfg.learn_beta, cfg.width) == (False, 48)
    assert _config("volsdf", "--data", "builtin", "--pos-freqs", "6").pos_freqs == 6  # its default
    register_field("toy_hash2", FieldTraits(in_box=True, config=(HashConfig,)))(lambda c: None)
    try:
        assert _config("nerf", "--data", "builtin", "--field", "toy_hash2", "--hash-levels",
                       "4").hash_levels == 4  # fmt: skip
        with pytest.raises(UserError, match="--width: MLP network settings, read by --field "
                           "mlp, volsdf, not by --field toy_hash2"):  # fmt: skip
            _config("nerf", "--data", "builtin", "--field", "toy_hash2", "--width", "8")
    finally:
        FIELDS.pop("toy_hash2", None)
        FIELD_TRAITS.pop("toy_hash2", None)
