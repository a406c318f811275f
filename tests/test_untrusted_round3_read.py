"""Security round 3, the reading side: decompression bombs, checkpoint integrity, dataset
confinement and image decoding (issue 32, classes 2, 3, 4 and 5).

Each class has tests that failed on the code before the fix:
  2  a compressed checkpoint, an .npz bomb, .npy/.npz headers declaring more than the file holds,
     a PNG declaring a huge size and an animated PNG are refused (or read) before inflating
  3  a checkpoint missing a part, a key, a shape or with a wrong optimiser state is refused by
     eval / render / mesh / train --resume of every run kind, one line, exit 2
  4  transforms*.json file paths outside the dataset (absolute, '..', symlinks) are refused unless
     --allow-outside-paths
  5  a CMYK JPEG loads as its colour, a palette with transparency as RGBA
The bombs are built small (streamed compression, header-only files) and are never inflated.
"""

from __future__ import annotations

import io as _io
import json
import shutil
import struct
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch

from warpnerf import outputs
from warpnerf.cli import main
from warpnerf.data import load_dataset
from warpnerf.errors import UserError
from warpnerf.train.sdf import load_points

from .test_datasets import make_blender, make_nerfstudio
from .test_hostile_runs import _copy, _one_line, runs  # noqa: F401  (runs: the tiny runs)

# ------------------------------------------------------------ 2: decompression bombs


def _deflated_copy(src: bytes, dst: Path) -> None:
    """A torch zip checkpoint rewritten with every member deflated (torch never writes this)."""
    with zipfile.ZipFile(_io.BytesIO(src)) as zin, zipfile.ZipFile(dst, "w") as zout:
        for info in zin.infolist():
            zout.writestr(info.filename, zin.read(info), compress_type=zipfile.ZIP_DEFLATED)


def test_compressed_checkpoint_is_refused_before_torch_inflates_it(tmp_path):
    buf = _io.BytesIO()
    torch.save({"step": 1, "w": torch.zeros(1 << 24)}, buf)  # 64 MiB of zeros
    path = tmp_path / "checkpoint.pt"
    _deflated_copy(buf.getvalue(), path)
    assert path.stat().st_size < 1 << 20  # a 64x bomb in well under a megabyte
    with pytest.raises(UserError, match="compressed") as e:
        outputs.load_checkpoint(path)
    assert str(path) in str(e.value) and "'" in str(e.value)  # the member is named


def test_legacy_torch_format_is_refused_before_it_allocates(tmp_path):
    """The pre-zip format declares storage sizes that torch allocates before reading."""
    path = tmp_path / "checkpoint.pt"
    torch.save({"step": 1}, path, _use_new_zipfile_serialization=False)
    with pytest.raises(UserError, match="not torch's zip format"):
        outputs.load_checkpoint(path)


def _npz_bomb(path: Path, n_bytes: int, name: str = "points.npy") -> None:
    """An .npz whose one member is an [N, 3] float32 array of zeros, deflated while streamed
    (nothing of its inflated size is held in memory)."""
    header = _io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "<f4", "fortran_order": False, "shape": (n_bytes // 12, 3)}
    )
    zeros = bytes(1 << 20)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        with z.open(name, "w", force_zip64=True) as f:
            f.write(header.getvalue())
            for _ in range(n_bytes // len(zeros)):
                f.write(zeros)


def test_npz_bomb_is_refused_from_its_zip_directory(tmp_path):
    path = tmp_path / "cloud.npz"
    _npz_bomb(path, 320 << 20)
    size = path.stat().st_size
    assert size < 1 << 20
    with pytest.raises(UserError) as e:
        load_points(path)
    msg = str(e.value)
    assert str(path) in msg and "limit" in msg and str(io_limit(size)) in msg, msg


def io_limit(size: int) -> int:
    from warpnerf.data.arrays import inflate_limit

    return inflate_limit(size)


def test_inflate_limit_is_overridable_and_real_npz_files_still_load(tmp_path, monkeypatch):
    g = np.random.default_rng(0).normal(size=(300, 3)).astype(np.float32)
    np.savez_compressed(tmp_path / "c.npz", points=g, normals=g)
    np.savez(tmp_path / "s.npz", verts=g)
    pts, nrm = load_points(tmp_path / "c.npz")
    assert np.array_equal(pts, g) and np.allclose(nrm, g / np.linalg.norm(g, axis=1)[:, None])
    assert np.array_equal(load_points(tmp_path / "s.npz")[0], g)
    from warpnerf.data.arrays import load_npz

    monkeypatch.setenv("WARPNERF_MAX_INFLATE", "1000")
    with pytest.raises(UserError, match="WARPNERF_MAX_INFLATE"):
        load_npz(tmp_path / "c.npz")


def _lying_npy(shape, data: bytes = b"\0" * 64) -> bytes:
    header = _io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "<f8", "fortran_order": False, "shape": shape}
    )
    return header.getvalue() + data


