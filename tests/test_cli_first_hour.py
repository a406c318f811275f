"""A user's first hour with the command line (issue 43, items 3, 4 and 13): an argument error is
one line naming the subcommand (a typo with the nearest flag, from the subcommand), `--help`
stays whole, `warpnerf --version` exists, `--data DIR/transforms.json` (a format's index file)
means DIR for every loader, and the guide says where its data sets come from and how `mesh`
takes a built-in SDF scene."""

from __future__ import annotations

import json
import platform
import re
from importlib import metadata
from pathlib import Path

import pytest

from tests.test_capture import _forward_cameras, _llff_capture
from tests.test_datasets import make_blender, make_nerfstudio
from warpnerf.cli import build_parser, main
from warpnerf.data import load_dataset
from warpnerf.errors import UserError

ROOT = Path(__file__).resolve().parents[1]

# ------------------------------------------------------- argument errors: one line, exit 2

ONE_LINE = [
    (["train", "nerf", "--iters", "-5"], "warpnerf train nerf", "argument --iters: must be"),
    (["train", "nerf", "--preset", "CPU"], "warpnerf train nerf", "did you mean 'cpu'?"),
    (["train", "nerf", "--itres", "10"], "warpnerf train nerf",
     "unrecognized arguments: --itres; did you mean --iters?"),
    (["train", "nerf", "--out", "o", "--itres", "10"], "warpnerf train nerf",
     "unrecognized arguments: --itres 10; did you mean --iters?"),
    (["train", "volsdf", "--out", "o", "--itres=10"], "warpnerf train volsdf",
     "did you mean --iters?"),
    (["render", "RUN", "--size", "0x0"], "warpnerf render", "argument --size"),
    (["mesh", "--level", "nan"], "warpnerf mesh", "argument --level: must be finite"),
    (["export", "RUN", "pointcloud"], "warpnerf export", "required: --out"),
    (["export", "RUN"], "warpnerf export", "required: what, --out"),
    (["eval", "RUN", "--bogus"], "warpnerf eval", "unrecognized arguments: --bogus"),
    (["train", "nerf2"], "warpnerf train", "did you mean 'nerf'?"),
    (["frobnicate"], "warpnerf", "argument COMMAND: invalid choice"),
]  # fmt: skip


@pytest.mark.parametrize("argv, prog, needle", ONE_LINE, ids=[" ".join(c[0]) for c in ONE_LINE])
def test_argument_error_is_one_line_naming_the_subcommand(argv, prog, needle, capsys, tmp_path,
                                                          monkeypatch):  # fmt: skip
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        main(argv)
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert e.value.code == 2 and captured.out == ""
    assert len(lines) == 1, captured.err  # no usage block before it
    assert lines[0].startswith(f"{prog}: error: ") and needle in lines[0], lines[0]
    assert not list(tmp_path.iterdir())  # nothing written


def test_a_typo_gets_no_suggestion_when_no_flag_is_close(capsys):
    with pytest.raises(SystemExit):
        main(["eval", "RUN", "--bogus"])
    assert "did you mean" not in capsys.readouterr().err


def test_help_stays_whole(capsys):
    with pytest.raises(SystemExit) as e:
        main(["train", "nerf", "--help"])
    out = capsys.readouterr().out
    assert e.value.code == 0 and out.startswith("usage: warpnerf train nerf ")
    for flag in ("--iters", "--preset", "--data", "--out", "--field", "--hash-levels"):
        assert flag in out, flag
    assert len(out.splitlines()) > 100
    # the fields `train nerf` trains (the surface fields are refused, with a pointer)
    assert "--field {mlp,hash} " in out and "train with `train volsdf`" in " ".join(out.split())
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    assert "--version" in out and all(c in out for c in ("train", "mesh", "export"))


def test_parse_args_of_a_good_command_line_is_unchanged():
    args = build_parser().parse_args(["train", "nerf", "--out", "o", "--iters", "5"])
    assert args.iters == 5 and args.out == "o" and args.model == "nerf"


# ----------------------------------------------------------------------------- --version


