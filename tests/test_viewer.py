"""The web viewer without a browser: camera conventions, the viewer renders what eval renders,
camera-path files (round trip, interpolation, hostile files, `render --path FILE`), the server's
address and clean shutdown, and the live viewer leaving the training unchanged."""

from __future__ import annotations

import json
import math
import socket

import numpy as np
import pytest

from warpnerf.cli.parser import main
from warpnerf.data.camera_path import CameraPath, interpolate_path, load_camera_path
from warpnerf.data.cameras import look_at
from warpnerf.errors import UserError

TINY = ["--data", "builtin", "--iters", "6", "--batch", "64", "--samples", "8", "--layers", "2",
        "--width", "16", "--builtin-size", "16", "--val-images", "0", "--quiet"]  # fmt: skip


@pytest.fixture(scope="module")
def nerf_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("viewer") / "r"
    assert main(["train", "nerf", *TINY, "--out", str(run)]) == 0
    return run


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _listening(port: int) -> list:
    """Local addresses (hex, as /proc/net/tcp writes them) listening on ``port``."""
    out = []
    for name in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = open(name).read().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            parts = line.split()
            addr, p = parts[1].split(":")
            if int(p, 16) == port and parts[3] == "0A":  # LISTEN
                out.append(addr)
    return out


def test_camera_conventions_round_trip():
    from warpnerf.viewer.server import gl_to_opencv, opencv_to_gl

    c2w = look_at((1.0, -2.0, 0.5), (0.1, 0.2, 0.0)).double().numpy()
    wxyz, pos = gl_to_opencv(c2w)
    assert np.allclose(opencv_to_gl(wxyz, pos), c2w, atol=1e-6)  # (a float32 pose)
    # OpenCV's +z (viser's look direction) is OpenGL's -z
    r_cv = opencv_to_gl(wxyz, pos)[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    assert np.allclose(r_cv[:, 2], -c2w[:3, 2])


def test_viewer_renders_what_eval_renders(nerf_run):
    """A training camera rendered by the viewer's scene equals the eval renderer's image."""
    from warpnerf.io import to_uint8
    from warpnerf.train.nerf import load_data, load_run, render_dataset_image
    from warpnerf.viewer import load_scene

    scene = load_scene(nerf_run)
    cfg, model, _ = load_run(nerf_run)
    train = load_data(cfg, "train")
    rgb, depth, acc = render_dataset_image(model, cfg, train, 0)
    k = train.intrinsics[0]
    img = scene.render(train.c2w[0].numpy(), float(k[0]), float(k[1]), train.width, train.height)
    assert img.shape == (train.height, train.width, 3) and img.dtype == np.uint8
    assert np.abs(img.astype(int) - to_uint8(rgb).astype(int)).max() <= 1
    for mode in scene.modes:
        assert scene.render(train.c2w[0].numpy(), 20.0, 20.0, 12, 8, mode).shape == (8, 12, 3)
    assert scene.cameras.shape[0] == train.c2w.shape[0] and scene.images.dtype == np.uint8
    with pytest.raises(ValueError, match="mode"):
        scene.render(np.eye(4), 10.0, 10.0, 4, 4, "sparkles")
    with pytest.raises(ValueError, match="finite"):
        scene.render(np.full((4, 4), np.nan), 10.0, 10.0, 4, 4)


def test_sdf_scenes_render_normals_and_point_sdf_runs_work(tmp_path):
    from warpnerf.viewer import load_scene

    run = tmp_path / "s"
    assert main(["train", "volsdf", "--data", "builtin", "--field", "hash_sdf", "--hash-levels",
                 "3", "--hash-log2-size", "8", "--hash-max-res", "16", "--grid-res", "8",
                 "--builtin-size", "16", "--batch", "64", "--val-images", "0", "--quiet",
                 "--iters", "2", "--out", str(run)]) == 0  # fmt: skip
    scene = load_scene(run)
    assert "normals" in scene.modes and scene.occupied_cells() is not None
    eye = look_at((0.0, -3.0, 1.0), (0.0, 0.0, 0.0)).numpy()
    img = scene.render(eye, 20.0, 20.0, 16, 16, "normals")
    assert img.shape == (16, 16, 3) and img.std() > 0  # the sphere prior: a shaded disc
    pts = tmp_path / "p.npz"
    ang = np.random.default_rng(0).normal(size=(500, 3))
    np.savez(pts, points=(ang / np.linalg.norm(ang, axis=1, keepdims=True)).astype(np.float32))
    srun = tmp_path / "sdf"
    assert main(["train", "sdf", "--points", str(pts), "--out", str(srun), "--iters", "5",
                 "--batch", "128", "--resolution", "16", "--width", "16", "--layers", "2",
                 "--pos-freqs", "2",
                 "--quiet"]) == 0  # fmt: skip
    s2 = load_scene(srun)
    assert s2.modes[0] == "shaded"
    for mode in s2.modes:
        assert s2.render(eye, 20.0, 20.0, 8, 8, mode).shape == (8, 8, 3)


def test_box_fits_render_and_unknown_runs_are_clean_errors(tmp_path):
    """A box fit (the main job's task) is shown too: its frame of a training camera equals the
    fit's own renderer's image; missing or unknown runs are one-line errors."""
    from warpnerf.data.blender import load_blender
    from warpnerf.io import to_uint8
    from warpnerf.train.box_fit import load_box_run, render_box_views
    from warpnerf.viewer import load_scene

    from ._scene import write_box_folder

    write_box_folder(tmp_path / "scene", n_views=4, size=16, name="transforms_train.json")
    run = tmp_path / "box"
    assert main(["train", "box", "--data", str(tmp_path / "scene"), "--out", str(run), "--iters",
                 "3", "--frames", "0", "--quiet", "--samples", "16"]) == 0  # fmt: skip
    scene = load_scene(run)
    assert scene.cameras.shape[0] == 4 and scene.modes == ("rgb", "depth", "opacity")
    cfg, data, dev, _ = load_box_run(run)
    ds = load_blender(data, "train", background=(cfg.background,) * 3, holdout=0)
    from warpnerf.fields.sdf_volume import SDFVolume
    from warpnerf.io import load_checkpoint

    vol = SDFVolume("box", alpha=cfg.alpha, beta=cfg.beta)
    vol.load_state_dict(load_checkpoint(run / "checkpoint.pt")["volume"])
    rgb, _ = render_box_views(vol, ds.c2w[:1], ds.intrinsics[:1], 16, 16, cfg)
    k = ds.intrinsics[0]
    img = scene.render(ds.c2w[0].numpy(), float(k[0]), float(k[1]), 16, 16)
    assert np.abs(img.astype(int) - to_uint8(rgb[0]).astype(int)).max() <= 1
    with pytest.raises(UserError, match="no such run folder"):
        load_scene(tmp_path / "nothing")
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "config.json").write_text('{"model": "teapot"}')
    with pytest.raises(UserError, match="not one the viewer knows"):
        load_scene(tmp_path / "b")
    (tmp_path / "b" / "config.json").write_text("[1, 2")
    with pytest.raises(UserError, match="config"):
        load_scene(tmp_path / "b")


