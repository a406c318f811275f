"""A run's config is built, resolved and checked once, then frozen (issue 46): setting a field of
a frozen config raises, a resumed or loaded run reads its config.json once a command, and the
config.json a run writes is the frozen config it trained with."""

from __future__ import annotations

import dataclasses
import json

import pytest

from warpnerf.cli.parser import main
from warpnerf.errors import UserError, check_device
from warpnerf.train.box_fit import BoxFitConfig
from warpnerf.train.nerf_config import NeRFConfig
from warpnerf.train.sdf import SDFConfig

# a tiny `train nerf` (tests/test_first_hour_resume.py's settings)
NERF = ["--data", "builtin", "--field", "mlp", "--layers", "2", "--width", "16", "--samples", "8",
        "--builtin-size", "16", "--batch", "64", "--val-images", "0", "--quiet"]  # fmt: skip


@pytest.mark.parametrize("cfg", [NeRFConfig(data="builtin"), SDFConfig(), BoxFitConfig(lr=0.01)],
                         ids=["nerf", "sdf", "box"])  # fmt: skip
def test_a_validated_config_is_frozen_and_the_draft_untouched(cfg):
    frozen = cfg.validate()
    assert frozen.frozen and not cfg.frozen and frozen is not cfg
    assert frozen.lr_decay_steps == frozen.iters and cfg.lr_decay_steps == 0  # (resolved copy)
    with pytest.raises(dataclasses.FrozenInstanceError, match="read-only"):
        frozen.iters = 5
    with pytest.raises(dataclasses.FrozenInstanceError):
        del frozen.seed
    changed = dataclasses.replace(frozen, iters=5)  # a changed config is a new one, not frozen
    assert changed.iters == 5 and not changed.frozen and frozen.iters != 5
    assert changed.validate().frozen


# what a COLMAP capture decides for a run (train.nerf_config.scene_settings), saved as ``scene``
SCENE = {"format": "colmap", "transform": [[1.0, 0, 0, 0.5], [0, 1.0, 0, 0], [0, 0, 1.0, 0],
                                           [0, 0, 0, 1]],
         "ndc": None, "near": 0.1, "far": 5.0, "aabb": 1.2, "inner": 0.8}  # fmt: skip


def test_a_frozen_configs_dicts_and_lists_are_read_only_too():
    frozen = NeRFConfig(data="builtin", field="hash").validate(scene=SCENE)
    assert frozen.scene == SCENE and frozen.field_options == {}
    for change in (
        lambda: frozen.scene.__setitem__("near", 1.0),
        lambda: frozen.scene.update(far=9.0),
        lambda: frozen.scene.pop("inner"),
        lambda: frozen.scene.setdefault("extra", 1),
        lambda: frozen.scene.__delitem__("aabb"),
        lambda: frozen.scene.clear(),
        lambda: frozen.scene["transform"][0].__setitem__(3, 7.0),
        lambda: frozen.scene["transform"].append([0, 0, 0, 1]),
        lambda: frozen.field_options.__setitem__("x", 1),
        lambda: frozen.field_options.update(x=1),
    ):
        with pytest.raises(TypeError, match="read-only"):
            change()
    with pytest.raises(TypeError, match="read-only"):
        frozen.scene |= {"near": 1.0}
    assert frozen.scene == SCENE and frozen.field_options == {}
    # a changed config is a new one, with writable copies: the frozen one stays as it was
    changed = dataclasses.replace(frozen, scene=dict(frozen.scene, near=0.2))
    changed.scene["transform"][0][3] = 7.0
    assert changed.scene["near"] == 0.2 and frozen.scene == SCENE
    # the values a caller handed in are copied, not shared
    mine = json.loads(json.dumps(SCENE))
    cfg = NeRFConfig(data="builtin", field="hash").validate(scene=mine)
    mine["near"] = 3.0
    assert cfg.scene["near"] == 0.1


def test_a_frozen_config_saves_loads_and_copies_as_before():
    import copy
    import pickle

    frozen = NeRFConfig(data="builtin", field="hash").validate(scene=SCENE)
    d = frozen.to_dict()  # plain dicts and lists, the same JSON as the values
    assert type(d["scene"]) is dict and type(d["scene"]["transform"][0]) is list
    assert json.dumps(d) == json.dumps(dataclasses.asdict(frozen))
    assert json.loads(json.dumps(d))["scene"] == SCENE
    loaded = NeRFConfig.from_dict(json.loads(json.dumps(d))).freeze()
    assert loaded == frozen and loaded.frozen
    for twin in (copy.deepcopy(frozen), pickle.loads(pickle.dumps(frozen))):
        assert twin == frozen and twin.frozen
        with pytest.raises(TypeError, match="read-only"):
            twin.scene["near"] = 1.0


