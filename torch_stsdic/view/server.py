"""The local web server of ``stsdic view``: the page's own files and the result's data, on
127.0.0.1 only.

Safety: the server binds the loopback address (never another one), answers only the fixed
routes below - the page's assets are looked up by exact name in :data:`ASSETS`, read from
the package, never from a path in the request, so ``../``, absolute and encoded paths get
404 - and refuses requests whose ``Host`` is not itself (403: another site's page cannot
read it through a DNS name pointing at 127.0.0.1) and cross-origin POSTs. The only file it
writes is the mask path given on the command line (``stsdic view FRAMES --mask-out``).

Routes: ``/`` the page; ``/assets/NAME``; ``/api/meta``, ``/api/progress``,
``/api/colormaps``, ``/api/field?name=&row=&min_zncc=`` (float32 values, little-endian),
``/api/positions?row=`` (float32 x, y pairs), ``/api/limits?name=[&row=]``,
``/api/point?row=&point=``, ``/api/history?point=&name=``, ``/api/stats?row=``,
``/api/shape?row=`` (stereo: float32 X, Y, Z triples), ``/api/image?frame=`` (PNG);
drawing mode: ``/api/meta``, ``/api/image?frame=``, POST ``/api/region``.
"""

from __future__ import annotations

import json
import math
import sys
import threading
from collections.abc import Callable
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any
from urllib.parse import parse_qs, urlsplit

import numpy as np

__all__ = ["ASSETS", "HOST", "ViewServer", "make_server"]

#: the only address served
HOST = "127.0.0.1"
#: the page's files (in torch_stsdic/view/assets) and their content types
ASSETS = {
    "index.html": "text/html; charset=utf-8",
    "view.css": "text/css; charset=utf-8",
    "view.js": "text/javascript; charset=utf-8",
    "draw.js": "text/javascript; charset=utf-8",
    "common.js": "text/javascript; charset=utf-8",
}
#: the largest request body read (a drawn region as JSON)
MAX_BODY = 4 << 20
_SECURITY_HEADERS = {
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Content-Security-Policy": "default-src 'self'; img-src 'self' blob: data:; "
                               "style-src 'self'; script-src 'self'; object-src 'none'; "
                               "base-uri 'none'; frame-ancestors 'none'",
}


class BadRequest(ValueError):
    """A request the server refuses with 400 and this message."""


def _asset(name: str) -> bytes:
    return resources.files("torch_stsdic.view").joinpath("assets", name).read_bytes()


class _Handler(BaseHTTPRequestHandler):
    server: ViewServer
    protocol_version = "HTTP/1.1"
    server_version = "stsdic-view"
    sys_version = ""

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - quiet
        if self.server.verbose:
            sys.stderr.write("stsdic view: " + (format % args) + "\n")

    # -- checks -------------------------------------------------------------------------
    def _host_ok(self) -> bool:
        host = (self.headers.get("Host") or "").strip().lower()
        port = self.server.server_address[1]
        return host in (f"127.0.0.1:{port}", f"localhost:{port}")

    def _route(self) -> tuple[str, dict[str, str]] | None:
        """(path, query) of a request whose target is a plain absolute path, else None."""
        target = self.path
        if not target.startswith("/") or target.startswith("//"):
            return None
        parts = urlsplit(target)
        query = {k: v[-1] for k, v in parse_qs(parts.query, keep_blank_values=True).items()}
        return parts.path, query

    # -- answers --------------------------------------------------------------------------
    def _send(self, status: int, body: bytes, ctype: str, cache: bool = False) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "max-age=60" if cache else "no-store")
        for k, v in _SECURITY_HEADERS.items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, data: Any, status: int = 200) -> None:
        self._send(status, json.dumps(data, allow_nan=False).encode(), "application/json")

    def _error(self, status: int, message: str) -> None:
        self._json({"error": message}, status)

    def do_HEAD(self) -> None:  # noqa: N802
        self.do_GET()

    def do_GET(self) -> None:  # noqa: N802
        if not self._host_ok():
            return self._error(HTTPStatus.FORBIDDEN, "wrong Host: the viewer answers only "
                               "requests to itself")
        route = self._route()
        if route is None:
            return self._error(HTTPStatus.NOT_FOUND, "not found")
        path, query = route
        if path in ("/", "/index.html"):
            return self._send(200, _asset("index.html"), ASSETS["index.html"])
        if path.startswith("/assets/") and path[len("/assets/"):] in ASSETS:
            name = path[len("/assets/"):]
            return self._send(200, _asset(name), ASSETS[name])
        handler = self.server.api_get.get(path)
        if handler is None:
            return self._error(HTTPStatus.NOT_FOUND, "not found")
        self._answer(handler, query)

    def do_POST(self) -> None:  # noqa: N802
        if not self._host_ok():
            return self._error(HTTPStatus.FORBIDDEN, "wrong Host")
        origin = self.headers.get("Origin")
        port = self.server.server_address[1]
        if origin is not None and origin not in (f"http://127.0.0.1:{port}",
                                                 f"http://localhost:{port}"):
            return self._error(HTTPStatus.FORBIDDEN, "cross-origin request refused")
        route = self._route()
        handler = None if route is None else self.server.api_post.get(route[0])
        if handler is None:
            return self._error(HTTPStatus.NOT_FOUND, "not found")
        if not (self.headers.get("Content-Type") or "").startswith("application/json"):
            return self._error(HTTPStatus.UNSUPPORTED_MEDIA_TYPE, "expected application/json")
        try:
            n = int(self.headers.get("Content-Length") or "0")
        except ValueError:
            n = -1
        if not 0 <= n <= MAX_BODY:
            return self._error(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, "body too large")
        try:
            body = json.loads(self.rfile.read(n) or b"null")
        except (json.JSONDecodeError, UnicodeDecodeError):
            return self._error(HTTPStatus.BAD_REQUEST, "the body is not JSON")
        self._answer(lambda _q: handler(body), {})

    def _answer(self, handler: Callable[[dict[str, str]], Any], query: dict[str, str]) -> None:
        try:
            out = handler(query)
        except (BadRequest, KeyError, IndexError, ValueError) as exc:
            msg = exc.args[0] if exc.args else str(exc)
            return self._error(HTTPStatus.BAD_REQUEST, str(msg))
        except OSError as exc:  # the result file went away, a full disk ...
            return self._error(HTTPStatus.SERVICE_UNAVAILABLE, str(exc))
        if isinstance(out, tuple):  # (bytes, content type)
            return self._send(200, out[0], out[1])
        if isinstance(out, np.ndarray):
            return self._send(200, np.ascontiguousarray(out, dtype="<f4").tobytes(),
                              "application/octet-stream")
        self._json(out)


