"""Bad input: every CLI command and loader stops with one clear error line that names the file,
field or flag, exits with status 2 (argparse's own errors too) without a traceback, and writes
nothing.

Most cases run in-process (``warpnerf.cli.main``, the demos' ``main``) against one module-wide
folder of tiny broken inputs (``world``); one test runs four commands as subprocesses to check the
exit status and stderr end to end. Cases that need an unreadable file (chmod 000) emulate
the denial when the tests run as root.
"""

# AUDIT MATRIX: command or loader x bad-input case.
#   Mi missing file/folder   Ur unreadable file or folder (chmod 000)   Js malformed JSON
#   Sh matrix shape (3x3, 4x5, nested, ragged)   Nf NaN/Inf in a pose or the intrinsics
#   Sz image sizes differ   Em empty (frames: [], no images, 0 points / wrong shape / NaN points,
#   no primitives)   Op unknown option or command   Rk run of another model (nerf / sdf / box),
#   corrupt, truncated or mismatched checkpoint, run folder without checkpoint or config
#   Of --out (--json) is a file, or lies under one   Nu bad numbers (<= 0, NaN, Inf, malformed)
# Cells: covered before this file by D = test_datasets, I = test_data_io, C = test_cli_demos;
#   h = tested here, was already clean;  F = failed (traceback, misleading message or silently
#   accepted), fixed and tested here;  r = a chmod case (as root the denial is emulated by
#   _deny_reads: chmod 000 does not stop root);  . = n/a.
#
#                         Mi    Ur    Js    Sh    Nf    Sz    Em    Op    Rk    Of    Nu
# load_blender            DIh   Fr    DIh   DIh   Dh    Dh    Dh    .     .     .     D
# load_nerfstudio         Dh    Fr    Dh    D     Dh    Dh    Dh    .     .     .     D
# load_dataset (detect)   Dh    Fr    D     D     D     D     Dh    .     .     .     D
# train box (box-fit      Ch    hFr   h     h     h     h     h     h     hF    F     CF
#   folder loader, load_box_run)
# train nerf              Ch    hFr   h     h     h     h     h     h     ChF   F     CF
# train volsdf            h     .     .     h     .     .     .     h     F     F     CF
# train sdf (load_points) Ch    hr    .     .     h     .     hF    h     ChFr  F     ChF
# eval (load_run)         Ch    Fr    h     .     .     .     .     h     ChF   F     Ch
# render (load_run)       Ch    .     .     .     .     .     .     h     ChF   F     Ch
# mesh (load_run,         Ch    hFr   h     .     h     .     h     h     hF    Ch    CF
#   load_sdf_run, SDFScene.load)
# demo                    .     .     .     .     .     .     .     h     .     F     Ch
# bench                   .     .     .     .     .     .     .     h     .     F     .
# demos/*.py: all ten run here in-process with an --out that is a file (F in 01, 02 and
#   _nerf_args = 03, 04, 05, 10; 06-09 already refused it) and, for the seven that read data
#   (02-05, 08-10), a missing --data / --points (already a one-line error, status 2; 02 no
#   longer creates --out first); 02 and 03 also as subprocesses. _nerf_args also refuses a
#   non-finite --near/--far/--lr.
# What F was: --out/--json that is a file: FileExistsError / NotADirectoryError /
#   IsADirectoryError tracebacks in demo, train *, eval, render, bench; `train volsdf --resume`
#   on a NeRF run silently continued the NeRF; --far inf / --near nan reached the renderer
#   (ValueError traceback); --max-seconds nan was ignored; mesh --level nan said "no surface";
#   train box --frames -1 / --near -1 were accepted; an unreadable transforms file said "not
#   valid JSON"; an unreadable data folder gave a PermissionError traceback (box loader).
# Fixed in a second pass (io.load_checkpoint / io.load_weights in load_run, load_sdf_run,
#   load_box_run; datasets.detect_format; mesh.read_ply_points): a corrupt / truncated /
#   other-model / resized checkpoint.pt (unpickling errors, KeyError, load_state_dict size
#   mismatches), an unreadable config.json or checkpoint.pt, a box run given to eval / render /
#   mesh / train nerf ("config: unknown field(s)", not naming the run), an unreadable data folder
#   (detect_format), an ASCII PLY with 0 vertices (IndexError).

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import warpnerf.mesh
from warpnerf.cli import main

from .test_datasets import _pattern, _png, make_blender, make_nerfstudio

ROOT = Path(__file__).resolve().parents[1]
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0
# train nerf flags for a tiny, fast run (only reached by cases that should fail before training)
TN = ["--iters", "2", "--batch", "32", "--samples", "4", "--layers", "2", "--width", "16"]
TN += ["--pos-freqs", "1", "--dir-freqs", "1", "--builtin-size", "8", "--val-images", "0"]
TN += ["--quiet"]


def _edit(path: Path, fn) -> None:
    js = json.loads(path.read_text())
    fn(js)
    path.write_text(json.dumps(js))  # NaN / Infinity are written as the tokens Python reads