def test_version_names_warpnerf_warp_torch_and_python(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    out = capsys.readouterr().out.strip()
    assert e.value.code == 0
    want = (f"warpnerf {metadata.version('warpnerf')} (warp {metadata.version('warp-lang')}, "
            f"torch {metadata.version('torch')}, Python {platform.python_version()})")  # fmt: skip
    assert out == want


# ----------------------------------------------- --data DIR/<index file>: the folder, everywhere


def _same(a, b):
    assert a.images.shape == b.images.shape and (a.images == b.images).all()
    assert (a.c2w == b.c2w).all() and (a.intrinsics == b.intrinsics).all()


@pytest.mark.parametrize("index", ["transforms_train.json", "transforms_val.json"])
def test_blender_index_file_means_its_folder(tmp_path, index):
    root = make_blender(make_blender(tmp_path / "bl", split="train"), split="val")
    _same(load_dataset(root / index, "train"), load_dataset(root, "train"))
    _same(load_dataset(root / index, "val"), load_dataset(root, "val"))


def test_nerfstudio_and_llff_index_files_mean_their_folders(tmp_path):
    ns = make_nerfstudio(tmp_path / "ns")
    _same(load_dataset(ns / "transforms.json", "train"), load_dataset(ns, "train"))
    _llff_capture(tmp_path / "ff", _forward_cameras(9), 20.0, [10.0, 40.0])
    ff = tmp_path / "ff"
    a, b = load_dataset(ff / "poses_bounds.npy", "train"), load_dataset(ff, "train")
    _same(a, b)
    assert a.format == "llff" and a.ndc == b.ndc


@pytest.mark.parametrize("name", ["train/r_0.png", "notes.txt"])
def test_any_other_file_asks_for_the_folder(tmp_path, name, capsys):
    root = make_blender(tmp_path / "bl")
    (root / "notes.txt").write_text("x")
    with pytest.raises(UserError, match="not a dataset folder; give the dataset's folder"):
        load_dataset(root / name)
    assert main(["data", str(root / name)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("warpnerf data: error: ") and "give the dataset's folder" in err
    assert len(err.splitlines()) == 1


def test_cli_data_and_train_take_the_index_file(tmp_path, capsys):
    _llff_capture(tmp_path / "ff", _forward_cameras(9), 20.0, [10.0, 40.0])
    ff = tmp_path / "ff"
    assert main(["data", str(ff / "poses_bounds.npy")]) == 0
    by_file = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert main(["data", str(ff)]) == 0
    assert by_file == json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert by_file["format"] == "llff"
    # a new run records the folder and the capture's settings (NDC), as with --data DIR
    from warpnerf.train.nerf import resolve_data
    from warpnerf.train.nerf_config import NeRFConfig

    cfg = resolve_data(NeRFConfig(data=str(ff / "poses_bounds.npy"), field="mlp"))
    assert cfg.data == str(ff) and cfg.scene["format"] == "llff" and cfg.scene["ndc"]


def test_train_box_takes_the_index_file(tmp_path, capsys):
    root = make_blender(tmp_path / "bl", n=2)
    run = tmp_path / "run"
    argv = ["train", "box", "--data", str(root / "transforms_train.json"), "--out", str(run),
            "--iters", "1", "--samples", "8", "--batch", "16", "--frames", "1",
            "--quiet"]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err


# ------------------------------------------------------------------------------ the guide


def _guide() -> str:
    return (ROOT / "docs" / "GUIDE.md").read_text()


def test_guide_says_mesh_takes_builtin_scenes_with_sdf():
    guide = _guide()
    assert "mesh RUN\\|--sdf scene.json\\|torus\\|scene" not in guide  # read as `mesh torus`
    assert "warpnerf mesh --sdf torus --out" in guide
    assert "a bare `warpnerf mesh torus` reads `torus` as a run folder" in guide


def test_guide_documents_version():
    guide = _guide()
    assert "`warpnerf --version`" in guide
    shown = re.search(r"\(`(warpnerf [0-9.]+ \(warp [^`]*)`\)", guide).group(1)
    assert re.fullmatch(r"warpnerf \S+ \(warp \S+, torch \S+, Python \S+\)", shown)


def test_guide_says_where_each_data_set_comes_from():
    guide = _guide()
    section = guide.split("## Data sets:")[1].split("\n## ")[0]
    rows = {m.group(1): m.group(2) for m in re.finditer(r"^\| `([a-z_.]+)` \| (.*)$", section,
                                                        re.M)}  # fmt: skip
    assert set(rows) >= {"lego", "fern", "beer", "materials"}
    assert "nerf_synthetic.zip" in rows["lego"] and "--downscale 2" in rows["lego"]
    assert "nerf_llff_data.zip" in rows["fern"] and "--format llff --downscale 8" in rows["fern"]
    assert "YhuoyuH/NeRF-Database" in rows["beer"] and "COLMAP" in rows["beer"]
    assert "Mitsuba 3" in rows["materials"] and "**Not** the NeRF synthetic" in rows["materials"]
    assert "../shared/data" in section and "transforms_train.json" in section