class ViewServer(ThreadingHTTPServer):
    """A threading HTTP server on 127.0.0.1 whose API is ``api_get`` (path -> query ->
    answer) and ``api_post`` (path -> JSON body -> answer); answers are JSON-able objects,
    float32 arrays (sent as little-endian bytes) or ``(bytes, content type)``."""

    daemon_threads = True
    allow_reuse_address = False

    def __init__(self, port: int, api_get: dict[str, Callable[[dict[str, str]], Any]],
                 api_post: dict[str, Callable[[Any], Any]] | None = None,
                 verbose: bool = False) -> None:
        self.api_get = api_get
        self.api_post = api_post or {}
        self.verbose = verbose
        super().__init__((HOST, int(port)), _Handler)

    @property
    def url(self) -> str:
        """The page's address, e.g. ``http://127.0.0.1:8731/``."""
        return f"http://{HOST}:{self.server_address[1]}/"

    def start(self) -> threading.Thread:
        """Serve in a background thread (tests); :meth:`shutdown` stops it."""
        t = threading.Thread(target=self.serve_forever, kwargs={"poll_interval": 0.1},
                             daemon=True)
        t.start()
        return t


# ----------------------------------------------------------------------------------------
# the API of a result file and of the drawing page
# ----------------------------------------------------------------------------------------


def _int(query: dict[str, str], key: str, default: int | None = None) -> int:
    text = query.get(key)
    if text is None or text == "":
        if default is None:
            raise BadRequest(f"missing parameter {key!r}")
        return default
    try:
        return int(text)
    except ValueError:
        raise BadRequest(f"{key}: expected an integer, got {text!r}") from None