def test_npy_and_npz_headers_cannot_declare_more_than_the_file_holds(tmp_path):
    (tmp_path / "poses_bounds.npy").write_bytes(_lying_npy((10**9, 17)))
    (tmp_path / "images").mkdir()
    with pytest.raises(UserError, match="declares shape") as e:
        load_dataset(tmp_path, "train", fmt="llff")
    assert "poses_bounds.npy" in str(e.value)
    with zipfile.ZipFile(tmp_path / "c.npz", "w") as z:
        z.writestr("points.npy", _lying_npy((10**9, 3)))
    with pytest.raises(UserError, match="declares shape"):
        load_points(tmp_path / "c.npz")
    from warpnerf.data.arrays import load_npy

    np.save(tmp_path / "ok.npy", np.arange(6.0).reshape(2, 3))
    assert np.array_equal(load_npy(tmp_path / "ok.npy"), np.arange(6.0).reshape(2, 3))
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(UserError, match="pickle"):
        load_npy(tmp_path / "obj.npy")


def _chunk(kind: bytes, data: bytes) -> bytes:
    crc = zlib.crc32(kind + data) & 0xFFFFFFFF
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)


def _png(w: int, h: int, idat: bytes, extra: bytes = b"", tail: bytes = b"") -> bytes:
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 6, 0, 0, 0)  # 8-bit RGBA
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + extra + _chunk(b"IDAT", idat) + tail
            + _chunk(b"IEND", b""))  # fmt: skip


@pytest.fixture
def decoded(monkeypatch):
    """Records every image decode (PIL's load) and every frame sought."""
    from PIL import ImageFile, PngImagePlugin

    seen = {"loads": 0, "frames": set()}
    load, seek = ImageFile.ImageFile.load, PngImagePlugin.PngImageFile.seek

    def counting_load(self):
        seen["loads"] += 1
        return load(self)

    def counting_seek(self, frame):
        seen["frames"].add(frame)
        return seek(self, frame)

    monkeypatch.setattr(ImageFile.ImageFile, "load", counting_load)
    monkeypatch.setattr(PngImagePlugin.PngImageFile, "seek", counting_seek)
    return seen


def test_png_declaring_a_huge_size_is_refused_before_decoding(tmp_path, decoded):
    from warpnerf.data.images import MAX_PIXELS

    side = 12000  # 144 M pixels: past the limit, below PIL's own bomb error (it only warns)
    assert side * side > MAX_PIXELS
    root = make_blender(tmp_path, n=1, w=4, h=4)
    (root / "train" / "r_0.png").write_bytes(_png(side, side, zlib.compress(b"\0" * 64)))
    with pytest.raises(UserError) as e:
        load_dataset(root)
    msg = str(e.value)
    assert "r_0.png" in msg and f"{side}x{side}" in msg and str(MAX_PIXELS) in msg, msg
    assert "frames[0].file_path" in msg
    assert decoded["loads"] == 0, "the image was decoded before its size was checked"


def test_animated_png_reads_its_first_frame_only(tmp_path, decoded):
    n = 2000  # frames of 1x1 (a 10^4-frame bomb has the same shape, only more frames)
    seq = iter(range(2 * n))
    actl = _chunk(b"acTL", struct.pack(">II", n, 0))

    def fctl():
        return _chunk(b"fcTL", struct.pack(">IIIIIHHBB", next(seq), 1, 1, 0, 0, 1, 10, 0, 0))

    first = actl + fctl()  # (sequence number 0, before the later frames' numbers)
    later = b"".join(
        fctl() + _chunk(b"fdAT", struct.pack(">I", next(seq)) + zlib.compress(b"\0\xff\0\0\xff"))
        for _ in range(n - 1)
    )
    root = make_blender(tmp_path, n=1, w=1, h=1)
    data = _png(1, 1, zlib.compress(b"\0" + bytes([10, 20, 30, 255])), extra=first, tail=later)
    (root / "train" / "r_0.png").write_bytes(data)
    assert len(data) < 150_000
    ds = load_dataset(root)
    assert ds.images.shape == (1, 1, 1, 3)
    assert np.allclose(ds.images[0, 0, 0].numpy(), np.array([10, 20, 30]) / 255.0)
    assert decoded["frames"] <= {0}, sorted(decoded["frames"])[:5]


# ------------------------------------------------------------ 3: checkpoint integrity


def _doctor(run: Path, edit) -> None:
    ck = outputs.load_checkpoint(run / "checkpoint.pt")
    edit(ck)
    (run / "checkpoint.pt").unlink()  # (a file the user replaced: not warpnerf's any more)
    outputs.save_checkpoint(run / "checkpoint.pt", ck)