def test_old_runs_load_frozen_with_the_same_config_json():
    from pathlib import Path

    from warpnerf.train.box_fit import BoxFitConfig as Box

    fixtures = Path(__file__).parent / "data" / "runs_986359d"
    for name, cls in (("nerf_mlp", NeRFConfig), ("nerf_hash", NeRFConfig),
                      ("sdf_mlp", SDFConfig), ("box", Box)):  # fmt: skip
        saved = json.loads((fixtures / name / "config.json").read_text())
        if cls is Box:  # (the box run saves its data and device beside its config)
            saved = {k: v for k, v in saved.items() if k in cls.__dataclass_fields__}
        cfg = cls.from_dict(saved).freeze()
        assert cfg.frozen
        # the keys and values it saves are the file's (older files lack the newer keys)
        assert {k: v for k, v in cfg.to_dict().items() if k in saved} == saved


def test_nerf_resolve_fills_in_a_copy():
    cfg = NeRFConfig(data="builtin", field="hash")
    resolved = cfg.resolve(train_images=7)
    assert cfg.lr is None and cfg.aabb == 0 and cfg.near is None  # (left as it was)
    assert resolved.lr > 0 and resolved.aabb > 0 and resolved.near is not None
    codes = NeRFConfig(data="builtin", field="hash", appearance_dim=4, pose_refine=True)
    assert (codes.resolve(train_images=7).appearance_images, codes.pose_images) == (7, 0)
    assert codes.validate(train_images=7).pose_images == 7


def test_the_device_is_checked_in_one_place(monkeypatch):
    import torch

    assert check_device("cpu") == "cpu"
    with pytest.raises(UserError, match="--device must be cpu or cuda"):
        check_device("gpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(UserError, match="--device cuda: no CUDA device"):
        check_device("cuda")
    with pytest.raises(UserError, match="RUN: device cuda:1: no CUDA device"):
        check_device("cuda:1", "RUN")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(UserError, match="sees 1 CUDA device"):
        check_device("cuda:1")
    with pytest.raises(UserError, match="no CUDA device"):  # (the configs ask the same check)
        monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
        NeRFConfig(data="builtin", device="cuda").validate()


@pytest.fixture(scope="module")
def nerf_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("frozen") / "r"
    assert main(["train", "nerf", *NERF, "--iters", "2", "--out", str(run)]) == 0
    return run


def _count_config_reads(monkeypatch) -> list:
    """The reads of a config.json from the disk (every JSON file is read by read_input)."""
    import warpnerf.safe_writes as files

    reads, read = [], files.read_input

    def counting(path, *args, **kw):
        if str(path).endswith("config.json"):
            reads.append(str(path))
        return read(path, *args, **kw)

    monkeypatch.setattr(files, "read_input", counting)
    return reads


def test_a_resume_reads_config_json_once(nerf_run, monkeypatch, capsys):
    reads = _count_config_reads(monkeypatch)
    assert main(["train", "nerf", *NERF, "--out", str(nerf_run), "--resume", "--iters", "3"]) == 0
    assert reads == [str(nerf_run / "config.json")]


def test_eval_reads_config_json_once(nerf_run, tmp_path, monkeypatch, capsys):
    reads = _count_config_reads(monkeypatch)
    code = main(["eval", str(nerf_run), "--split", "val", "--max-images", "1",
                 "--out", str(tmp_path / "e")])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    assert reads == [str(nerf_run / "config.json")]


def test_the_written_config_json_is_the_frozen_config(tmp_path):
    from warpnerf.train.nerf import train_nerf

    seen = []

    class Watch:  # a loop hook: the config the task trains with
        def on_start(self, task, step):
            seen.append(task.cfg)

        def on_step(self, *a):
            pass

        def on_validation(self, *a):
            pass

        def close(self):
            pass

    cfg = NeRFConfig(data="builtin", field="mlp", n_layers=2, width=16, n_coarse=8,
                     builtin_size=16, batch=64, val_images=0, iters=2)  # fmt: skip
    train_nerf(cfg, tmp_path / "r", progress=False, log=lambda *a: None, hooks=[Watch()])
    (trained,) = seen
    assert trained.frozen and not cfg.frozen
    saved = json.loads((tmp_path / "r" / "config.json").read_text())
    assert saved == json.loads(json.dumps(trained.to_dict()))
    assert NeRFConfig.from_dict(saved) == trained
