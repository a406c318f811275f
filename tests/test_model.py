"""The model object and the field registry (warpnerf/fields/model.py): what each registered field
builds, what a checkpoint holds, old checkpoints, and a new field added with one registry entry
training through the unchanged pipeline."""

from __future__ import annotations

import json
from dataclasses import dataclass

import pytest
import torch
from torch import nn

from warpnerf.errors import UserError
from warpnerf.fields import (
    FIELDS,
    FieldTraits,
    RadianceModel,
    build_model,
    field_traits,
    fields_with,
    register_field,
)  # fmt: skip
from warpnerf.fields.model import FIELD_TRAITS
from warpnerf.fields.nerf import NeRFField
from warpnerf.options import option
from warpnerf.train import evaluate_run, train_nerf
from warpnerf.train.nerf import load_run
from warpnerf.train.nerf_config import NeRFConfig

from .test_nerf import GRID, HASH, HASH_SDF, VOLSDF, tiny


def quiet(*a):
    pass


def test_registry_lists_the_builtin_fields():
    assert list(FIELDS)[:3] == ["mlp", "hash", "volsdf"]
    with pytest.raises(ValueError, match="registered already"):
        register_field("mlp")(lambda cfg: None)
    with pytest.raises(ValueError, match="unknown field"):
        build_model(tiny(field="nope"))
    with pytest.raises(UserError, match="--field must be one of mlp, hash, volsdf"):
        tiny(field="nope").check_values()


@pytest.mark.parametrize(
    "kw, fine, grid, shared",
    [
        (dict(field="mlp"), False, False, False),
        (dict(field="mlp", n_fine=8), True, False, False),
        (dict(HASH, n_fine=8), True, False, True),
        (GRID, False, True, False),
        (dict(VOLSDF, n_fine=8), True, False, True),
        (HASH_SDF, False, True, False),
    ],
)
def test_what_each_field_builds(kw, fine, grid, shared):
    m = build_model(tiny(**kw))
    assert isinstance(m, RadianceModel)
    assert (m.fine is not None, m.grid is not None, m.fine is m.coarse) == (fine, grid, shared)
    parts = m.parts()
    assert list(parts) == ["coarse", "fine", "grid"]
    assert (parts["fine"] is not None) == (fine and not shared)  # a shared network: saved once
    n = sum(p.numel() for p in m.parameters())
    want = sum(p.numel() for f in parts.values() if f is not None for p in f.parameters())
    assert n == want and n > 0
    assert m.field is (m.fine if fine else m.coarse)
    assert m.kind == ("sdf" if kw.get("field") in ("volsdf", "hash_sdf") else "density")
    again = build_model(tiny(**kw))  # the seed fixes the initial weights
    for a, b in zip(m.parameters(), again.parameters()):
        assert torch.equal(a, b)


def test_checkpoint_layout_and_old_checkpoints_without_grid_key(tmp_path):
    run = tmp_path / "r"
    train_nerf(tiny(iters=3, n_fine=8), run, progress=False, log=quiet)
    ck = torch.load(run / "checkpoint.pt", weights_only=True)
    assert set(ck["fields"]) == {"coarse", "fine", "grid"} and ck["fields"]["grid"] is None
    del ck["fields"]["grid"]  # as runs wrote it before the model object
    torch.save(ck, run / "checkpoint.pt")
    cfg, m, _ = load_run(run)
    for k, v in ck["fields"]["fine"].items():
        assert torch.equal(m.fine.state_dict()[k], v)
    assert evaluate_run(run, max_images=1)["psnr"] > 0


class _Blob(nn.Module):
    """A field written by a user: a learned density blob with a learned colour."""

    kind = "density"

    def __init__(self):
        super().__init__()
        self.log_sigma = nn.Parameter(torch.tensor(0.0))
        self.radius = nn.Parameter(torch.tensor(0.6))
        self.rgb = nn.Parameter(torch.zeros(3))

    def density(self, x):
        s = torch.nn.functional.softplus(self.radius - x.norm(dim=-1)) * self.log_sigma.exp() * 20
        return s, x

    def color(self, x, d, features):
        return torch.sigmoid(self.rgb).expand(x.shape[0], 3)

    def aux_losses(self):
        return {}

    def forward(self, x, d=None):
        s, h = self.density(x)
        return s, self.color(x, d, h)


def test_a_new_field_is_one_module_and_one_registry_entry(tmp_path):
    @register_field("blob")
    def _blob(cfg):
        return RadianceModel(_Blob())

    try:
        cfg = tiny(field="blob", iters=4)
        hist = train_nerf(cfg, tmp_path / "r", progress=False, log=quiet)
        assert len(hist["loss"]) == 4 and all(map(torch.isfinite, torch.tensor(hist["loss"])))
        saved = json.loads((tmp_path / "r" / "config.json").read_text())
        assert saved["field"] == "blob"
        cfg2, m, _ = load_run(tmp_path / "r")
        assert isinstance(m.coarse, _Blob) and cfg2.field == "blob"
        assert evaluate_run(tmp_path / "r", max_images=1)["psnr"] > 0
        from warpnerf.cli.parser import build_parser

        args = build_parser().parse_args(["train", "nerf", "--out", "x", "--field", "blob"])
        assert args.field == "blob"
    finally:
        FIELDS.pop("blob", None)
        FIELD_TRAITS.pop("blob", None)