def _first_key(d: dict) -> str:
    return next(iter(d))


def _drop_first(d: dict) -> None:
    d.pop(_first_key(d))


def _bad_moment(ck):
    st = ck["optimizer"]["state"]
    st[_first_key(st)]["exp_avg"] = torch.zeros(7)


EVAL = ["eval", "RUN", "--max-images", "1"]
RENDER = ["render", "RUN", "--frames", "1", "--size", "8x8"]
MESH = ["mesh", "RUN", "--out", "m.ply", "--resolution", "8", "--no-screenshot"]


def _resume(kind):
    return ["train", kind, "--out", "RUN", "--resume", "--iters", "5", "--quiet"]


# (run kind, what is wrong, the edit, the command, words of the error)
DOCTORED = [
    ("nerf", "no coarse part", lambda c: c["fields"].pop("coarse"), EVAL, ["coarse"]),
    ("nerf", "empty fields", lambda c: c["fields"].clear(), RENDER, ["coarse"]),
    ("nerf", "an extra fine part", lambda c: c["fields"].update(fine=c["fields"]["coarse"]),
     EVAL, ["'fine'"]),
    ("nerf", "a missing key", lambda c: _drop_first(c["fields"]["coarse"]), EVAL, ["Missing"]),
    ("volsdf", "no coarse part", lambda c: c["fields"].pop("coarse"), MESH, ["coarse"]),
    ("volsdf", "a wrong shape", lambda c: c["fields"]["coarse"].update(
        {_first_key(c["fields"]["coarse"]): torch.zeros(3)}), EVAL, ["size mismatch"]),
    ("nerf", "a wrong optimiser moment", _bad_moment, _resume("nerf"), ["optimizer", "exp_avg"]),
    ("volsdf", "a wrong optimiser moment", _bad_moment, _resume("volsdf"), ["exp_avg"]),
    ("nerf", "a bad generator", lambda c: c.update(generator=torch.zeros(3)), _resume("nerf"),
     ["'generator'"]),
    ("nerf", "a bad step", lambda c: c.update(step="2"), EVAL, ["'step'"]),
    ("sdf", "a missing key", lambda c: _drop_first(c["model"]), MESH, ["Missing"]),
    ("sdf", "a wrong optimiser moment", _bad_moment, _resume("sdf"), ["exp_avg"]),
    ("sdf", "a bad generator", lambda c: c.update(generator=torch.zeros(3)), _resume("sdf"),
     ["'generator'"]),
    ("box", "no box parameters", lambda c: c["volume"].clear(), _resume("box"), ["Missing"]),
    ("box", "a wrong optimiser moment", _bad_moment, _resume("box"), ["exp_avg"]),
]  # fmt: skip


@pytest.mark.parametrize(
    "kind,what,edit,argv,words", DOCTORED, ids=[f"{d[0]}-{d[1]}" for d in DOCTORED]
)
def test_incomplete_checkpoints_are_refused(runs, tmp_path, monkeypatch, capsys, kind, what,  # noqa: F811
                                            edit, argv, words):  # fmt: skip
    import warpnerf.mesh

    run = _copy(runs, kind, tmp_path)
    shutil.copy(runs / "ok.npz", tmp_path / "ok.npz")  # (the sdf run's points, a relative path)
    _doctor(run, edit)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(warpnerf.mesh, "screenshot", _no_screenshot)
    capsys.readouterr()
    rc = main([str(run) if a == "RUN" else a for a in argv])
    _one_line(capsys, rc, 2, str(run / "checkpoint.pt"), *words)


def _no_screenshot(*args, **kwargs):
    raise ImportError("screenshots are skipped in these tests")


def test_untouched_checkpoints_still_load_and_resume(runs, tmp_path, monkeypatch):  # noqa: F811
    monkeypatch.chdir(tmp_path)
    shutil.copy(runs / "ok.npz", tmp_path / "ok.npz")
    for kind in ("nerf", "sdf", "box"):
        run = _copy(runs, kind, tmp_path)
        assert main([str(run) if a == "RUN" else a for a in _resume(kind)]) == 0, kind
    assert main(["eval", str(tmp_path / "nerf"), "--max-images", "1"]) == 0


# ------------------------------------------------------------ 4: dataset confinement


def _set_path(js_path: Path, i: int, value: str) -> None:
    js = json.loads(js_path.read_text())
    js["frames"][i]["file_path"] = value
    js_path.write_text(json.dumps(js))


