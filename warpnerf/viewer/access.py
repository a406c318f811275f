"""Who may use the viewer, and what a browser may ask of it.

The viewer is a network service: its websocket renders the run from any camera, saves
camera-path files into the run folder and sends the training images. A web page from another
site open in the same browser can open a websocket to ``localhost`` too, so the server checks
every request (:class:`Gate`), as Jupyter does:

- :attr:`Gate.token` (``secrets.token_urlsafe``, 32 bytes) is in the URL the viewer prints
  (``http://localhost:PORT/?token=...``). The page is served only to a request carrying it
  (query ``token=``) or its cookie; serving the tokened page sets the cookie
  (``warpnerf-viewer-PORT``, ``HttpOnly``, ``SameSite=Strict``), which the page's own websocket
  request then carries (viser's page connects to its own address without the query string).
- A websocket handshake is refused (HTTP 403) without the token (cookie or ``?token=``), and
  with an ``Origin`` header other than the viewer's own address (the request's ``Host``):
  browsers always send ``Origin`` on a websocket request, so a foreign page is refused even if
  it guessed the token; a client that is not a browser (no ``Origin``) needs the token.

Every value a browser sends is checked on the server (:func:`client_pose`, :func:`bounded`):
non-finite camera parameters are refused (the frame is not rendered; the panel says why), the
field of view is clamped into (0, pi), the aspect into [1/100, 100], the canvas to at least
one pixel. :func:`exposure` is the warning printed when the viewer listens on an address other
than loopback.
"""

from __future__ import annotations

import contextlib
import hmac
import http
import http.cookies
import ipaddress
import math
import secrets
import socket
import threading
from urllib.parse import parse_qs, urlsplit

import numpy as np

from ..errors import UserError

__all__ = ["Gate", "client_pose", "bounded", "exposure", "is_loopback", "check_address"]

MIN_FOV, MAX_FOV = 1e-3, math.pi - 1e-3  # radians: the field of view a frame may have
MIN_ASPECT, MAX_ASPECT = 1e-2, 1e2
MAX_COORD = 1e9  # |position| of a browser's camera
_SERVE_LOCK = threading.Lock()
_REFUSED_PAGE = (
    "<!doctype html><title>warpnerf viewer</title><p>This viewer needs its token: open the "
    "address it printed (<code>http://HOST:PORT/?token=...</code>).</p>"
)


class Gate:
    """The access check of one viewer: its token, and :meth:`check` for every HTTP request and
    websocket handshake (installed on viser's websockets server by :meth:`installed`)."""

    def __init__(self, token: str | None = None):
        self.token = token or secrets.token_urlsafe(32)
        self.hooked = False  # the check is installed on the server's handshakes
        self.refused = 0  # requests refused so far

    def _is_token(self, value) -> bool:
        return isinstance(value, str) and hmac.compare_digest(
            value.encode("utf-8", "replace"), self.token.encode()
        )

    @staticmethod
    def cookie_name(port: int) -> str:
        """The cookie holding the token for the viewer on ``port`` (cookies are shared by all
        the ports of a host: one name a port)."""
        return f"warpnerf-viewer-{int(port)}"

    def check(self, connection, request, inner=None):
        """The websockets ``process_request`` hook: a 403 response for a refused request, else
        ``inner`` (viser's file server) with the token cookie added to a tokened page."""
        headers = request.headers
        port = connection.local_address[1]
        query = parse_qs(urlsplit(request.path).query)
        by_query = any(self._is_token(t) for t in query.get("token", []))
        by_cookie = any(self._is_token(c) for c in _cookies(headers, self.cookie_name(port)))
        if headers.get("Upgrade", "").lower() == "websocket":
            origin = headers.get("Origin")
            if origin is not None and not _same_origin(origin, headers.get("Host")):
                return self._refuse(connection, f"websocket from a foreign origin ({origin[:80]})")
            if not (by_query or by_cookie):
                return self._refuse(connection, "websocket without the viewer's token")
            return None  # (viser's own hook lets handshakes through)
        if not (by_query or by_cookie):
            return self._refuse(connection, "page requested without the viewer's token", True)
        resp = inner(connection, request) if inner is not None else None
        if resp is not None and by_query:
            resp.headers["Set-Cookie"] = (
                f"{self.cookie_name(port)}={self.token}; Path=/; HttpOnly; SameSite=Strict"
            )
        return resp

    def _refuse(self, connection, why: str, page: bool = False):
        self.refused += 1
        resp = connection.respond(http.HTTPStatus.FORBIDDEN, _REFUSED_PAGE if page else why)
        if page:
            resp.headers["Content-Type"] = "text/html; charset=utf-8"
        return resp

    @contextlib.contextmanager
    def installed(self):
        """While inside, a websockets server started (viser's, in its own thread, before
        ``ViserServer()`` returns) checks every request with :meth:`check` before viser's own
        hook. The patch is module-wide for that moment, under a lock; :attr:`hooked` tells
        whether it took (the caller refuses to serve otherwise)."""
        import websockets.asyncio.server as wss

        original, gate = wss.serve, self

        class serve(original):  # noqa: N801 (the name websockets uses)
            def __init__(self, handler, *args, process_request=None, **kw):
                def hook(connection, request):
                    return gate.check(connection, request, process_request)

                gate.hooked = True
                super().__init__(handler, *args, process_request=hook, **kw)

        with _SERVE_LOCK:
            wss.serve = serve
            try:
                yield self
            finally:
                wss.serve = original