# ------------------------------------------------------------------------------- camera paths


def _keys():
    return np.stack([look_at((3 * math.cos(a), 3 * math.sin(a), 1.0), (0, 0, 0)).double().numpy()
                     for a in (0.0, 1.0, 2.0, 3.0)])  # fmt: skip


def test_interpolated_path_passes_through_its_keyframes():
    keys = _keys()
    cams = interpolate_path(keys, 31).double().numpy()
    for i, f in enumerate((0, 10, 20, 30)):  # 3 segments of 10 frames
        assert np.allclose(cams[f], keys[i], atol=1e-5)
    r = cams[:, :3, :3]
    assert np.allclose(r @ r.transpose(0, 2, 1), np.eye(3), atol=1e-5)  # rotations stay rotations
    assert np.allclose(np.linalg.det(r), 1.0, atol=1e-5)
    looped = interpolate_path(keys, 40, loop=True).numpy()
    assert np.allclose(looped[0], keys[0], atol=1e-5)
    assert np.allclose(looped[10], keys[1], atol=1e-5)
    assert interpolate_path(keys[:1], 5).shape == (5, 4, 4)


def test_camera_path_file_round_trip(tmp_path):
    p = CameraPath(_keys(), fov_y=0.7, aspect=1.5, frames=12, loop=True)
    p.save(tmp_path / "path.json")
    q = load_camera_path(tmp_path / "path.json")
    assert np.allclose(q.keyframes, p.keyframes) and (q.fov_y, q.aspect, q.frames, q.loop) == (
        0.7, 1.5, 12, True)  # fmt: skip
    k = q.intrinsics(300, 200)
    assert math.isclose(float(k[1]), 100 / math.tan(0.35), rel_tol=1e-6)


