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
    from warpnerf.outputs import to_uint8
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
    from warpnerf.outputs import to_uint8
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
    from warpnerf.outputs import load_checkpoint

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
    with pytest.raises(UserError, match="not a kind of run warpnerf knows"):
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


def watching_viewer():
    """A LiveViewer with one fake browser client watching from a fixed pose, a frame rendered
    after every training step (shared with tests/test_ema.py)."""
    from warpnerf.viewer import LiveViewer
    from warpnerf.viewer.server import _ClientState

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

    return Watching


def test_live_viewer_leaves_training_unchanged(tmp_path):
    """Training with the live viewer (no browser, then a watching client whose frames render
    between steps) gives the same losses as training without it."""
    from warpnerf.viewer import LiveViewer

    base = _train(tmp_path / "a")
    live = LiveViewer(tmp_path / "b", port=_free_port(), log=lambda *a: None)
    assert _train(tmp_path / "b", [live])["loss"] == base["loss"]
    assert live.viewer is None  # closed with the loop

    Watching = watching_viewer()

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
                 "--no-viewer-wait", "--viewer-port", str(_free_port())]) == 0  # fmt: skip
    pts = tmp_path / "p.npz"
    ang = np.random.default_rng(0).normal(size=(300, 3))
    np.savez(pts, points=(ang / np.linalg.norm(ang, axis=1, keepdims=True)).astype("f4"))
    assert main(["train", "sdf", "--points", str(pts), "--out", str(tmp_path / "s"), "--iters",
                 "2", "--batch", "64", "--resolution", "8", "--width", "16", "--layers", "2",
                 "--pos-freqs", "2", "--quiet", "--viewer", "--no-viewer-wait",
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


# ------------------------------------------------- stopping, abandoned frames, still frames


def _slow_scene(seconds_per_ray: float, log: list | None = None):
    """A scene that takes ``seconds_per_ray`` a ray (sleeping, as a native kernel would,
    without the GIL); ``log`` gets (start, end) of every block rendered."""
    import time

    import torch

    from warpnerf.viewer.scene import RunScene

    def render_rays(o, d, mode):
        t0 = time.perf_counter()
        time.sleep(seconds_per_ray * len(o))
        if log is not None:
            log.append((t0, time.perf_counter()))
        return torch.full((len(o), 3), 0.5)

    return RunScene(render_rays, ("rgb",), [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0])


def _watching(viewer, canvas: int = 800, still: bool = True):
    """A fake browser looking at the scene from (0, -4, 1); its camera still since long ago."""
    from warpnerf.viewer.server import _ClientState

    st = _ClientState(_FakeClient())
    st.pose = (look_at((0.0, -4.0, 1.0), (0, 0, 0)).double().numpy(), 0.8, 1.0, canvas)
    st.moved_at = 0.0 if still else 1e18
    with viewer._lock:
        viewer._clients[1] = st
    return st


def _wait_for(cond, seconds: float) -> bool:
    import time

    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        if cond():
            return True
        time.sleep(0.02)
    return cond()


def test_close_stops_a_slow_frame_within_two_seconds_and_frees_the_port():
    """A frame that would take minutes (2 ms a ray, the full 800x800 frame 20 min; its first
    blocks one of 16k rays, i.e. 33 s, before) is in flight: close() returns within ~2 s, the
    render thread is gone and the port is free."""
    import time

    from warpnerf.viewer import Viewer

    blocks: list = []
    port = _free_port()
    v = Viewer(_slow_scene(2e-3, blocks), port=port, log=lambda *a: None, still_seconds=30.0)
    try:
        _watching(v)
        assert _wait_for(lambda: len(blocks) >= 3, 20), "the frame did not start"
        assert max(e - s for s, e in blocks) < 0.6  # blocks sized from the measured speed
    finally:
        t0 = time.perf_counter()
        v.close()
        took = time.perf_counter() - t0
    assert took < 2.5, f"close() took {took:.2f} s"
    assert not v.rendering()
    with socket.socket() as s:
        s.bind(("127.0.0.1", port))


def test_abandoned_frames_stop_at_the_next_block():
    """The browser disconnects, or its camera moves, while a long frame renders: the frame stops
    at its next block (nothing more is rendered for the departed browser, nothing sent)."""
    import time

    from warpnerf.viewer import Viewer

    blocks: list = []
    v = Viewer(_slow_scene(2e-3, blocks), port=_free_port(), log=lambda *a: None,
               still_seconds=60.0)  # fmt: skip
    try:
        st = _watching(v)
        assert _wait_for(lambda: len(st.client.images) >= 1 and len(blocks) >= 2 + 1, 30)
        sent = len(st.client.images)  # the 32-pixel first frame; now a 60 s still frame
        t_move = time.perf_counter()
        with v._lock:  # the camera moves: the 60 s frame is dropped, a coarse one follows
            st.version += 1
            st.moved_at = time.perf_counter()
        assert _wait_for(lambda: len(st.client.images) > sent, 5), "no frame for the new view"
        assert time.perf_counter() - t_move < 2.0
        _wait_for(lambda: len(blocks) > 0 and blocks[-1][0] > t_move + 0.5, 5)  # refining
        t_gone = time.perf_counter()
        v._disconnect(st.client)
        time.sleep(1.0)
        n = len(blocks)
        assert blocks[-1][1] < t_gone + 0.6, "the departed browser's frame went on rendering"
        time.sleep(0.3)
        assert len(blocks) == n and v.watched() is False
    finally:
        v.close()


def test_a_still_frame_arrives_in_bounded_time_on_a_slow_scene():
    """1 ms a ray: the full 800x800 frame would take 11 minutes. The still camera gets a first
    frame that measures the speed, then still frames sized to take about still_seconds, each
    next one 4 times longer up to refine_seconds, then no more."""
    from warpnerf.viewer import Viewer

    v = Viewer(_slow_scene(1e-3), port=_free_port(), log=lambda *a: None, still_seconds=0.4,
               refine_seconds=1.6)  # fmt: skip
    try:
        st = _watching(v)
        assert _wait_for(lambda: len(st.client.images) >= 2, 4.0), "no still frame in 4 s"
        assert _wait_for(lambda: st.shown[3], 8.0), "the refinement did not finish"
        n = len(st.client.images)
        sizes = [im.shape[0] * im.shape[1] for im in st.client.images]
        assert sizes == sorted(sizes) and sizes[0] < sizes[-1] < 800 * 800
        assert 0.4 * 1.6 / 1e-3 <= sizes[-1] <= 1.6 * 1.6 / 1e-3  # ~1.6 s of rays, measured
        assert not _wait_for(lambda: len(st.client.images) > n, 1.0)  # final: nothing more
    finally:
        v.close()


_STOP_SCRIPT = """
import sys, time, torch
import warpnerf.viewer as wv
from warpnerf.cli.parser import main
from warpnerf.viewer.scene import RunScene
from warpnerf.viewer.server import Viewer
from tests.test_viewer import _slow_scene, _watching

class Watched(Viewer):  # a browser watching a 2 ms-a-ray scene: a frame always in flight
    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        _watching(self)

wv.load_scene = lambda *a, **k: _slow_scene(2e-3)
wv.Viewer = Watched
sys.exit(main(["view", ".", "--port", sys.argv[1], "--exit-after", "120"]))
"""


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_view_stops_within_two_seconds_of_a_signal(sig):
    """`warpnerf view` with a frame rendering on the CPU: Ctrl-C (SIGINT) or SIGTERM ends it
    within the bound (exit 0, "stopped after N frames", port free)."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-c", _STOP_SCRIPT, str(port)], cwd=root,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)  # fmt: skip
    try:
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if "Ctrl-C stops" in line:
                break
        assert proc.poll() is None, "".join(lines)
        time.sleep(1.5)  # the first frame done, a still frame of ~2 s in flight
        t0 = time.perf_counter()
        proc.send_signal(getattr(signal, sig))
        out, _ = proc.communicate(timeout=30)
        took = time.perf_counter() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
    out = "".join(lines) + out
    assert proc.returncode == 0, out
    assert "stopped after" in out and "Traceback" not in out, out
    assert took < 5.0, f"exited {took:.2f} s after {sig}"
    with socket.socket() as s:
        s.bind(("127.0.0.1", port))


def test_a_frame_for_a_closed_connection_is_quiet_and_other_warnings_stay():
    """viser warns when a message is queued on a closed connection; the viewer drops that
    warning for its frames only (a browser gone mid-frame is not an error)."""
    import asyncio
    import warnings

    from viser import _messages
    from viser.infra._async_message_buffer import AsyncMessageBuffer

    from warpnerf.viewer.server import _quiet_viser

    _quiet_viser()
    loop = asyncio.new_event_loop()
    try:
        for msg, warns in (
            (_messages.BackgroundImageMessage(format="jpeg", rgb_data=b"", depth_data=None), 0),
            (_messages.GuiUpdateMessage("x", {"value": 1}), 1),
        ):
            buf = AsyncMessageBuffer(loop, persistent_messages=False)
            buf.set_done()  # the connection closed
            with warnings.catch_warnings(record=True) as got:
                warnings.simplefilter("default")
                _quiet_viser()  # (catch_warnings reset the filters)
                buf.push(msg)
            assert len([w for w in got if "closed connection" in str(w.message)]) == warns
    finally:
        loop.close()


# ------------------------------------------------------- camera paths keep the viewer's range


def _ball_run(nerf_run, tmp_path):
    """A copy of the built-in MLP run whose field is an opaque red octahedron of radius 0.45 at
    the origin and empty elsewhere (a ReLU trunk computing |x|_1): from 4.5 units out, all of it
    lies beyond the run's far (4)."""
    import shutil

    import torch

    from warpnerf.outputs import load_checkpoint, save_checkpoint

    run = tmp_path / "ball"
    shutil.copytree(nerf_run, run)
    ck = load_checkpoint(run / "checkpoint.pt")
    f = ck["fields"]["coarse"]
    for k in f:
        f[k].zero_()
    for i in range(3):  # trunk 0: relu(+x_i), relu(-x_i); trunk 1 passes them on
        f["trunk.0.weight"][2 * i, i], f["trunk.0.weight"][2 * i + 1, i] = 1.0, -1.0
    f["trunk.1.weight"][:6, :6] = torch.eye(6)
    f["sigma_head.weight"][0, :6] = -50.0  # softplus(1 + 50 * 0.45 - 50 |x|_1 - 1)
    f["sigma_head.bias"].fill_(1.0 + 50.0 * 0.45)
    f["color_out.bias"].copy_(torch.tensor([10.0, -10.0, -10.0]))
    save_checkpoint(run / "checkpoint.pt", ck)
    return run


class _Browser(_FakeClient):
    """A fake client that also takes the viewer's starting camera (fov, position, look_at)."""

    def on_update(self, cb):
        pass

    def pose(self):
        c2w = look_at(tuple(self.position), tuple(self.look_at), tuple(self.up_direction))
        return c2w.double().numpy()


def _red(img) -> int:
    return int(((img[..., 0] > 150) & (img[..., 1] < 100) & (img[..., 2] < 100)).sum())


def test_a_path_saved_in_the_viewer_renders_what_the_viewer_showed(nerf_run, tmp_path, capsys):
    """3 keyframes from `view`'s starting camera (4.5 units out: beyond the run's far of 4 for
    most of the object) saved, then `render --path`: the frames show the object as the viewer
    did (its near/far saved per keyframe), also for a file saved without near/far."""
    import imageio.v3 as iio

    from warpnerf.viewer import Viewer, load_scene

    run = _ball_run(nerf_run, tmp_path)
    scene = load_scene(run)
    viewer = Viewer(scene, port=_free_port(), run=run, log=lambda *a: None)
    try:
        b = _Browser()
        viewer._connect(b)
        st = viewer._clients[b.client_id]
        c2w = b.pose()
        target = np.asarray(b.look_at)
        assert abs(np.linalg.norm(c2w[:3, 3] - target) - 4.5) < 0.05
        for a in (0.0, 0.3, 0.6):  # orbit the target at the starting distance
            r = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0],
                          [0, 0, 1.0]])  # fmt: skip
            k = c2w.copy()
            k[:3, :3], k[:3, 3] = r @ c2w[:3, :3], r @ (c2w[:3, 3] - target) + target
            st.pose = (k, float(b.fov), 4 / 3, 64)
            viewer._add_keyframe(b)
        viewer.path_frames.value = 3
        viewer.path_file.value = "camera_path.json"
        viewer._save_path(b)
    finally:
        viewer.close()
    path = load_camera_path(run / "camera_path.json")
    assert path.windows is not None and np.allclose(path.windows[0], [3.0, 6.0], atol=0.05)
    w, h = 64, 48
    fy = 0.5 * h / math.tan(0.5 * path.fov_y)
    shown = scene.render(path.keyframes[0], fy, fy, w, h)
    assert _red(shown) >= 20  # the viewer shows the object
    d = json.loads((run / "camera_path.json").read_text())
    for k in d["keyframes"]:
        k.pop("near"), k.pop("far")
    (run / "old_path.json").write_text(json.dumps(d))  # a file from before near/far were saved
    for name in ("camera_path", "old_path"):
        assert main(["render", str(run), "--path", str(run / f"{name}.json"), "--size",
                     f"{w}x{h}"]) == 0  # fmt: skip
        capsys.readouterr()
        frame = iio.imread(run / f"render_{name}" / "rgb_000.png")[..., :3]
        assert _red(frame) >= 0.8 * _red(shown), name  # the object, not the white background
        assert np.abs(frame.astype(int) - shown.astype(int)).mean() < 4, name


