"""Outside packages add fields, formats and methods through entry points (warpnerf/plugins.py),
with no edit inside warpnerf: the tiny package tests/data/plugin_pkg is "installed" by writing
its dist-info (METADATA + entry_points.txt) beside it in a folder on sys.path / PYTHONPATH."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from warpnerf import plugins
from warpnerf.data import dataset as dataset_mod
from warpnerf.fields import model as model_mod
from warpnerf.train import methods as methods_mod

ROOT = Path(__file__).resolve().parents[1]
PKG = Path(__file__).parent / "data" / "plugin_pkg" / "warpnerf_toy_plugin"
ENTRY_POINTS = """\
[warpnerf.fields]
toy_mlp = warpnerf_toy_plugin.field

[warpnerf.formats]
toynpz = warpnerf_toy_plugin.fmt:register
"""
QUIET = ["--quiet", "--no-tensorboard"]
TINY = ["--preset", "cpu", "--iters", "2", "--batch", "32", "--samples", "4", "--toy-hidden", "8",
        "--val-images", "0", *QUIET]  # fmt: skip


def install(site: Path, name: str = "warpnerf-toy-plugin", entry_points: str = ENTRY_POINTS):
    """Installs the toy package into folder ``site`` as pip would (the package and its
    dist-info), with these entry points."""
    if not (site / PKG.name).exists():
        shutil.copytree(PKG, site / PKG.name, ignore=shutil.ignore_patterns("__pycache__"))
    info = site / f"{name.replace('-', '_')}-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(entry_points)
    return site


@pytest.fixture
def site(tmp_path, monkeypatch):
    """A site folder on sys.path for this test: the registries load its plugins afresh and
    lose them afterwards."""
    site = tmp_path / "site"
    site.mkdir()
    regs = (model_mod.FIELDS, model_mod.FIELD_TRAITS, dataset_mod.REGISTRY, methods_mod.METHODS)
    before = [list(dict.keys(r)) for r in regs]
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.setattr(plugins, "_LOADED", set())
    try:
        yield site
    finally:
        for r, keys in zip(regs, before):
            for k in [k for k in dict.keys(r) if k not in keys]:
                dict.pop(r, k)
        for m in [m for m in sys.modules if m.split(".")[0] == PKG.name]:
            del sys.modules[m]


def scene_folder(folder: Path) -> Path:
    """A toynpz folder: the built-in scene's train and val images at 8 x 8 pixels."""
    from warpnerf.data import load_dataset

    tr, va = (load_dataset("builtin", s, builtin_size=8, uint8=True) for s in ("train", "val"))
    folder.mkdir()
    np.savez(folder / "scene.toynpz.npz",
             images=np.concatenate([tr.images.numpy(), va.images.numpy()]),
             c2w=np.concatenate([tr.c2w.numpy(), va.c2w.numpy()]),
             intrinsics=np.concatenate([tr.intrinsics.numpy(), va.intrinsics.numpy()]),
             near_far=np.array([tr.near, tr.far]))  # fmt: skip
    return folder


def env_with(site: Path) -> dict:
    """The environment of a subprocess that imports this checkout and the plugin in ``site``."""
    path = os.pathsep.join(p for p in (str(ROOT), str(site), os.environ.get("PYTHONPATH")) if p)
    return dict(os.environ, PYTHONPATH=path, OMP_NUM_THREADS="1")


def test_a_plugin_package_adds_a_field_and_a_format(site, tmp_path):
    from warpnerf.data import FORMATS, detect_format, load_dataset
    from warpnerf.data.loading import data_summary
    from warpnerf.fields import FIELDS, field_traits
    from warpnerf.train.nerf_config import NeRFConfig

    install(site)
    assert "toy_mlp" in FIELDS and list(FIELDS)[:4] == ["mlp", "hash", "volsdf", "hash_sdf"]
    assert field_traits("toy_mlp").options.__name__ == "ToyOptions"
    assert "toynpz" in FORMATS and list(FORMATS)[-1] == "toynpz"
    data = scene_folder(tmp_path / "scene")
    assert detect_format(data) == "toynpz"
    val = load_dataset(data, "val", holdout=8)
    assert val.format == "toynpz" and val.images.shape[1:] == (8, 8, 3)
    assert data_summary(data)["format"] == "toynpz"
    NeRFConfig(data=str(data), field="toy_mlp").check_values()  # the config's checks know both