@pytest.mark.parametrize("edit, match", [
    (lambda d: d.pop("warpnerf_camera_path"), "not a warpnerf camera path"),
    (lambda d: d.update(keyframes=[]), "keyframes"),
    (lambda d: d.update(keyframes=[{"c2w": [[1, 0, 0, 0]] * 4}] * 1001), "keyframes"),
    (lambda d: d["keyframes"][1].update(c2w=[[1, 0, 0]] * 3), r"keyframes\[1\].c2w"),
    (lambda d: d["keyframes"][0]["c2w"][0].__setitem__(0, float("nan")), r"keyframes\[0\]"),
    (lambda d: d["keyframes"][2]["c2w"][0].__setitem__(0, 5.0), "not a rotation"),
    (lambda d: d.update(frames=0), "frames"),
    (lambda d: d.update(frames=1e9), "frames"),
    (lambda d: d.update(fov_y=4.0), "fov_y"),
    (lambda d: d.update(loop="yes"), "loop"),
    (lambda d: d.update(aspect=None), "aspect"),
])  # fmt: skip
def test_hostile_camera_path_files_are_refused(tmp_path, edit, match):
    d = CameraPath(_keys(), frames=10).to_dict()
    edit(d)
    f = tmp_path / "p.json"
    f.write_text(json.dumps(d))
    with pytest.raises(UserError, match=match):
        load_camera_path(f)