def test_mlp_runs_get_a_box_and_camera_frustums_from_their_cameras(nerf_run):
    """An MLP run has no scene box (aabb 0): the viewer derives one from the training cameras
    (around their target, what they all see between near and far) and sizes the frustums by it."""
    from warpnerf.train.nerf import load_run
    from warpnerf.viewer import Viewer, load_scene

    cfg, _, _ = load_run(nerf_run)
    assert cfg.aabb == 0 and cfg.aabb_box() is None
    scene = load_scene(nerf_run)
    # built-in cameras: 2.5 units from the origin, near 1, far 4 -> half side min(1.5, 1.5)
    assert np.allclose(scene.box, [-1.5, -1.5, -1.5, 1.5, 1.5, 1.5], atol=1e-3)
    assert math.isclose(scene.frustum_scale, 0.035 * 3.0, rel_tol=1e-3)
    v = Viewer(scene, port=_free_port(), log=lambda *a: None)
    try:
        assert len(v.frustums) == len(scene.cameras)
        assert all(f.scale > 0 for f in v.frustums)
    finally:
        v.close()


def test_a_live_frame_stops_at_a_signal_and_the_training_still_gets_it():
    """`train --viewer`: a frame renders in the training thread; Ctrl-C stops it at its next
    block and the training's own handler (finish the step, checkpoint) still gets the signal."""
    import os
    import signal
    import threading
    import time

    from warpnerf.train.loop import stop_requests
    from warpnerf.viewer import Viewer

    v = Viewer(_slow_scene(2e-3), port=_free_port(), live=True, log=lambda *a: None,
               still_seconds=30.0)  # fmt: skip
    try:
        st = _watching(v)
        v.scene.ray_seconds = 2e-3  # (measured before): this still frame would take 30 s
        with stop_requests() as stop:
            threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGINT)).start()
            t0 = time.perf_counter()
            v.tick()
            took = time.perf_counter() - t0
        assert stop["signum"] == signal.SIGINT and st.client.images == []
        assert took < 1.5, f"the live frame went on for {took:.1f} s after Ctrl-C"
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # all restored
    finally:
        v.close()