def _variant(world: Path, base: str, name: str, fn) -> None:
    shutil.copytree(world / base, world / name)
    js = "transforms_train.json" if base == "bl" else "transforms.json"
    _edit(world / name / js, fn)


def _frame(i, **kw):
    return lambda js: js["frames"][i].update(kw)


_NAN_POSE = [[float("nan")] * 4] * 3 + [[0, 0, 0, 1]]
_INF_POSE = [[1, 0, 0, float("inf")], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
# name -> (base folder, edit of its transforms JSON)
DATA_VARIANTS = {
    "bl_3x3": ("bl", _frame(1, transform_matrix=np.eye(3).tolist())),
    "bl_4x5": ("bl", _frame(1, transform_matrix=np.eye(4, 5).tolist())),
    "bl_nested": ("bl", _frame(1, transform_matrix=[np.eye(4).tolist()])),
    "bl_ragged": ("bl", _frame(1, transform_matrix=[[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0]])),
    "bl_inf": ("bl", _frame(1, transform_matrix=_INF_POSE)),
    "bl_fov_nan": ("bl", lambda js: js.update(camera_angle_x=float("nan"))),
    "bl_empty": ("bl", lambda js: js.update(frames=[])),
    "ns_nan": ("ns", _frame(2, transform_matrix=_NAN_POSE)),
    "ns_fl_nan": ("ns", lambda js: js.update(fl_x=float("nan"))),
    "ns_cx_inf": ("ns", lambda js: js.update(cx=float("inf"))),
    "ns_frame_fy_nan": ("ns", _frame(1, fl_y=float("nan"))),
    "ns_w_mismatch": ("ns", lambda js: js.update(w=10)),
}


def _train(x):
    return ["train", "nerf", "--data", x, "--out", "OUT", *TN]


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A folder of tiny good and broken inputs: datasets, point clouds, scenes, runs."""
    w = tmp_path_factory.mktemp("bad_input")
    (w / "afile").write_text("a plain file, not a folder")
    (w / "emptydir").mkdir()
    (w / "dir.ply").mkdir()  # a folder named like a mesh file
    make_blender(w / "bl", n=2)
    make_nerfstudio(w / "ns", n=3)
    for name, (base, fn) in DATA_VARIANTS.items():
        _variant(w, base, name, fn)
    (w / "bl_badjson").mkdir()
    (w / "bl_badjson" / "transforms_train.json").write_text('{"frames": [')
    (w / "ns_badjson").mkdir()
    (w / "ns_badjson" / "transforms.json").write_text("{'single': 'quotes'}")
    shutil.copytree(w / "bl", w / "bl_noimg")
    shutil.rmtree(w / "bl_noimg" / "train")
    shutil.copytree(w / "bl", w / "bl_size")
    _png(w / "bl_size" / "train" / "r_1.png", _pattern(10, 8, 0, 4))
    make_nerfstudio(w / "ns_one", n=1)
    # point clouds
    g = np.random.default_rng(0).normal(size=(200, 3))
    np.savez(w / "ok.npz", points=g / np.linalg.norm(g, axis=1, keepdims=True))
    np.savez(w / "p0.npz", points=np.zeros((0, 3)))
    np.savez(w / "p2d.npz", points=np.zeros((100, 2)))
    np.savez(w / "pnan.npz", points=np.where(np.arange(300).reshape(100, 3) == 7, np.nan, 1.0))
    np.savez(w / "pkey.npz", xyz=g)
    np.savez(w / "pnormals.npz", points=g, normals=g[:5])
    (w / "pbad.npz").write_bytes(b"not a zip file")
    (w / "pbad.ply").write_bytes(b"not a ply file")
    (w / "p0.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n"
    )
    (w / "points.txt").write_text("0 0 0\n")
    # SDF scenes
    (w / "bad_scene.json").write_text('{"primitives": [')
    (w / "empty_scene.json").write_text('{"primitives": []}')
    nan_sphere = {"kind": "sphere", "params": [0.5, 0, 0, 0], "center": [0, float("nan"), 0]}
    (w / "nan_scene.json").write_text(json.dumps({"primitives": [nan_sphere]}))
    # runs: a tiny NeRF (on bl: rendering the built-in scene costs seconds) and a tiny neural
    # SDF (without its pyvista screenshot, seconds too), then broken copies of them
    sdf = ["train", "sdf", "--points", "ok.npz", "--out", "sdf_run", "--iters", "2"]
    sdf += ["--batch", "32", "--layers", "2", "--width", "16", "--pos-freqs", "1"]
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(w)
        mp.setattr(warpnerf.mesh, "screenshot", _no_screenshot)
        assert main(["train", "nerf", "--data", "bl", "--out", "nerf_run", *TN]) == 0
        assert main([*sdf, "--resolution", "8", "--quiet"]) == 0
        box = ["train", "box", "--data", "bl", "--out", "box_run", "--iters", "1"]
        assert main([*box, "--batch", "16", "--samples", "4", "--frames", "0", "--quiet"]) == 0
    for kind in ("nerf", "sdf"):
        run = w / f"{kind}_run"
        for name, change in (
            ("corrupt", lambda r: (r / "checkpoint.pt").write_bytes(b"junk")),
            ("truncated", lambda r: _truncate(r / "checkpoint.pt")),
            ("nockpt", lambda r: (r / "checkpoint.pt").unlink()),
            ("nocfg", lambda r: (r / "config.json").unlink()),
            ("badcfg", lambda r: (r / "config.json").write_text("{not json")),
        ):
            shutil.copytree(run, w / f"{kind}_{name}")
            change(w / f"{kind}_{name}")
    shutil.copytree(w / "box_run", w / "box_corrupt")
    (w / "box_corrupt" / "checkpoint.pt").write_bytes(b"junk")
    # a run folder whose checkpoint.pt comes from the other kind of run
    shutil.copytree(w / "nerf_run", w / "nerf_otherckpt")
    shutil.copy(w / "sdf_run" / "checkpoint.pt", w / "nerf_otherckpt" / "checkpoint.pt")
    shutil.copytree(w / "sdf_run", w / "sdf_otherckpt")
    shutil.copy(w / "nerf_run" / "checkpoint.pt", w / "sdf_otherckpt" / "checkpoint.pt")
    # a run whose config.json describes a wider network than its checkpoint holds
    shutil.copytree(w / "nerf_run", w / "nerf_resized")
    _edit(w / "nerf_resized" / "config.json", lambda c: c.update(width=32))
    # a run whose default eval / render output folders are files
    shutil.copytree(w / "nerf_run", w / "nerf_blocked")
    (w / "nerf_blocked" / "eval_val").write_text("a file")
    (w / "nerf_blocked" / "render_spiral").write_text("a file")
    return w


def _no_screenshot(*args, **kwargs):
    raise ImportError("screenshots are skipped in these tests")


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _snapshot(root: Path) -> list:
    return sorted((str(p.relative_to(root)), p.stat().st_size) for p in root.rglob("*"))


def _fails_cleanly(argv, capsys, needles, status=2) -> str:
    """Runs ``warpnerf argv`` in-process: status 2, one stderr line naming ``needles``."""
    rc = main(argv)
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.strip()]
    assert rc == status, (rc, err)
    assert len(lines) == 1, err
    assert lines[0].startswith(f"warpnerf {argv[0]}: error: "), lines[0]
    for n in needles:
        assert n in lines[0], (n, lines[0])
    assert "Traceback" not in err
    return lines[0]


# ------------------------------------------------------------------- user errors (exit 2)

# (argv with OUT = a fresh path that must stay absent, substrings of the error line)
CASES = [
    # datasets through train nerf: missing, malformed JSON, matrices, non-finite, sizes, empty
    (_train("nope"), ["nope", "not found"]),
    (_train("afile"), ["afile", "not a dataset folder; give the dataset's folder"]),
    (_train("emptydir"), ["emptydir", "transforms_train.json", "transforms.json"]),
    (_train("bl_badjson"), ["bl_badjson/transforms_train.json", "not valid JSON"]),
    (_train("ns_badjson"), ["ns_badjson/transforms.json", "not valid JSON"]),
    (_train("bl_3x3"), ["transforms_train.json", "frames[1].transform_matrix", "shape [3, 3]"]),
    (_train("bl_4x5"), ["frames[1].transform_matrix", "shape [4, 5]"]),
    (_train("bl_nested"), ["frames[1].transform_matrix", "shape [1, 4, 4]"]),
    (_train("bl_ragged"), ["frames[1].transform_matrix", "not a list of numbers"]),
    (_train("bl_inf"), ["frames[1].transform_matrix", "non-finite"]),
    (_train("ns_nan"), ["transforms.json", "frames[2].transform_matrix", "non-finite"]),
    (_train("bl_fov_nan"), ["transforms_train.json", "'camera_angle_x'", "nan"]),
    (_train("ns_fl_nan"), ["transforms.json", "'fl_x'", "nan"]),
    (_train("ns_cx_inf"), ["transforms.json", "'cx'", "inf"]),
    (_train("ns_frame_fy_nan"), ["transforms.json", "'frames[1].fl_y'"]),
    (_train("bl_size"), ["r_1.png", "10x8", "12x8", "one size"]),
    (_train("ns_w_mismatch"), ["frame_00001.png", "'w', 'h'"]),
    (_train("bl_empty"), ["transforms_train.json", "'frames'", "non-empty"]),
    (_train("bl_noimg"), ["frames[0].file_path", "not found"]),
    (_train("ns_one"), ["transforms.json", "split 'train' is empty"]),
    (["train", "volsdf", "--data", "bl_inf", "--out", "OUT", *TN], ["frames[1].transform_matrix"]),
    # the box-fit folder loader (train box): the same cases
    (["train", "box", "--data", "nope", "--out", "OUT"], ["nope", "not found"]),
    (["train", "box", "--data", "emptydir", "--out", "OUT"], ["emptydir", "transforms"]),
    (["train", "box", "--data", "bl_badjson", "--out", "OUT"], ["not valid JSON"]),
    (["train", "box", "--data", "bl_4x5", "--out", "OUT"], ["frames[1].transform_matrix"]),
    (["train", "box", "--data", "bl_inf", "--out", "OUT"], ["non-finite"]),
    (["train", "box", "--data", "bl_fov_nan", "--out", "OUT"], ["'camera_angle_x'"]),
    (["train", "box", "--data", "ns_fl_nan", "--out", "OUT"], ["'fl_x'"]),
    (["train", "box", "--data", "bl_size", "--out", "OUT"], ["r_1.png", "one size"]),
    (["train", "box", "--data", "bl_empty", "--out", "OUT"], ["'frames'"]),
    (["train", "box", "--data", "bl_noimg", "--out", "OUT"], ["not found"]),
    # point clouds (train sdf)
    (["train", "sdf", "--points", "nope.npz", "--out", "OUT"], ["nope.npz", "no such"]),
    (["train", "sdf", "--points", "emptydir", "--out", "OUT"], ["emptydir", "is a folder"]),
    (["train", "sdf", "--points", "p0.npz", "--out", "OUT"], ["p0.npz", "[N >= 16, 3]", "[0, 3]"]),
    (
        ["train", "sdf", "--points", "p0.ply", "--out", "OUT"],
        ["p0.ply", "[0, 3]"],
    ),
    (["train", "sdf", "--points", "p2d.npz", "--out", "OUT"], ["p2d.npz", "[100, 2]"]),
    (["train", "sdf", "--points", "pnan.npz", "--out", "OUT"], ["pnan.npz", "NaN"]),
    (["train", "sdf", "--points", "pkey.npz", "--out", "OUT"], ["pkey.npz", "'points'"]),
    (["train", "sdf", "--points", "pnormals.npz", "--out", "OUT"], ["pnormals.npz", "normals"]),
    (["train", "sdf", "--points", "pbad.npz", "--out", "OUT"], ["pbad.npz", "unreadable"]),
    (["train", "sdf", "--points", "pbad.ply", "--out", "OUT"], ["pbad.ply", "unreadable"]),
    (["train", "sdf", "--points", "points.txt", "--out", "OUT"], ["points.txt", ".npz or .ply"]),
    # SDF scenes (mesh --sdf)
    (["mesh", "--sdf", "nope.json", "--out", "OUT/m.ply"], ["nope.json", "no such scene"]),
    (["mesh", "--sdf", "emptydir", "--out", "OUT/m.ply"], ["emptydir", "is a folder"]),
    (["mesh", "--sdf", "bad_scene.json", "--out", "OUT/m.ply"], ["bad_scene.json", "JSON"]),
    (["mesh", "--sdf", "empty_scene.json", "--out", "OUT/m.ply"], ["'primitives' is empty"]),
    (["mesh", "--sdf", "nan_scene.json", "--out", "OUT/m.ply"], ["primitives[0]", "center"]),
    # runs: missing, incomplete, malformed, of another model type, corrupt checkpoints
    (["eval", "nope"], ["nope", "not found"]),
    (["eval", "nerf_nockpt"], ["nerf_nockpt", "checkpoint.pt"]),
    (["eval", "nerf_nocfg"], ["nerf_nocfg", "config.json"]),
    (["eval", "nerf_badcfg"], ["nerf_badcfg/config.json"]),
    (["eval", "sdf_run"], ["sdf_run", "neural-SDF run"]),
    (["eval", "nerf_corrupt"], ["nerf_corrupt/checkpoint.pt"]),
    (["eval", "nerf_truncated"], ["nerf_truncated/checkpoint.pt"]),
    (["eval", "nerf_otherckpt"], ["nerf_otherckpt/checkpoint.pt"]),
    (["eval", "nerf_resized"], ["nerf_resized/checkpoint.pt", "config.json"]),
    (["render", "nope"], ["nope", "not found"]),
    (["render", "nerf_nockpt"], ["nerf_nockpt", "checkpoint.pt"]),
    (["render", "sdf_run"], ["sdf_run", "neural-SDF run"]),
    (["render", "nerf_corrupt"], ["nerf_corrupt/checkpoint.pt"]),
    (["mesh", "nope", "--out", "OUT/m.ply"], ["nope", "not found"]),
    (["mesh", "nerf_nockpt", "--out", "OUT/m.ply"], ["nerf_nockpt", "checkpoint.pt"]),
    (["mesh", "nerf_badcfg", "--out", "OUT/m.ply"], ["nerf_badcfg/config.json"]),
    (["mesh", "sdf_nockpt", "--out", "OUT/m.ply"], ["sdf_nockpt", "checkpoint.pt"]),
    (["mesh", "sdf_nocfg", "--out", "OUT/m.ply"], ["sdf_nocfg", "not a training run"]),
    (["mesh", "sdf_badcfg", "--out", "OUT/m.ply"], ["sdf_badcfg/config.json"]),
    (["mesh", "nerf_corrupt", "--out", "OUT/m.ply"], ["nerf_corrupt/checkpoint.pt"]),
    (["mesh", "sdf_corrupt", "--out", "OUT/m.ply"], ["sdf_corrupt/checkpoint.pt"]),
    (["mesh", "sdf_truncated", "--out", "OUT/m.ply"], ["sdf_truncated/checkpoint.pt"]),
    (["mesh", "sdf_otherckpt", "--out", "OUT/m.ply"], ["sdf_otherckpt/checkpoint.pt"]),
    (["train", "nerf", "--out", "sdf_run", "--resume", "--iters", "9"], ["neural-SDF run"]),
    (["train", "nerf", "--out", "nerf_nocfg", "--resume", "--iters", "9"], ["config.json"]),
    (["train", "volsdf", "--out", "nerf_run", "--resume", "--iters", "9"], ["not a VolSDF run"]),
    (["train", "sdf", "--out", "nerf_run", "--resume", "--iters", "9"], ["not a neural-SDF run"]),
    (["train", "sdf", "--out", "sdf_nockpt", "--resume", "--iters", "9"], ["checkpoint.pt"]),
    (["train", "sdf", "--out", "sdf_badcfg", "--resume", "--iters", "9"], ["config.json"]),
    (["train", "nerf", "--out", "nerf_corrupt", "--resume", "--iters", "9"], ["nerf_corrupt/"]),
    # box runs (train box) where a NeRF / neural-SDF run is expected, and the other way round
    (["eval", "box_run"], ["box_run", "box"]),
    (["render", "box_run"], ["box_run", "box"]),
    (["mesh", "box_run", "--out", "OUT/m.ply"], ["box_run", "box"]),
    (["train", "nerf", "--out", "box_run", "--resume", "--iters", "9"], ["box_run", "box"]),
    (["train", "sdf", "--out", "box_run", "--resume", "--iters", "9"], ["not a neural-SDF run"]),
    (["train", "box", "--out", "nerf_run", "--resume", "--iters", "9"], ["not a box run"]),
    (["train", "box", "--out", "sdf_run", "--resume", "--iters", "9"], ["not a box run"]),
    (["train", "box", "--out", "nope", "--resume", "--iters", "9"], ["nope", "not found"]),
    (["train", "box", "--out", "box_corrupt", "--resume", "--iters", "9"], ["box_corrupt/"]),
    (["train", "sdf", "--out", "sdf_corrupt", "--resume", "--iters", "9"], ["sdf_corrupt"]),
    # an output path that is a file, or lies under a file
    (["demo", "--out", "afile", "--quiet"], ["--out afile", "is a file"]),
    (["train", "box", "--data", "bl", "--out", "afile"], ["--out afile", "is a file"]),
    (["train", "box", "--out", "afile", "--resume", "--iters", "9"], ["--out afile", "is a file"]),
    (["train", "nerf", "--data", "builtin", "--out", "afile", *TN], ["--out afile"]),
    (["train", "nerf", "--data", "builtin", "--out", "afile/run", *TN], ["afile is a file"]),
    (["train", "volsdf", "--data", "builtin", "--out", "afile", *TN], ["--out afile"]),
    (["train", "sdf", "--points", "ok.npz", "--out", "afile"], ["--out afile", "is a file"]),
    (["train", "nerf", "--out", "afile", "--resume", "--iters", "9"], ["--out afile"]),
    (["eval", "nerf_run", "--out", "afile"], ["--out afile", "is a file"]),
    (["eval", "nerf_run", "--out", "afile/sub"], ["--out afile/sub", "afile is a file"]),
    (["eval", "nerf_blocked"], ["nerf_blocked/eval_val", "is a file"]),
    (["render", "nerf_blocked"], ["nerf_blocked/render_spiral", "is a file"]),
    (["mesh", "--sdf", "torus", "--out", "emptydir"], [".ply"]),
    (["mesh", "--sdf", "torus", "--out", "afile/m.ply"], ["afile is a file"]),
    (["mesh", "--sdf", "torus", "--out", "dir.ply"], ["--out dir.ply", "is a folder"]),
    (["bench", "--quick", "--json", "afile/b.json"], ["--json afile/b.json", "afile is a file"]),
    (["bench", "--quick", "--json", "emptydir"], ["--json emptydir", "is a folder"]),
    (["bench", "encoding", "--rays", "8"], ["--rays and --samples", "composite"]),
    # numbers that parse but are out of range for the command
    (["train", "box", "--data", "bl", "--out", "OUT", "--near", "-1"], ["--near", "--far"]),
    (["train", "box", "--data", "bl", "--out", "OUT", "--near", "6"], ["--near", "--far"]),
    (["train", "nerf", "--data", "builtin", "--out", "OUT", "--near", "4", "--far", "1"], ["near"]),
    (["train", "volsdf", "--data", "builtin", "--out", "OUT", "--beta-min", "1"], ["--beta-min"]),
    # a surface field under `train nerf`, which has none of its flags or defaults
    (
        ["train", "nerf", "--data", "builtin", "--out", "OUT", "--field", "hash_sdf"],
        ["surface field", "train volsdf --field hash_sdf"],
    ),
    (
        ["train", "nerf", "--data", "builtin", "--out", "OUT", "--field", "volsdf"],
        ["train volsdf --field volsdf"],
    ),
    (["train", "sdf", "--points", "ok.npz", "--out", "OUT", "--resolution", "4"], ["--resolution"]),
    (["train", "sdf", "--points", "ok.npz", "--out", "OUT", "--eikonal-weight", "-1"], ["--eik"]),
    (["mesh", "--sdf", "torus", "--out", "OUT/m.ply", "--resolution", "0"], ["--resolution"]),
    (["eval", "nerf_run", "--march-step", "0.1", "--out", "OUT"], ["--march-step", "grid"]),
]


def _case_id(case) -> str:
    return " ".join(a for a in case[0] if a not in TN)[:60]


@pytest.mark.parametrize("argv, needles", CASES, ids=[_case_id(c) for c in CASES])
def test_user_error_is_one_line_exit_2_and_writes_nothing(
    world, tmp_path, monkeypatch, capsys, argv, needles
):
    monkeypatch.chdir(world)
    out = tmp_path / "out"
    argv = [a.replace("OUT", str(out)) for a in argv]
    before = _snapshot(world)
    _fails_cleanly(argv, capsys, needles)
    assert not out.exists()
    assert _snapshot(world) == before  # no output, no half-written or temporary file


# ------------------------------------------------------------ argparse errors (exit 2)

ARGPARSE_CASES = [
    # unknown options and commands, for every command
    (["frobnicate"], "invalid choice"),
    (["train", "frobnicate", "--out", "o"], "invalid choice"),
    (["demo", "--bogus"], "unrecognized arguments: --bogus"),
    (["train", "box", "--data", "bl", "--out", "o", "--bogus"], "unrecognized arguments"),
    (["train", "nerf", "--out", "o", "--bogus"], "unrecognized arguments: --bogus"),
    (["train", "volsdf", "--out", "o", "--bogus"], "unrecognized arguments: --bogus"),
    (["train", "sdf", "--out", "o", "--bogus"], "unrecognized arguments: --bogus"),
    (["eval", "nerf_run", "--bogus"], "unrecognized arguments: --bogus"),
    (["render", "nerf_run", "--bogus"], "unrecognized arguments: --bogus"),
    (["mesh", "--sdf", "torus", "--out", "m.ply", "--bogus"], "unrecognized arguments"),
    (["bench", "--bogus"], "unrecognized arguments: --bogus"),
    (["bench", "frobnicate"], "invalid choice"),
    (["bench", "--rays", "0"], "argument --rays"),
    (["bench", "--samples", "-1"], "argument --samples"),
    (["eval", "nerf_run", "--split", "training"], "argument --split"),
    # zero, negative, non-finite and malformed numbers
    (["demo", "--iters", "0"], "argument --iters"),
    (["demo", "--size", "-4"], "argument --size"),
    (["demo", "--frames", "nan"], "argument --frames"),
    (["train", "box", "--data", "bl", "--out", "o", "--iters", "-1"], "argument --iters"),
    (["train", "box", "--data", "bl", "--out", "o", "--far", "inf"], "argument --far"),
    (["train", "box", "--data", "bl", "--out", "o", "--near", "nan"], "argument --near"),
    (["train", "box", "--data", "bl", "--out", "o", "--frames", "-1"], "argument --frames"),
    (["train", "box", "--data", "bl", "--out", "o", "--lr", "nan"], "argument --lr"),
    (["train", "nerf", "--out", "o", "--iters", "0"], "argument --iters"),
    (["train", "nerf", "--out", "o", "--batch", "-8"], "argument --batch"),
    (["train", "nerf", "--out", "o", "--far", "inf"], "argument --far"),
    (["train", "nerf", "--out", "o", "--near", "nan"], "argument --near"),
    (["train", "nerf", "--out", "o", "--max-seconds", "nan"], "argument --max-seconds"),
    (["train", "nerf", "--out", "o", "--max-seconds", "-1"], "argument --max-seconds"),
    (["train", "nerf", "--out", "o", "--t-threshold", "nan"], "argument --t-threshold"),
    (["train", "nerf", "--out", "o", "--downscale", "0"], "argument --downscale"),
    (["train", "nerf", "--out", "o", "--lr", "inf"], "argument --lr"),
    (["train", "nerf", "--out", "o", "--aabb", "-1"], "argument --aabb"),
    (["train", "volsdf", "--out", "o", "--beta", "0"], "argument --beta"),
    (["train", "volsdf", "--out", "o", "--eikonal-weight", "nan"], "argument --eikonal-weight"),
    (["train", "sdf", "--out", "o", "--iters", "0"], "argument --iters"),
    (["train", "sdf", "--out", "o", "--max-seconds", "nan"], "argument --max-seconds"),
    (["train", "sdf", "--out", "o", "--normal-weight", "inf"], "argument --normal-weight"),
    (["train", "sdf", "--out", "o", "--resolution", "1.5"], "argument --resolution"),
    (["eval", "nerf_run", "--max-images", "-1"], "argument --max-images"),
    (["eval", "nerf_run", "--chunk", "0"], "argument --chunk"),
    (["eval", "nerf_run", "--march-step", "nan"], "argument --march-step"),
    (["render", "nerf_run", "--frames", "0"], "argument --frames"),
    (["render", "nerf_run", "--size", "0x4"], "argument --size"),
    (["render", "nerf_run", "--size", "64"], "argument --size"),
    (["mesh", "--sdf", "torus", "--out", "m.ply", "--level", "nan"], "argument --level"),
    (["mesh", "--sdf", "torus", "--out", "m.ply", "--bounds", "0"], "argument --bounds"),
    (["mesh", "--sdf", "torus", "--out", "m.ply", "--resolution", "x"], "argument --resolution"),
]


@pytest.mark.parametrize(
    "argv, needle", ARGPARSE_CASES, ids=[" ".join(c[0]) for c in ARGPARSE_CASES]
)
def test_bad_option_exits_2_before_doing_anything(world, monkeypatch, capsys, argv, needle):
    monkeypatch.chdir(world)
    before = _snapshot(world)
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2
    last = err.strip().splitlines()[-1]  # argparse: the usage, then one error line
    assert last.startswith("warpnerf") and "error: " in last and needle in last, err
    assert "Traceback" not in err
    assert _snapshot(world) == before


# ------------------------------------------------------------- unreadable files (chmod 000)

# (argv with SRC = a copy of the world's ``source``, the file (. = SRC) made unreadable, needles)
UNREADABLE = [
    (["train", "box", "--data", "SRC", "--out", "OUT"], "bl", ".", ["src", "not readable"]),
    (_train("SRC"), "bl", ".", ["src", "not readable"]),
    (_train("SRC"), "bl", "transforms_train.json", ["transforms_train.json", "cannot read"]),
    (["train", "box", "--data", "SRC", "--out", "OUT"], "bl", "train/r_1.png",
     ["r_1.png", "cannot read image"]),
    (["train", "sdf", "--points", "SRC/ok.npz", "--out", "OUT"], ".", "ok.npz",
     ["ok.npz", "unreadable"]),
    (["mesh", "--sdf", "SRC/nan_scene.json", "--out", "OUT/m.ply"], ".", "nan_scene.json",
     ["nan_scene.json", "not a readable"]),
    (["train", "sdf", "--out", "SRC", "--resume", "--iters", "9"], "sdf_run", "config.json",
     ["config.json"]),
    (["mesh", "SRC", "--out", "OUT/m.ply"], "sdf_run", "config.json", ["config.json"]),
    (["eval", "SRC"], "nerf_run", "config.json", ["config.json"]),
    (["eval", "SRC"], "nerf_run", "checkpoint.pt", ["checkpoint.pt"]),
    (["mesh", "SRC", "--out", "OUT/m.ply"], "sdf_run", "checkpoint.pt", ["checkpoint.pt"]),
]  # fmt: skip


def _deny_reads(monkeypatch, victim: Path) -> None:
    """What ``chmod 000 victim`` does to a non-root process, for tests that run as root (CI):
    opening, listing or ``os.access``-checking ``victim`` (or anything under it, when it is a
    folder) fails with EACCES."""
    import builtins
    import io

    victim = victim.resolve()

    def denied(path) -> bool:
        try:
            p = Path(os.fsdecode(path)).resolve()
        except (TypeError, ValueError):
            return False  # a file descriptor or a file object
        return p == victim or victim in p.parents

    def guard(fn):
        def wrapped(path, *args, **kwargs):
            if denied(path):
                raise PermissionError(13, "Permission denied", os.fsdecode(path))
            return fn(path, *args, **kwargs)

        return wrapped

    for mod, name in [(builtins, "open"), (io, "open"), (os, "open"), (os, "scandir"),
                      (os, "listdir")]:  # fmt: skip
        monkeypatch.setattr(mod, name, guard(getattr(mod, name)))
    access = os.access
    monkeypatch.setattr(os, "access", lambda p, m, **kw: not denied(p) and access(p, m, **kw))


@pytest.mark.parametrize(
    "argv, source, victim, needles",
    UNREADABLE,
    ids=[f"{_case_id(c)} ({c[2]})" for c in UNREADABLE],
)
def test_unreadable_file(world, tmp_path, monkeypatch, capsys, argv, source, victim, needles):
    """chmod 000 on a file or folder; as root (which reads it anyway) the denial is emulated."""
    src = tmp_path / "src"
    if source == ".":
        src.mkdir()
        shutil.copy(world / victim, src / victim)
    else:
        shutil.copytree(world / source, src)
    out = tmp_path / "out"
    argv = [a.replace("SRC", str(src)).replace("OUT", str(out)) for a in argv]
    mode = 0o755 if (src / victim).is_dir() else 0o644
    if IS_ROOT:
        _deny_reads(monkeypatch, src / victim)
    (src / victim).chmod(0)
    try:
        _fails_cleanly(argv, capsys, needles)
    finally:
        monkeypatch.undo()
        (src / victim).chmod(mode)
    assert not out.exists()


# ----------------------------------------------------------------- end to end (subprocesses)


def _run_all(commands, cwd) -> list:
    """Runs ``python *args`` for each args in ``commands`` side by side (their start-up, importing
    torch and warp, dominates); returns the finished processes."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    procs = [
        subprocess.Popen([sys.executable, *args], cwd=cwd, env=env, text=True,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        for args in commands
    ]  # fmt: skip
    done = []
    for p in procs:
        out, err = p.communicate(timeout=300)
        done.append(subprocess.CompletedProcess(p.args, p.returncode, out, err))
    return done


def _one_error_line(p, *needles, status=2):
    """Exit ``status``, no traceback, and the last stderr line is the error naming ``needles``
    (argparse prints its usage before it; nothing else may)."""
    err = p.stderr
    lines = [x for x in err.splitlines() if x.strip()]
    assert p.returncode == status, (p.args, p.returncode, err)
    assert "Traceback" not in err and lines, err
    assert "error" in lines[-1] and all(n in lines[-1] for n in needles), (needles, err)
    assert len(lines) == 1 or lines[0].startswith("usage:"), err


def test_end_to_end_subprocesses(world):
    """Through the interpreter: a CLI user error (bad pose) and an unknown option, demo 02 with
    an --out that is a file (argparse's error, as in 01 and 06-09) and demo 03 with a missing
    --data folder (the caught UserError, as in 04, 05, 08-10)."""
    cli = ["-m", "warpnerf.cli"]
    bad_pose, unknown, d02, d03 = _run_all(
        [
            [*cli, "train", "nerf", "--data", "bl_inf", "--out", "o_sub", *TN],
            [*cli, "eval", "nerf_run", "--bogus"],
            [str(ROOT / "demos" / "02_fit_box.py"), "--out", "afile", "--iters", "1"],
            [str(ROOT / "demos" / "03_nerf_lego.py"), "--data", "nope", "--out", "o03"],
        ],
        world,
    )
    _one_error_line(bad_pose, "bl_inf/transforms_train.json", "frames[1].transform_matrix")
    assert bad_pose.stderr.startswith("warpnerf train: error: ")
    _one_error_line(unknown, "unrecognized arguments: --bogus")
    _one_error_line(d02, "--out afile is a file")
    _one_error_line(d03, "03_nerf_lego: error: nope", "not found")
    assert not (world / "o_sub").exists() and not (world / "o03").exists()
    assert not (world / "nerf_run" / "eval_val").exists()


# ------------------------------------------------------------------- demos, in-process

DEMOS = sorted(p.name for p in (ROOT / "demos").glob("[0-9][0-9]_*.py"))
DATA_FLAG = {"02": "--data", "03": "--data", "04": "--data", "05": "--data", "08": "--points",
             "09": "--data", "10": "--data"}  # fmt: skip


def _demo_fails_cleanly(demo, argv, capsys, needles):
    """Runs demos/``demo``'s main(argv): a non-zero status (returned, or argparse's / SystemExit's)
    and the last stderr line is the error naming ``needles``; no traceback."""
    spec = importlib.util.spec_from_file_location(f"demo_{demo[:2]}", ROOT / "demos" / demo)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    try:
        status = mod.main(argv)
    except SystemExit as e:  # argparse: 2; SystemExit("error: ...") prints the message, exit 1
        status = e.code
        if isinstance(status, str):
            print(status, file=sys.stderr)
            status = 1
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.strip()]
    assert status not in (0, None), err
    assert "Traceback" not in err and lines, err
    assert "error" in lines[-1] and all(n in lines[-1] for n in needles), (needles, err)