def test_render_follows_a_saved_camera_path(nerf_run, tmp_path, capsys):
    f = tmp_path / "mypath.json"
    CameraPath(_keys(), fov_y=0.6, aspect=2.0, frames=3).save(f)
    assert main(["render", str(nerf_run), "--path", str(f), "--size", "8x4"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["frames"] == 3 and res["size"] == [8, 4] and res["out"].endswith("render_mypath")
    assert main(["render", str(nerf_run), "--path", str(tmp_path / "none.json")]) == 2
    assert "no such file" in capsys.readouterr().err


# ------------------------------------------------------------------------------------ server


def test_server_binds_loopback_and_frees_its_port(nerf_run):
    from warpnerf.viewer import Viewer, load_scene

    port = _free_port()
    v = Viewer(load_scene(nerf_run), port=port)
    try:
        assert v.port == port and _listening(port)
        # 127.0.0.1 only: no wildcard (0.0.0.0 / ::) listener, so other hosts cannot connect
        assert set(_listening(port)) <= {"0100007F"}, _listening(port)
    finally:
        v.close()
    with socket.socket() as s:  # the port is free again
        s.bind(("127.0.0.1", port))


class _FakeClient:
    """What the viewer touches of a viser client: the id, set_background_image, the camera."""

    def __init__(self):
        self.client_id, self.images, self.poses = 1, [], []
        self.scene = self
        self.camera = self

    def set_background_image(self, img, **kw):
        self.images.append(img)

    def atomic(self):
        import contextlib

        return contextlib.nullcontext()

    def __setattr__(self, name, value):
        if name == "position":  # set after wxyz by the preview
            self.poses.append((self.__dict__.get("wxyz"), value))
        object.__setattr__(self, name, value)


def _train(run, hooks=()):
    from warpnerf.train.nerf import train_nerf
    from warpnerf.train.nerf_config import NeRFConfig

    cfg = NeRFConfig(data="builtin", iters=8, batch=64, n_coarse=8, n_layers=2, width=16,
                     builtin_size=16, val_images=0, seed=3)  # fmt: skip
    return train_nerf(cfg, run, progress=False, log=lambda *a: None, hooks=hooks)


def test_live_viewer_leaves_training_unchanged(tmp_path):
    """Training with the live viewer (no browser, then a watching client whose frames render
    between steps) gives the same losses as training without it."""
    from warpnerf.viewer import LiveViewer
    from warpnerf.viewer.server import _ClientState

    base = _train(tmp_path / "a")
    live = LiveViewer(tmp_path / "b", port=_free_port(), log=lambda *a: None)
    assert _train(tmp_path / "b", [live])["loss"] == base["loss"]
    assert live.viewer is None  # closed with the loop

    class Watching(LiveViewer):
        def on_start(self, task, step):
            super().on_start(task, step)
            st = _ClientState(_FakeClient())
            st.pose = (look_at((0.0, -4.0, 1.0), (0, 0, 0)).double().numpy(), 0.8, 1.0, 32)
            self.viewer._clients[1] = st
            self.viewer.refresh_seconds = 0.0
            self.client = st.client
            self.viewer._last_frame_seconds = 0.0
            self.viewer.settle_seconds = 1e9

        def on_step(self, step, history, lr):
            self.viewer._last_tick_frame = 0.0  # a frame after every step
            super().on_step(step, history, lr)

    class Noting(Watching):
        def close(self):
            self.text = self.viewer.train_info.content
            super().close()

    w = Noting(tmp_path / "c", port=_free_port(), log=lambda *a: None)
    assert _train(tmp_path / "c", [w])["loss"] == base["loss"]
    assert len(w.client.images) >= 4 and w.client.images[-1].shape[2] == 3
    assert w.text.startswith("training: step ") and "loss" in w.text

    class Hostile(Watching):  # a browser sending a broken camera: the training goes on
        def on_start(self, task, step):
            super().on_start(task, step)
            st = self.viewer._clients[1]
            st.pose = (np.full((4, 4), np.nan), 0.8, 1.0, 32)

    h = Hostile(tmp_path / "d", port=_free_port(), log=lambda *a: None)
    assert _train(tmp_path / "d", [h])["loss"] == base["loss"]
    assert h.client.images == []


def test_viewer_overlays_and_the_path_editor(tmp_path):
    """A hash_sdf run with a coloured mesh: the viewer builds its grid, mesh and camera overlays;
    keyframes added from a client's camera are saved as a path file `render --path` reads."""
    from warpnerf.mesh import write_ply
    from warpnerf.viewer import Viewer, load_scene
    from warpnerf.viewer.server import _ClientState, opencv_to_gl

    run = tmp_path / "s"
    assert main(["train", "volsdf", "--data", "builtin", "--field", "hash_sdf", "--hash-levels",
                 "3", "--hash-log2-size", "8", "--hash-max-res", "16", "--grid-res", "8",
                 "--builtin-size", "16", "--batch", "64", "--val-images", "0", "--quiet",
                 "--iters", "2", "--out", str(run)]) == 0  # fmt: skip
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    write_ply(run / "mesh.ply", v, np.array([[0, 1, 2]]), colors=np.full((3, 3), 200, np.uint8))
    viewer = Viewer(load_scene(run), port=_free_port(), run=run, log=lambda *a: None)
    try:
        assert viewer.mesh is not None and viewer.grid_points is not None
        assert len(viewer.frustums) == len(viewer.scene.cameras)
        st = _ClientState(_FakeClient())
        viewer._clients[1] = st
        for a in (0.0, 0.5, 1.0):
            st.pose = (look_at((3 * math.cos(a), 3 * math.sin(a), 1), (0, 0, 0)).double().numpy(),
                       0.7, 1.5, 64)  # fmt: skip
            viewer._add_keyframe(st.client)
        viewer.path_frames.value = 7
        viewer._preview(st.client, fps=1e6)  # flies the camera through the 7 path frames
        assert len(st.client.poses) == 7
        wxyz, pos = st.client.poses[-1]
        assert np.allclose(opencv_to_gl(wxyz, pos), st.pose[0], atol=1e-5)  # ends on the last
        viewer.path_file.value = "p.json"
        viewer._save_path(st.client)
        assert "saved 3 keyframes" in viewer.path_info.content
        path = load_camera_path(run / "p.json")
        assert path.keyframes.shape == (3, 4, 4) and path.frames == 7
        assert math.isclose(path.fov_y, 0.7) and math.isclose(path.aspect, 1.5)
        (run / "mine.json").write_text("{}")  # a user's file is never replaced
        viewer.path_file.value = "mine.json"
        viewer._save_path(st.client)
        assert "not saved" in viewer.path_info.content
        assert (run / "mine.json").read_text() == "{}"
        # the browser names a file, never a folder: nothing is written outside the run folder
        for name in (str(tmp_path / "x.json"), "../x.json", "sub/x.json", "x.txt", ".."):
            viewer.path_file.value = name
            viewer._save_path(st.client)
            assert "plain file name" in viewer.path_info.content
        assert not (tmp_path / "x.json").exists()
    finally:
        viewer.close()


def test_reload_picks_up_a_newer_checkpoint(tmp_path):
    """`view` while another process trains: "Reload checkpoint" swaps in the latest weights, so
    the frames equal those of a viewer opened afresh on the newer checkpoint."""
    from warpnerf.viewer import Viewer, load_scene

    run = tmp_path / "r"
    assert main(["train", "nerf", *TINY, "--out", str(run)]) == 0
    scene = load_scene(run)
    eye = look_at((0.0, -4.0, 1.0), (0, 0, 0)).numpy()
    before = scene.render(eye, 20.0, 20.0, 16, 16)
    assert main(["train", "nerf", "--out", str(run), "--resume", "--iters", "30", "--quiet"]) == 0
    viewer = Viewer(scene, port=_free_port(), run=run, log=lambda *a: None)
    try:
        viewer._reload()
        assert "step 30" in viewer.status.content and viewer.weights_version == 1
    finally:
        viewer.close()
    after = scene.render(eye, 20.0, 20.0, 16, 16)
    assert np.array_equal(after, load_scene(run).render(eye, 20.0, 20.0, 16, 16))
    assert not np.array_equal(before, after)


def test_live_viewer_of_every_task(tmp_path, monkeypatch):
    """`--viewer` on `train box` and `train sdf` too: the live scene of the task renders."""
    import warpnerf.viewer
    from warpnerf.viewer import LiveViewer

    from ._scene import write_box_folder

    frames = []

    class OneFrame(LiveViewer):
        def on_start(self, task, step):
            super().on_start(task, step)
            eye = look_at((0.0, -4.0, 1.0), (0, 0, 0)).numpy()
            sc = self.viewer.scene
            frames.append(sc.render(eye, 10.0, 10.0, 8, 8, sc.modes[0]))

    monkeypatch.setattr(warpnerf.viewer, "LiveViewer", OneFrame)  # (what --viewer builds)
    write_box_folder(tmp_path / "scene", n_views=3, size=8, name="transforms_train.json")
    assert main(["train", "box", "--data", str(tmp_path / "scene"), "--out", str(tmp_path / "b"),
                 "--iters", "2", "--frames", "0", "--quiet", "--samples", "8", "--viewer",
                 "--viewer-port", str(_free_port())]) == 0  # fmt: skip
    pts = tmp_path / "p.npz"
    ang = np.random.default_rng(0).normal(size=(300, 3))
    np.savez(pts, points=(ang / np.linalg.norm(ang, axis=1, keepdims=True)).astype("f4"))
    assert main(["train", "sdf", "--points", str(pts), "--out", str(tmp_path / "s"), "--iters",
                 "2", "--batch", "64", "--resolution", "8", "--width", "16", "--layers", "2",
                 "--pos-freqs", "2", "--quiet", "--viewer",
                 "--viewer-port", str(_free_port())]) == 0  # fmt: skip
    assert len(frames) == 2 and all(f.shape == (8, 8, 3) for f in frames)


def test_review_fixes(tmp_path, nerf_run, capsys):
    """Half turns round-trip through the quaternions; a path never replaces a run's own file;
    an address the machine does not have is an error, not a hang; --max-resolution is bounded."""
    from warpnerf.viewer.server import gl_to_opencv, opencv_to_gl

    for r in (np.array([[0, 1, 0], [-1, 0, 0], [0, 0, 1.0]]), np.diag([1.0, -1.0, -1.0]),
              np.array([[0, -1, 0], [-1, 0, 0], [0, 0, -1.0]])):  # fmt: skip
        c2w = np.eye(4)
        c2w[:3, :3] = r
        assert np.allclose(opencv_to_gl(*gl_to_opencv(c2w)), c2w, atol=1e-12)
        assert np.allclose(interpolate_path(np.stack([np.eye(4), c2w]), 3)[-1].numpy(), c2w,
                           atol=1e-6)  # fmt: skip
    before = (nerf_run / "config.json").read_text()
    with pytest.raises(UserError, match="not a camera path"):
        CameraPath(_keys()).save(nerf_run / "config.json")
    assert (nerf_run / "config.json").read_text() == before
    CameraPath(_keys()).save(tmp_path / "p.json")
    CameraPath(_keys()[:2]).save(tmp_path / "p.json")  # a camera path: replaced
    assert load_camera_path(tmp_path / "p.json").keyframes.shape[0] == 2
    t0 = __import__("time").perf_counter()
    assert main(["view", str(nerf_run), "--host", "10.255.255.1", "--exit-after", "1"]) == 2
    assert "--host 10.255.255.1" in capsys.readouterr().err
    assert __import__("time").perf_counter() - t0 < 30
    with pytest.raises(SystemExit) as e:  # (argparse)
        main(["view", str(nerf_run), "--max-resolution", "9000"])
    assert e.value.code == 2
    big = {"warpnerf_camera_path": 1, "frames": 10**400, "keyframes": [{"c2w": np.eye(4).tolist()}]}
    (tmp_path / "big.json").write_text(json.dumps(big))
    with pytest.raises(UserError, match="frames"):
        load_camera_path(tmp_path / "big.json")


def test_thumbnails_of_eight_bit_and_float_images_agree():
    """The frustums' thumbnails of a training split kept as 8-bit (--images-on host) are the
    images themselves, as those of its float values are (they were all white)."""
    import torch

    from warpnerf.viewer.scene import _thumbnails

    u8 = torch.randint(
        0, 256, (2, 6, 8, 3), dtype=torch.uint8, generator=torch.Generator().manual_seed(0)
    )
    a, b = _thumbnails(u8), _thumbnails(u8.float() / 255.0)
    assert a.dtype == b.dtype == np.uint8 and a.shape == b.shape == (2, 6, 8, 3)
    assert np.array_equal(a, b) and np.array_equal(a, u8.numpy())