@dataclass
class BallOptions:
    """The toy field's own settings: registered with it, flags on `train nerf`."""

    ball_radius: float = option(0.6, "the toy ball's initial radius", check="positive")
    ball_density: float = option(20.0, "the toy ball's density scale", check="positive")
    ball_hollow: bool = option(False, "a toy switch (a bool option: off unless given)")


class _Ball(_Blob):
    def __init__(self, radius, scale):
        super().__init__()
        self.radius.data.fill_(radius)
        self.scale = scale

    def density(self, x):
        s, h = super().density(x)
        return s * (self.scale / 20), h


def test_a_new_field_brings_its_own_flags(tmp_path, capsys):
    """A new field is one module and one registry entry with its traits and options: `train
    nerf` takes its flags (in --help, refused with another field), the run saves them, and
    eval, render, mesh and view accept the run."""
    from warpnerf.cli import main
    from warpnerf.viewer import load_scene

    @register_field("ball", FieldTraits(options=BallOptions))
    def _ball(cfg):
        o = cfg.field_settings()
        return RadianceModel(_Ball(o.ball_radius, o.ball_density))

    run = tmp_path / "r"
    base = [
        "train",
        "nerf",
        "--data",
        "builtin",
        "--builtin-size",
        "12",
        "--iters",
        "3",
        "--batch",
        "32",
        "--samples",
        "8",
        "--val-images",
        "1",
        "--quiet",
        "--no-tensorboard",
    ]
    try:
        with pytest.raises(SystemExit):
            main(["train", "nerf", "--help"])
        help_ = capsys.readouterr().out
        assert "--ball-radius" in help_ and "initial radius" in help_ and "--field ball" in help_
        assert main([*base, "--field", "mlp", "--ball-radius", "0.3", "--out", str(run)]) == 2
        assert "--ball-radius: options of another field" in capsys.readouterr().err
        assert not run.exists()
        assert main([*base, "--field", "mlp", "--ball-hollow", "--out", str(run)]) == 2
        assert main([*base, "--iters", "1", "--field", "mlp", "--out", str(tmp_path / "m")]) == 0
        assert main([*base, "--field", "ball", "--ball-radius", "0.3", "--out", str(run)]) == 0
        saved = json.loads((run / "config.json").read_text())
        assert saved["field_options"] == {"ball_radius": 0.3, "ball_hollow": False}
        assert saved["model"] == "nerf"
        cfg, m, _ = load_run(run)
        assert cfg.field_settings() == BallOptions(ball_radius=0.3)
        assert isinstance(m.coarse, _Ball)
        capsys.readouterr()
        assert main(["eval", str(run), "--max-images", "1"]) == 0
        assert main(["render", str(run), "--frames", "1", "--size", "8x8"]) == 0
        assert main(["mesh", str(run), "--resolution", "12", "--level", "7", "--out",
                     str(tmp_path / "m.ply"), "--no-screenshot"]) == 0  # fmt: skip
        assert load_scene(run).title.endswith("ball")
        assert main(["train", "nerf", "--out", str(run), "--resume", "--iters", "4",
                     "--quiet"]) == 0  # fmt: skip
        bad = dict(saved, field_options={"ball_radius": "big"})  # a saved config is untrusted
        (run / "config.json").write_text(json.dumps(bad))
        with pytest.raises(UserError, match="field_options of --field ball"):
            load_run(run)
    finally:
        FIELDS.pop("ball", None)
        FIELD_TRAITS.pop("ball", None)


def test_a_field_option_named_like_a_train_flag_is_refused_by_name():
    @dataclass
    class Clashing:
        width: int = option(3, "a name `train nerf` has already")

    register_field("clash", FieldTraits(options=Clashing))(lambda cfg: None)
    try:
        from warpnerf.cli.parser import build_parser

        with pytest.raises(ValueError, match="--field clash .* other train flags: width"):
            build_parser()
    finally:
        FIELDS.pop("clash", None)
        FIELD_TRAITS.pop("clash", None)


def test_the_builtin_fields_traits():
    assert fields_with(geometry="sdf") == ("volsdf", "hash_sdf")
    assert fields_with(hash=True) == ("hash", "hash_sdf")
    assert fields_with(in_box=True) == ("hash", "volsdf", "hash_sdf")
    assert fields_with(captures=True) == ("hash",)
    assert field_traits("nope") == FieldTraits()  # (the config's choices check reports it)
    with pytest.raises(ValueError, match="geometry"):
        FieldTraits(geometry="surface")
    with pytest.raises(ValueError, match="grid"):
        FieldTraits(captures=True)