@pytest.mark.parametrize("demo", DEMOS)
def test_demo_out_is_a_file(world, monkeypatch, capsys, demo):
    monkeypatch.chdir(world)
    before = _snapshot(world)
    _demo_fails_cleanly(demo, ["--out", "afile", "--iters", "1"], capsys, ["--out afile"])
    assert _snapshot(world) == before


@pytest.mark.parametrize("demo", [d for d in DEMOS if d[:2] in DATA_FLAG])
def test_demo_missing_data(world, tmp_path, monkeypatch, capsys, demo):
    monkeypatch.chdir(world)
    out = tmp_path / "out"
    argv = [DATA_FLAG[demo[:2]], "nope", "--out", str(out), "--iters", "1"]
    _demo_fails_cleanly(demo, argv, capsys, ["nope"])
    assert not out.exists()


@pytest.mark.parametrize(
    "demo, args",
    [
        ("01_render_volume.py", ["--frames", "1", "--size", "8", "--samples", "4"]),
        ("06_sphere_trace_torus.py", ["--frames", "1", "--size", "8", "--iters", "8"]),
    ],
)
def test_demo_os_refusal_is_one_line(tmp_path, monkeypatch, capsys, demo, args):
    """A path the file system refuses (a name longer than NAME_MAX) is a one-line error with
    status 2 in the demos too, as in the `warpnerf` command (they share errors.exit_status)."""
    monkeypatch.chdir(tmp_path)
    out = tmp_path / ("x" * 300)
    _demo_fails_cleanly(demo, ["--out", str(out), *args], capsys, ["ENAMETOOLONG"])
