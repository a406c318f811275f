"""The viewer as a network service: a token and the page's own origin are required for every
request, every value a browser sends is bounded on the server, a raising panel callback leaves
the server alive, a non-loopback ``--host`` is warned about, and "Save path" refuses a FIFO
(or link) at the typed name without hanging."""

from __future__ import annotations

import asyncio
import contextlib
import http.client
import math
import os
import re
import threading
import time

import numpy as np
import pytest

from tests.test_viewer import _FakeClient, _free_port, _slow_scene, _watching
from warpnerf.data.camera_path import MAX_FRAMES, CameraPath, load_camera_path
from warpnerf.data.cameras import look_at
from warpnerf.errors import UserError


@contextlib.contextmanager
def _viewer(**kw):
    """A viewer of a scene that renders grey fast, on a free loopback port; its log lines."""
    from warpnerf.viewer.server import Viewer

    logs: list = []
    v = Viewer(_slow_scene(1e-7), port=_free_port(), log=logs.append, **kw)
    try:
        yield v, logs
    finally:
        v.close()


def _handshake(port: int, path: str = "/", origin=None, cookie=None):
    """The HTTP status of a websocket handshake to the viewer (101: accepted)."""
    import viser
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    headers = {"Cookie": cookie} if cookie else None
    try:
        with connect(f"ws://127.0.0.1:{port}{path}", origin=origin, additional_headers=headers,
                     subprotocols=[f"viser-v{viser.__version__}"], open_timeout=10):  # fmt: skip
            return 101
    except InvalidStatus as e:
        return e.response.status_code


def _get(port: int, path: str, cookie=None):
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.request("GET", path, headers={"Cookie": cookie} if cookie else {})
        r = conn.getresponse()
        r.read()
        return r.status, r.getheader("Set-Cookie")
    finally:
        conn.close()


def test_websocket_needs_the_token_and_the_viewers_own_origin():
    with _viewer() as (v, _):
        port = v.port
        m = re.fullmatch(rf"http://localhost:{port}/\?token=([A-Za-z0-9_-]{{32,}})", v.url)
        assert m, v.url
        token = m.group(1)
        own, evil = f"http://127.0.0.1:{port}", "http://evil.example"
        cookie = f"warpnerf-viewer-{port}={token}"
        # the page: only with the token (which sets the cookie) or the cookie
        assert _get(port, "/")[0] == 403
        assert _get(port, "/?token=wrong")[0] == 403
        status, set_cookie = _get(port, f"/?token={token}")
        assert status == 200 and set_cookie.startswith(cookie)
        assert "HttpOnly" in set_cookie and "SameSite=Strict" in set_cookie
        assert _get(port, "/", cookie=cookie)[0] == 200
        assert _get(port, "/", cookie=f"warpnerf-viewer-{port + 1}={token}")[0] == 403
        # the websocket: refused without the token, and from another site's page even with it
        assert _handshake(port) == 403
        assert _handshake(port, origin=own) == 403
        assert _handshake(port, origin=own, cookie=f"warpnerf-viewer-{port}=x") == 403
        assert _handshake(port, origin=evil, cookie=cookie) == 403
        assert _handshake(port, f"/?token={token}", origin=evil) == 403
        assert _handshake(port, f"/?token={token}", origin="null") == 403
        assert _handshake(port, origin=f"http://127.0.0.1:{port + 1}", cookie=cookie) == 403
        # the page's own websocket (its cookie, its origin) and a script with the token
        assert _handshake(port, origin=own, cookie=cookie) == 101
        assert _handshake(port, f"/?token={token}") == 101
        assert v.gate.refused >= 10


def _browser_sends(viewer, handle, value) -> None:
    """What viser does with a browser's GUI update message (the value cast to the handle's
    type, no bounds), on viser's own event loop."""
    from viser import _messages

    loop = viewer.server._websock_server._background_event_loop
    msg = _messages.GuiUpdateMessage(handle._impl.uuid, {"value": value})
    asyncio.run_coroutine_threadsafe(viewer.server.gui._handle_gui_updates(0, msg), loop).result(10)