def test_a_new_fields_traits_decide_its_defaults_and_checks():
    """What the library does with a field follows its registered traits, not its name: an SDF
    field in the box with its own learning rate and check."""

    def check(cfg, fail):
        if cfg.width > 64:
            raise fail("width", "the toy SDF field is at most 64 wide")

    traits = FieldTraits(geometry="sdf", in_box=True, lr=3e-3, lr_decay=4.0,
                         eikonal_weight=0.5, check=check)  # fmt: skip
    register_field("toy_sdf", traits)(lambda cfg: None)
    try:
        cfg = tiny(field="toy_sdf", lr=None, lr_final=None).check_values().resolve()
        assert (cfg.lr, cfg.lr_final, cfg.eikonal_weight) == (3e-3, 3e-3 / 4.0, 0.5)
        assert cfg.aabb > 0 and cfg.aabb_box() is not None and cfg.grid_res == 0
        with pytest.raises(UserError, match="toy SDF field is at most 64"):
            tiny(field="toy_sdf", width=128).check_values()
        with pytest.raises(UserError, match="pose-refine is for NeRF"):
            tiny(field="toy_sdf", pose_refine=True).check_values()
        with pytest.raises(UserError, match="--field hash or hash_sdf"):  # no grid trait
            tiny(field="toy_sdf", grid_res=32).check_values()
        assert "toy_sdf" in fields_with(geometry="sdf")
        from warpnerf.cli.parser import build_parser
        from warpnerf.cli.train import cmd_train_nerf

        args = build_parser().parse_args(["train", "volsdf", "--out", "x", "--field", "mlp"])
        with pytest.raises(UserError, match=r"SDF field \(volsdf, hash_sdf, toy_sdf\)"):
            cmd_train_nerf(args)
    finally:
        FIELDS.pop("toy_sdf", None)
        FIELD_TRAITS.pop("toy_sdf", None)


def test_model_is_what_renders(tmp_path):
    m = RadianceModel(NeRFField(2, 16, 1, 2, 1, True, "softplus"))
    from warpnerf.train.nerf import render_rays_of

    cfg = NeRFConfig(near=1.0, far=4.0, n_coarse=8)
    o = torch.zeros(5, 3)
    o[:, 2] = -3
    d = torch.tensor([[0.0, 0.0, 1.0]]).repeat(5, 1)
    out = render_rays_of(m, cfg, o, d)
    assert out["rgb"].shape == (5, 3) and torch.isfinite(out["rgb"]).all()


# ------------------------------------------------------------ the one chunked-rendering helper


def test_render_chunks_joins_rows_and_sums_counters():
    from warpnerf.render import render_chunks

    calls = []

    def fn(sl):
        calls.append((sl.start, sl.stop))
        rows = torch.arange(sl.start, sl.stop, dtype=torch.float64)
        return {"rgb": rows[:, None].expand(-1, 3), "pair": (rows, rows * 2), "n_kept": len(rows)}

    out = render_chunks(10, 4, fn)
    assert calls == [(0, 4), (4, 8), (8, 10)]
    assert torch.equal(out["rgb"][:, 0], torch.arange(10.0, dtype=torch.float64))
    assert torch.equal(out["pair"][1], 2 * torch.arange(10.0, dtype=torch.float64))
    assert out["n_kept"] == 10
    calls.clear()
    assert render_chunks(0, 4, fn)["rgb"].shape == (0, 3) and calls == [(0, 0)]
    with pytest.raises(ValueError, match="chunk"):
        render_chunks(10, 0, fn)


@pytest.mark.parametrize("chunk", [None, 1, 7, 64])
def test_renderers_give_the_same_image_in_any_chunk(chunk):
    """render_rays and render_nerf (coarse + fine) through render_chunks: chunking changes
    nothing but the memory."""
    from warpnerf.render import render_nerf, render_rays

    g = torch.Generator().manual_seed(0)
    o = torch.randn(23, 3, generator=g, dtype=torch.float64) * 0.1
    d = torch.nn.functional.normalize(torch.randn(23, 3, generator=g, dtype=torch.float64), dim=-1)

    def field(p, _):
        return 3.0 * torch.exp(-(p**2).sum(-1)), torch.sigmoid(p)

    a = render_rays(o, d, 0.1, 2.0, field, n_samples=16, chunk=chunk)
    b = render_rays(o, d, 0.1, 2.0, field, n_samples=16)
    a2 = render_nerf(field, o, d, 0.1, 2.0, fine=field, n_coarse=8, n_fine=8, chunk=chunk)
    b2 = render_nerf(field, o, d, 0.1, 2.0, fine=field, n_coarse=8, n_fine=8)
    for k in ("rgb", "depth", "opacity"):
        assert a[k].shape[0] == 23 and torch.equal(a[k], b[k]) and torch.equal(a2[k], b2[k])
    assert b[k].abs().sum() > 0
