"""The HTTP server behind the browser views: routes, the token, nothing about the car.

Why the standard library's ThreadingHTTPServer: it is on every Python the car runs (a Jetson's
3.10 included) and needs no new dependency; each request gets its own thread, so a slow or
stalled browser only ever holds its own thread, never the control loop, which does not know
the server exists (it publishes a LiveStatus every tick whether anyone reads it or not).

Who may ask: bound to localhost (the default) anyone on this machine may, as with any local
tool; the Host header must then name localhost too, so a web page elsewhere cannot reach the
server through DNS rebinding. Bound beyond localhost, every request must carry the token
printed at start (``?token=`` or the ``X-Carrt-Token`` header), or it is refused with 403.
A POST must also carry ``X-Carrt: 1``, a header a page on another origin cannot send without
a CORS preflight this server never answers, so no other site can post an e-stop either.
"""

from __future__ import annotations

import http.server
import json
import math
import secrets
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from typing import Any
from urllib.parse import parse_qs, urlsplit

from carrt.errors import UserError

LOCALHOST = ("127.0.0.1", "localhost", "::1")
LOCAL_HOST_HEADERS = ("127.0.0.1", "localhost", "[::1]", "::1")


@dataclass(frozen=True)
class Response:
    body: bytes
    content_type: str = "application/json"
    status: int = 200


Route = Callable[[dict[str, str]], Response]  # the query's parameters -> the answer


def json_response(value: Any) -> Response:
    """JSON with NaN and infinities as null: JavaScript's JSON.parse refuses them."""
    return Response(json.dumps(finite(value), separators=(",", ":")).encode())


def finite(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite(v) for v in value]
    return value


def page(name: str) -> Response:
    """A page shipped as package data (carrt/view/*.html), with each `<!--include F.js-->` line
    replaced by that script inline: one request, so a token in the page's URL covers it all."""
    folder = resources.files("carrt.view")
    text = folder.joinpath(name).read_text()
    while (start := text.find("<!--include ")) >= 0:
        end = text.index("-->", start)
        script = folder.joinpath(text[start + len("<!--include ") : end].strip()).read_text()
        text = f"{text[:start]}<script>\n{script}</script>{text[end + 3 :]}"
    return Response(text.encode(), "text/html; charset=utf-8")


def parse_address(text: str, flag: str = "--view") -> tuple[str, int]:
    """`PORT` (on localhost) or `HOST:PORT` (`[::1]:PORT` for IPv6); port 0 picks a free one."""
    host, sep, port_text = text.rpartition(":")
    if not sep:
        host = "127.0.0.1"
    host = host.strip("[]")
    try:
        port = int(port_text)
    except ValueError:
        port = -1
    if not 0 <= port <= 65535 or (sep and not host):
        raise UserError(f"{flag}: expected PORT or HOST:PORT (port 0-65535), got {text!r}")
    return host, port


class ViewServer:
    """Binds at once (so a port in use is found before the car starts), serves once given its
    routes; `close()` stops it. `token` is None on localhost."""

    def __init__(self, address: str, *, flag: str = "--view") -> None:
        self.host, port = parse_address(address, flag)
        self.token = None if self.host in LOCALHOST else secrets.token_urlsafe(16)
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        server_class = type("Server", (_Server,), {"address_family": family})
        try:
            self._http = server_class((self.host, port), _Handler)
        except (OSError, OverflowError) as exc:
            why = getattr(exc, "strerror", None) or str(exc)
            message = f"{flag} {address}: cannot listen on {self.host}:{port} ({why})"
            raise UserError(message) from exc
        self._http.view = self
        self.port = self._http.server_address[1]
        self.get: dict[str, Route] = {}
        self.post: dict[str, Route] = {}
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host = self.host
        if host in ("0.0.0.0", "::", ""):
            host = socket.gethostname()  # what another machine would type
        elif ":" in host:
            host = f"[{host}]"
        return f"http://{host}:{self.port}/" + (f"?token={self.token}" if self.token else "")

    def serve(self, get: dict[str, Route], post: dict[str, Route] | None = None) -> ViewServer:
        self.get, self.post = dict(get), dict(post or {})
        self._thread = threading.Thread(
            target=self._http.serve_forever, kwargs={"poll_interval": 0.2}, name="carrt-view",
            daemon=True,
        )  # fmt: skip
        self._thread.start()
        return self

    def close(self) -> None:
        if self._thread is not None:
            self._http.shutdown()
            self._thread.join(timeout=5)
        self._http.server_close()

    def allowed(self, query: dict[str, str], headers: Any) -> bool:
        if self.token is None:
            return _hostname(headers.get("Host") or "") in LOCAL_HOST_HEADERS
        given = query.get("token") or headers.get("X-Carrt-Token") or ""
        return secrets.compare_digest(given.encode(), self.token.encode())


def _hostname(host_header: str) -> str:
    """The host of a Host header without its port: `localhost:8090` -> `localhost`."""
    if host_header.startswith("["):
        return host_header.split("]")[0] + "]"
    return host_header.rsplit(":", 1)[0]


class _Server(http.server.ThreadingHTTPServer):
    daemon_threads = True  # a browser left open never keeps the command from exiting
    view: ViewServer


class _Handler(http.server.BaseHTTPRequestHandler):
    server: _Server
    protocol_version = "HTTP/1.1"  # keep-alive: the page's polls reuse one connection
    timeout = 30  # an idle or stalled connection frees its thread

    def do_GET(self) -> None:
        self._answer(self.server.view.get)

    def do_POST(self) -> None:
        length = int(self.headers.get("Content-Length") or 0)
        if length:
            self.rfile.read(min(length, 4096))
        if self.headers.get("X-Carrt") != "1":
            self._send(Response(b'{"error":"missing X-Carrt header"}', status=403))
            return
        self._answer(self.server.view.post)

    def _answer(self, routes: dict[str, Route]) -> None:
        parts = urlsplit(self.path)
        query = {k: v[-1] for k, v in parse_qs(parts.query).items()}
        view = self.server.view
        if not view.allowed(query, self.headers):
            self._send(Response(b'{"error":"forbidden: token required"}', status=403))
            return
        route = routes.get(parts.path)
        if route is None:
            status = 405 if parts.path in view.get or parts.path in view.post else 404
            self._send(Response(b'{"error":"no such route"}', status=status))
            return
        try:
            response = route(query)
        except (KeyError, ValueError, IndexError) as exc:
            response = Response(json.dumps({"error": str(exc)}).encode(), status=400)
        self._send(response)

    def _send(self, response: Response) -> None:
        try:
            self.send_response(response.status)
            self.send_header("Content-Type", response.content_type)
            self.send_header("Content-Length", str(len(response.body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(response.body)
        except (BrokenPipeError, ConnectionResetError):
            self.close_connection = True  # the browser went away: nothing to tell it

    def log_message(self, *args: object) -> None:
        pass  # a request log would bury the loop's own messages in the terminal