def test_a_browser_cannot_ask_for_more_pixels_than_max_resolution():
    with _viewer(max_resolution=128) as (v, _):
        _browser_sends(v, v.max_res, 10**9)
        assert v.max_res.value == 10**9  # (viser does not bound it)
        v.scene.ray_seconds = 1e-12  # (a fast scene: the full size fits any budget)
        for level in (0, 1, 5):
            w, h, _ = v._size(1.0, 10**6, level)
            assert max(w, h) <= 128, (level, w, h)
        w, h, final = v._size(1.0, 0, 1)  # no canvas size: max_resolution
        assert (w, h, final) == (128, 128, True)
        _browser_sends(v, v.max_res, -(10**9))
        assert max(v._size(1.0, 10**6, 1)[:2]) == 16  # (the smallest frame)


class _Camera:
    """A browser camera as viser exposes it (``aspect``: width / height, raising on 0)."""

    def __init__(self, wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, -4.0, 1.0), fov=0.8,
                 width=640, height=480):  # fmt: skip
        self.wxyz, self.position, self.fov = np.array(wxyz), np.array(position), fov
        self.image_width, self.image_height = width, height

    @property
    def aspect(self):
        return float(self.image_width) / self.image_height


def _client_with(camera):
    c = _FakeClient()
    object.__setattr__(c, "camera", camera)
    return c


def test_a_zero_or_negative_canvas_renders_a_small_frame_without_a_crash():
    from warpnerf.viewer.server import _ClientState

    with _viewer() as (v, logs):
        for w, h in ((0, 0), (0, 480), (-5, -5)):
            st = _ClientState(_client_with(_Camera(width=w, height=h)))
            v._camera(st)  # (viser's aspect raised ZeroDivisionError here)
            c2w, fov, aspect, canvas = st.pose
            assert aspect == 1.0 and canvas == 0 and np.isfinite(c2w).all()
            v.scene.ray_seconds = None
            assert v._render_job((st, st.version, 0, 0))
            img = st.client.images[-1]
            assert 8 <= min(img.shape[:2]) and max(img.shape[:2]) <= v.max_resolution
        assert not any("failed" in line for line in logs), logs


def test_non_finite_cameras_are_refused_and_the_field_of_view_is_bounded():
    from warpnerf.viewer.server import _ClientState

    with _viewer() as (v, logs):
        st = _ClientState(_client_with(_Camera()))
        v._camera(st)
        good = st.pose
        for bad in (dict(wxyz=(math.nan, 0, 0, 0)), dict(position=(0, math.inf, 0)),
                    dict(fov=math.nan), dict(fov=math.inf), dict(wxyz=(0, 0, 0, 0)),
                    dict(position=(1e300, 0, 0))):  # fmt: skip
            st.client.camera = _Camera(**bad)
            v._camera(st)
            assert st.pose is good, bad  # not taken: no frame of it is rendered
            assert v.status.content.startswith("camera refused"), v.status.content
        assert sum("camera refused" in line for line in logs) == 6
        for fov in (0.0, -1.0, 10.0, math.pi):
            st.client.camera = _Camera(fov=fov)
            v._camera(st)
            assert 0 < st.pose[1] < math.pi
        st.client.camera = _Camera(width=10**9, height=1)
        v._camera(st)
        assert st.pose[2] == 100.0


def test_a_billion_path_frames_are_refused_and_preview_is_lazy(tmp_path):
    with _viewer(run=tmp_path) as (v, _):
        st = _watching(v)
        for x in (0.0, 1.0):
            st.pose = (look_at((x, -4.0, 1.0), (0, 0, 0)).double().numpy(), 0.8, 1.0, 64)
            v._add_keyframe(st.client)
        _browser_sends(v, v.path_frames, 10**9)
        assert v.path_frames.value == 10**9  # (viser does not bound it)
        v._save_path(st.client)
        assert "not saved" in v.path_info.content and "Frames" in v.path_info.content
        assert not (tmp_path / "camera_path.json").exists()
        # preview of the largest path: cameras computed as flown, a newer click ends it
        _browser_sends(v, v.path_frames, MAX_FRAMES)
        t0 = time.perf_counter()
        v._start_preview(st.client)
        deadline = time.perf_counter() + 10
        while not st.client.poses and time.perf_counter() < deadline:
            time.sleep(0.01)
        assert st.client.poses, "the preview did not start"
        first = time.perf_counter() - t0
        assert first < 1.0, f"the first preview frame took {first:.2f} s"  # (no 10^5 up front)
        v._previews[st.client.client_id] += 1  # (a newer click)
        time.sleep(0.3)
        n = len(st.client.poses)
        time.sleep(0.3)
        assert len(st.client.poses) == n < 100  # stopped, after a few frames at 20 per second
        _browser_sends(v, v.path_frames, 7)
        v._save_path(st.client)
        assert load_camera_path(tmp_path / "camera_path.json").frames == 7