@pytest.mark.parametrize("how", ["dotdot", "absolute", "symlink"])
def test_blender_paths_stay_inside_the_dataset(tmp_path, how, capsys):
    root = make_blender(tmp_path / "ds", n=2)
    make_blender(root, n=1, split="val")  # (warpnerf data loads both splits)
    outside = tmp_path / "secret"
    outside.mkdir()
    shutil.copy(root / "train" / "r_1.png", outside / "img.png")
    js = root / "transforms_train.json"
    if how == "dotdot":
        _set_path(js, 1, "../secret/img.png")
    elif how == "absolute":
        _set_path(js, 1, str(outside / "img.png"))
    else:
        (root / "train" / "r_1.png").unlink()
        (root / "train" / "r_1.png").symlink_to(outside / "img.png")
    with pytest.raises(UserError) as e:
        load_dataset(root)
    msg = str(e.value)
    assert str(js) in msg and "frames[1].file_path" in msg and "--allow-outside-paths" in msg
    assert ("resolves" in msg) == (how == "symlink"), msg
    ds = load_dataset(root, allow_outside=True)
    assert len(ds) == 2
    assert main(["data", str(root)]) == 2
    _one_line(capsys, 2, 2, "frames[1].file_path")
    assert main(["data", str(root), "--allow-outside-paths"]) == 0


def test_nerfstudio_paths_stay_inside_the_dataset(tmp_path):
    root = make_nerfstudio(tmp_path / "ns", n=3, per_frame={2: {"file_path": "../x.png"}})
    shutil.copy(root / "images" / "frame_00002.png", tmp_path / "x.png")
    with pytest.raises(UserError, match=r"frames\[2\]\.file_path '\.\./x\.png'"):
        load_dataset(root, "train", holdout=0)
    assert len(load_dataset(root, "train", holdout=0, allow_outside=True)) == 3
    # a symlinked folder inside the dataset whose target is inside it too is fine
    (root / "alias").symlink_to(root / "images")
    _set_path(root / "transforms.json", 2, "alias/frame_00002.png")
    assert len(load_dataset(root, "train", holdout=0)) == 3


def test_train_flag_reaches_the_loader(tmp_path):
    root = make_blender(tmp_path / "ds", n=2)
    make_blender(tmp_path / "ds", n=1, split="val")
    (tmp_path / "elsewhere").mkdir()
    shutil.move(root / "train" / "r_1.png", tmp_path / "elsewhere" / "r_1.png")
    _set_path(root / "transforms_train.json", 1, "../elsewhere/r_1.png")
    tiny = ["--iters", "1", "--batch", "16", "--samples", "4", "--layers", "2", "--width", "8",
            "--pos-freqs", "1", "--dir-freqs", "1", "--val-images", "0", "--quiet",
            "--no-tensorboard", "--data", str(root)]  # fmt: skip
    assert main(["train", "nerf", *tiny, "--out", str(tmp_path / "a")]) == 2
    assert main(["train", "nerf", *tiny, "--out", str(tmp_path / "b"),
                 "--allow-outside-paths"]) == 0  # fmt: skip
    saved = json.loads((tmp_path / "b" / "config.json").read_text())
    assert saved["allow_outside_paths"] is True  # (eval of the run loads the data as trained)


# ------------------------------------------------------------ 5: image decoding


def test_cmyk_jpeg_loads_as_its_colour(tmp_path):
    from PIL import Image

    colour = (30, 140, 200)
    root = make_blender(tmp_path, n=1, w=16, h=16)
    (root / "train" / "r_0.png").unlink()
    Image.new("RGB", (16, 16), colour).convert("CMYK").save(root / "train" / "r_0.jpg",
                                                            quality=95)  # fmt: skip
    assert Image.open(root / "train" / "r_0.jpg").mode == "CMYK"
    img = load_dataset(root).images[0].numpy() * 255.0
    assert np.abs(img - np.array(colour)).max() <= 3.0, img[8, 8]


def test_palette_with_transparency_and_grey_alpha_are_composited(tmp_path):
    from PIL import Image

    from warpnerf.data.images import read_image

    p = Image.new("P", (4, 4), 1)
    p.putpalette([0, 0, 0, 255, 0, 0] + [0] * 762)
    p.save(tmp_path / "p.png", transparency=1)  # red, fully transparent
    assert np.array_equal(read_image(tmp_path / "p.png")[0, 0], [1.0, 0.0, 0.0, 0.0])
    Image.new("LA", (2, 2), (128, 255)).save(tmp_path / "la.png")
    assert np.allclose(read_image(tmp_path / "la.png")[0, 0], [128 / 255] * 3 + [1.0])
    Image.new("I;16", (2, 2), 40000).save(tmp_path / "g16.png")
    assert np.allclose(read_image(tmp_path / "g16.png")[0, 0], [40000 / 65535] * 3)
    Image.new("RGB", (2, 2)).save(tmp_path / "t.png", format="TIFF")
    with pytest.raises(UserError, match="TIFF"):
        read_image(tmp_path / "t.png")