def _float(query: dict[str, str], key: str, default: float) -> float:
    text = query.get(key)
    if text is None or text == "":
        return default
    try:
        v = float(text)
    except ValueError:
        raise BadRequest(f"{key}: expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise BadRequest(f"{key}: expected a finite number")
    return v


def result_api(src: Any) -> dict[str, Callable[[dict[str, str]], Any]]:
    """The GET routes of a result file's page (``src``: :mod:`torch_stsdic.view.source`)."""
    from torch_stsdic.view.source import MIN_ZNCC, colour_maps

    maps = colour_maps()

    def zn(q: dict[str, str]) -> float:
        return _float(q, "min_zncc", MIN_ZNCC)

    def image(q: dict[str, str]) -> tuple[bytes, str]:
        if src.images is None:
            raise BadRequest("no image series: start 'stsdic view' with --image")
        k = _int(q, "frame")
        if not 0 <= k < len(src.images):
            raise BadRequest(f"frame {k} is not in the image series (0..{len(src.images) - 1})")
        return src.images.png(k), "image/png"

    def limits(q: dict[str, str]) -> dict[str, Any]:
        row = q.get("row")
        return src.limits(q.get("name", ""), None if row in (None, "") else _int(q, "row"),
                          zn(q))

    api: dict[str, Callable[[dict[str, str]], Any]] = {
        "/api/meta": lambda q: src.meta(),
        "/api/progress": lambda q: src.progress(),
        "/api/colormaps": lambda q: maps,
        "/api/field": lambda q: src.row_values(q.get("name", ""), _int(q, "row"), zn(q)),
        "/api/positions": lambda q: src.positions(_int(q, "row")),
        "/api/limits": limits,
        "/api/point": lambda q: src.point_values(_int(q, "row"), _int(q, "point")),
        "/api/history": lambda q: src.history(_int(q, "point"), q.get("name", ""), zn(q)),
        "/api/stats": lambda q: src.row_stats(_int(q, "row"), zn(q)),
        "/api/image": image,
    }
    if hasattr(src, "shape3d"):
        api["/api/shape"] = lambda q: src.shape3d(_int(q, "row"))
    return api


def make_server(port: int, api_get: dict[str, Callable[[dict[str, str]], Any]],
                api_post: dict[str, Callable[[Any], Any]] | None = None,
                verbose: bool = False) -> ViewServer:
    """A :class:`ViewServer` on 127.0.0.1:``port`` (0: a free port); OSError (one line)
    when the port is taken."""
    try:
        return ViewServer(port, api_get, api_post, verbose)
    except OSError as exc:
        raise OSError(f"cannot serve on {HOST}:{port}: {exc.strerror or exc}") from None


def draw_api(images: Any, reference: int, inputs: list[str], mask_out: Any,
             overwrite: bool = False, on_save: Callable[[dict[str, Any]], None] | None = None
             ) -> tuple[dict[str, Callable[[dict[str, str]], Any]],
                        dict[str, Callable[[Any], Any]]]:
    """The GET and POST routes of the drawing page: the reference frame ``reference`` of
    ``images`` (:class:`~torch_stsdic.view.source.ImageSource`), and POST ``/api/region``
    which saves the drawn mask to ``mask_out`` (a file there before the server started is
    replaced only with ``overwrite``) and answers the ``stsdic run`` command; ``on_save``
    gets that answer too (the command line prints it)."""
    from pathlib import Path

    from torch_stsdic.analysis.points import grid_points
    from torch_stsdic.view.region import Region, rasterise, run_command, save_mask

    h, w = images.shape
    mask_path = Path(mask_out)
    protect = mask_path.exists() and not overwrite
    lock = threading.Lock()

    def meta(q: dict[str, str]) -> dict[str, Any]:
        return {"mode": "draw", "image": {"width": w, "height": h, "frames": len(images)},
                "reference": reference, "inputs": inputs, "mask_out": str(mask_path),
                "step": 10, "subset": 21}

    def image(q: dict[str, str]) -> tuple[bytes, str]:
        k = _int(q, "frame", reference)
        if not 0 <= k < len(images):
            raise BadRequest(f"frame {k} is not in the image series (0..{len(images) - 1})")
        return images.png(k), "image/png"

    def region(body: Any) -> dict[str, Any]:
        nonlocal protect
        reg = Region.from_json(body, (h, w))
        step = int(body.get("step") or 10)
        subset = int(body.get("subset") or 21)
        if not (1 <= step <= 10_000 and 5 <= subset <= 10_001 and subset % 2):
            raise BadRequest("step: expected 1 .. 10000 px; subset: an odd number >= 5 px")
        mask = rasterise(reg, (h, w)) if reg.has_mask else None
        if mask is not None and not mask.any():
            raise BadRequest("the mask is empty: the holes cover every region")
        try:
            pts = grid_points((h, w), step, reg.roi, mask, subset).numpy()
        except ValueError as exc:
            raise BadRequest(f"no grid point: {exc}") from None
        with lock:
            if mask is not None:
                if protect:
                    raise BadRequest(f"{mask_path} exists: start 'stsdic view' with "
                                     "--overwrite to replace it, or choose --mask-out")
                save_mask(mask, mask_path)
        opts = ([] if step == 10 else ["--step", str(step)]) + \
            ([] if subset == 21 else ["--subset", str(subset)])
        cmd = run_command(inputs, reg.roi, str(mask_path) if mask is not None else None,
                          options=opts)
        out = {"command": cmd, "roi": list(reg.roi) if reg.roi else None,
               "mask": str(mask_path) if mask is not None else None,
               "mask_pixels": int(mask.sum()) if mask is not None else None,
               "n_points": int(len(pts)), "points": pts.astype(np.float32).ravel().tolist()}
        if on_save is not None:
            on_save(out)
        return out

    return {"/api/meta": meta, "/api/image": image}, {"/api/region": region}