def _cookies(headers, name: str) -> list:
    """The values of cookie ``name`` in the request's Cookie headers (malformed ones ignored)."""
    out = []
    for line in headers.get_all("Cookie"):
        jar = http.cookies.SimpleCookie()
        with contextlib.suppress(http.cookies.CookieError):
            jar.load(line)
        if name in jar:
            out.append(jar[name].value)
    return out


def _same_origin(origin: str, host: str | None) -> bool:
    """Whether a request's ``Origin`` is the page served at ``host`` (the Host header)."""
    if not host:
        return False
    try:
        o = urlsplit(origin)
    except ValueError:
        return False
    return o.scheme in ("http", "https") and o.netloc.lower() == host.strip().lower()


def is_loopback(host: str) -> bool:
    """Whether every address ``host`` names is a loopback address (127.0.0.0/8, ::1)."""
    try:
        infos = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError):
        return False
    addrs = {info[4][0].split("%")[0] for info in infos}
    return bool(addrs) and all(ipaddress.ip_address(a).is_loopback for a in addrs)


def check_address(host: str) -> None:
    """UserError unless ``host`` is an address this machine can listen on (viser would try 1000
    ports on it and then wait forever)."""
    try:
        infos = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as e:
        raise UserError(f"--host {host}: not an address of this machine ({e})") from None
    for family, kind, proto, _, addr in infos:
        try:
            with socket.socket(family, kind, proto) as s:
                s.bind(addr)
                return
        except OSError as e:
            err = e
    raise UserError(f"--host {host}: cannot listen there ({err.strerror or err})")


def exposure(host: str, port: int) -> str | None:
    """The warning for a viewer listening on ``host`` (None for loopback): which interfaces, and
    what anyone reaching the port with the token can do."""
    if is_loopback(host):
        return None
    where = (
        "every network interface of this machine"
        if host in ("0.0.0.0", "::", "")
        else f"the interface with address {host}"
    )
    return (
        f"viewer: warning: --host {host} listens on {where} (port {port}): anyone who can reach "
        "that port and has the printed URL (its token) can drive the viewer, save camera-path "
        "files into the run folder and see the run's renders and training images; the "
        "connection is not encrypted. For a remote machine prefer the default 127.0.0.1 and an "
        f"SSH tunnel (ssh -L {port}:localhost:{port} HOST)."
    )


def bounded(value, lo: int, hi: int, what: str) -> int:
    """``value`` (a number a browser sent) as an integer in ``lo..hi``; ValueError naming
    ``what`` when it is not a finite integral number in that range."""
    try:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        ok = ok and math.isfinite(value) and value == int(value) and lo <= value <= hi
    except (OverflowError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"{what} must be an integer in {lo}..{hi}, got {value!r}")
    return int(value)


def client_pose(camera) -> tuple:
    """(wxyz [4], position [3], fov_y, aspect, canvas width) of a browser's camera, checked:
    ValueError for a non-finite or degenerate rotation, position or field of view; the field of
    view clamped into (0, pi), the aspect into [1/100, 100], the canvas at least 1 pixel (0 when
    the browser sent none)."""

    def vector(name, n):
        try:
            v = np.asarray(getattr(camera, name), dtype=np.float64).reshape(n)
        except (TypeError, ValueError, OverflowError):
            raise ValueError(f"camera {name} must be {n} numbers") from None
        if not np.isfinite(v).all() or np.abs(v).max() > MAX_COORD:
            raise ValueError(f"camera {name} must be finite numbers, got {v.tolist()}")
        return v

    wxyz, position = vector("wxyz", 4), vector("position", 3)
    if np.linalg.norm(wxyz) < 1e-6:
        raise ValueError("camera rotation is a zero quaternion")
    try:
        fov = float(camera.fov)
    except (TypeError, ValueError, OverflowError):
        fov = math.nan
    if not math.isfinite(fov):
        raise ValueError(f"camera fov must be a finite angle, got {getattr(camera, 'fov', None)}")
    fov = min(max(fov, MIN_FOV), MAX_FOV)
    w, h = _pixels(getattr(camera, "image_width", 0)), _pixels(getattr(camera, "image_height", 0))
    aspect = w / h if w > 0 and h > 0 else 1.0
    return wxyz, position, fov, min(max(aspect, MIN_ASPECT), MAX_ASPECT), w


def _pixels(value) -> int:
    """A canvas size a browser sent, as a count of pixels in 0..65536 (0: none or nonsense)."""
    try:
        v = float(value or 0)
    except (TypeError, ValueError, OverflowError):
        return 0
    return int(min(v, 65536)) if math.isfinite(v) and v >= 1 else 0