def test_a_nan_keyframe_is_never_saved(tmp_path):
    from warpnerf.viewer.server import _ClientState

    bad = np.eye(4)
    bad[0, 3] = math.nan
    for keys in ([bad], [np.eye(4), bad]):
        with pytest.raises(UserError, match="finite"):
            CameraPath(keys).save(tmp_path / "p.json")
    with pytest.raises(UserError, match="fov_y"):
        CameraPath([np.eye(4)], fov_y=math.nan).save(tmp_path / "p.json")
    assert not (tmp_path / "p.json").exists()
    with _viewer(run=tmp_path) as (v, _):  # a NaN pose that got into the path anyway
        st = _ClientState(_FakeClient())
        v._clients[1] = st
        st.pose = (bad, 0.8, 1.0, 64)
        v._path = [st.pose]
        v._save_path(st.client)
        assert "not saved" in v.path_info.content
    assert not (tmp_path / "camera_path.json").exists()


def test_a_raising_panel_callback_leaves_the_server_alive():
    from viser import GuiEvent

    with _viewer() as (v, logs):

        def boom(_keys):
            raise RuntimeError("boom")

        v._set_path = boom
        clear = next(h for h in v.server.gui._gui_input_handle_from_uuid.values()
                     if getattr(h, "label", "") == "Clear")  # fmt: skip
        for cb in clear._impl.update_cb:  # what viser runs for a click
            cb(GuiEvent(_FakeClient(), 0, clear))
        assert v.status.content == "clear failed: RuntimeError: boom"
        assert logs == ["viewer: clear failed: RuntimeError: boom"]
        token = v.url.split("token=")[1]
        assert _handshake(v.port, f"/?token={token}") == 101  # still serving


def test_a_host_other_than_loopback_is_warned_about():
    from warpnerf.viewer.access import exposure

    with _viewer() as (_, logs):
        assert not any("warning" in line for line in logs)
    with _viewer(host="0.0.0.0") as (v, logs):
        warned = [line for line in logs if "warning" in line]
        assert len(warned) == 1, logs
        for words in ("--host 0.0.0.0", "every network interface", str(v.port), "token",
                      "save camera-path files", "training images"):  # fmt: skip
            assert words in warned[0], (words, warned[0])
    assert exposure("127.0.0.1", 7007) is None and exposure("localhost", 7007) is None
    assert "interface with address 10.1.2.3" in exposure("10.1.2.3", 7007)


def _saves_within(fn, seconds: float = 10.0):
    """Runs ``fn`` in a thread; fails (and releases it) if it blocks longer than ``seconds``."""
    out: list = []

    def run():
        try:
            fn()
            out.append(None)
        except Exception as e:  # noqa: BLE001
            out.append(e)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(seconds)
    return t.is_alive(), out


def test_saving_a_path_onto_a_fifo_or_link_is_refused_without_hanging(tmp_path):
    fifo = tmp_path / "camera_path.json"
    os.mkfifo(fifo)
    hung, out = _saves_within(lambda: CameraPath([np.eye(4)]).save(fifo))
    if hung:  # release the blocked open (a writer arrives), then fail
        with contextlib.suppress(OSError):
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        pytest.fail("saving onto a FIFO hung")
    assert isinstance(out[0], UserError) and str(fifo) in str(out[0]), out
    (tmp_path / "target.json").write_text("{}")
    os.symlink(tmp_path / "target.json", tmp_path / "link.json")
    with pytest.raises(UserError, match="link.json"):
        CameraPath([np.eye(4)]).save(tmp_path / "link.json")
    assert (tmp_path / "target.json").read_text() == "{}"
    with _viewer(run=tmp_path) as (v, _):  # the panel's Save onto the FIFO: a message
        st = _watching(v)
        v._add_keyframe(st.client)
        hung, out = _saves_within(lambda: v._save_path(st.client))
        if hung:
            with contextlib.suppress(OSError):
                os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
            pytest.fail("the viewer's Save onto a FIFO hung")
        assert out == [None] and v.path_info.content.startswith("not saved"), out
    assert fifo.is_fifo()