def test_plugins_load_when_a_registry_is_first_read_not_at_import(tmp_path):
    site = install(tmp_path / "site")
    code = (
        "import sys, warpnerf, warpnerf.train, warpnerf.cli.parser\n"
        "from warpnerf import plugins\n"
        "assert not plugins._LOADED and 'warpnerf_toy_plugin' not in sys.modules\n"
        "from warpnerf.fields import FIELDS\n"
        "assert 'toy_mlp' in FIELDS and plugins._LOADED == {'warpnerf.fields'}\n"
        "print(list(FIELDS))\n"
    )
    res = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env_with(site),
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    assert "toy_mlp" in res.stdout


def test_train_nerf_with_a_plugin_field_on_builtin_and_on_a_plugin_format(tmp_path):
    """The issue's "done when": `train nerf --field <its field>` trains, on the built-in scene
    and on a folder of its format; `eval` reads the run back."""
    site = install(tmp_path / "site")
    data = scene_folder(tmp_path / "scene")
    env = env_with(site)

    def warpnerf(*argv):
        res = subprocess.run([sys.executable, "-m", "warpnerf.cli", *argv], cwd=tmp_path,
                             env=env, capture_output=True, text=True, timeout=600)  # fmt: skip
        assert res.returncode == 0, res.stderr[-3000:]
        return res

    warpnerf("train", "nerf", "--field", "toy_mlp", "--data", "builtin", "--builtin-size", "8",
             "--out", "a", *TINY)  # fmt: skip
    saved = json.loads((tmp_path / "a" / "config.json").read_text())
    assert saved["field"] == "toy_mlp" and saved["field_options"] == {"toy_hidden": 8}
    warpnerf("train", "nerf", "--field", "toy_mlp", "--data", str(data), "--near", "1",
             "--far", "4", "--out", "b", *TINY)  # fmt: skip
    saved = json.loads((tmp_path / "b" / "config.json").read_text())
    assert saved["field"] == "toy_mlp" and saved["data_format"] == "auto"
    res = warpnerf("eval", "b", "--max-images", "1")
    assert json.loads(res.stdout.strip().splitlines()[-1])["psnr"] > 0


def test_a_broken_plugin_is_named_in_a_warning_and_the_rest_works(site):
    from warpnerf.cli.parser import build_parser
    from warpnerf.fields import FIELDS

    (site / "warpnerf_broken.py").write_text("raise RuntimeError('boom')\n")
    (site / "warpnerf_clash.py").write_text(
        "from warpnerf.fields import register_field\n"
        "register_field('mlp')(lambda cfg: None)\n"
    )  # fmt: skip
    install(site, "warpnerf-broken-plugin", "[warpnerf.fields]\nbroken = warpnerf_broken\n"
            "clash = warpnerf_clash\n")  # fmt: skip
    install(site)
    with pytest.warns(plugins.PluginWarning) as seen:
        names = list(FIELDS)
    text = " | ".join(str(w.message) for w in seen)
    assert "plugin 'broken' (warpnerf_broken, from warpnerf-broken-plugin)" in text
    assert "RuntimeError: boom" in text
    assert "plugin 'clash'" in text and "'mlp' is registered already" in text
    # each shown at the plugin's own failing line, not inside warpnerf
    assert {(Path(w.filename).name, w.lineno) for w in seen} == {
        ("warpnerf_broken.py", 1),
        ("warpnerf_clash.py", 2),
    }
    assert "toy_mlp" in names and "mlp" in names and "broken" not in names
    args = build_parser().parse_args(["train", "nerf", "--out", "x", "--field", "toy_mlp"])
    assert args.field == "toy_mlp"
    assert plugins.load_plugins("warpnerf.fields") == []  # (once: no second warning)


def test_the_built_in_train_commands_come_from_the_method_registry():
    """Every `train` command is made by one path from the method registry (issue 46): the
    built-in methods' commands carry their method and the front end registered for them, as an
    added method's would; a second front end for a command is a developer's error."""
    from warpnerf.cli.parser import build_parser
    from warpnerf.cli.train_commands import TrainCommand, register_train_command

    parser = build_parser()
    made = {}
    for method in methods_mod.METHODS.values():
        for command in method.commands:
            args = parser.parse_args(["train", command, "--out", "x"])
            assert args.method is method and args.model == command
            made[command] = method.name
    built_in = {"nerf": "nerf", "volsdf": "nerf", "sdf": "neural_sdf", "box": "box"}
    assert {k: made[k] for k in built_in} == built_in
    with pytest.raises(ValueError, match="has a front end already"):
        register_train_command("nerf", "nerf", TrainCommand("", print, print))
