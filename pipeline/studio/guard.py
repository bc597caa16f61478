"""Who may open the studio: its own page, with the token of this launch (as Jupyter does).

A page on any site can open `ws://127.0.0.1:PORT` from the user's browser (binding to the
loopback does not stop it), so every request is checked before viser sees it:
- the websocket's `Origin` must be the studio's own address (the request's `Host`, itself a
  name of the bound address: a DNS-rebound name is refused), or absent (a program, not a
  browser page: the token then is all it has);
- the token printed in the URL (`?token=...`) must come with it, in the URL or in the cookie
  the page got when it was opened with the token (HttpOnly, SameSite=Strict: a foreign page
  never sends it).
The page itself (viser's client) is served only with the token too.

viser (1.1) has no hook on the opening handshake: `viser.infra.WebsockServer` passes its own
`process_request` to `websockets.asyncio.server.serve` from its server thread. `guarded`
therefore replaces `serve` in websockets' module only while `ViserServer` starts (the call
is made before `ViserServer()` returns) and wraps viser's `process_request` with `Guard.check`;
nothing else of viser or websockets is changed, and other servers of the process are not
touched.
"""

from __future__ import annotations

import hmac
import http
import secrets
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from http.cookies import SimpleCookie
from typing import Any
from urllib.parse import parse_qs, urlsplit

import websockets.asyncio.server as ws_server
from websockets.http11 import Request, Response

LOOPBACK = ("127.0.0.1", "localhost", "::1")
ANY = ("0.0.0.0", "::", "")


class Guard:
    """The checks of one launch: its token and the host names it answers to."""

    def __init__(self, host: str, token: str | None = None):
        self.token = token or secrets.token_urlsafe(24)
        # names a browser may use for the bound address (any, when bound to all interfaces:
        # the token is then what keeps other pages out)
        self.hosts = None if host in ANY else {host, *LOOPBACK} if host in LOOPBACK else {host}
        self.refused = 0  # requests refused so far

    def cookie_name(self, port: int) -> str:
        return f"blunf-studio-{port}"  # one per port: two studios keep their own

    def check(self, connection: Any, request: Request) -> Response | None:
        """None lets the request through; else the refusal (403) viser never sees."""
        h = request.headers
        port = connection.local_address[1]
        hosts = h.get_all("Host")
        if len(hosts) != 1:
            return self._refuse(connection, "one Host header expected")
        host = hosts[0]
        url = urlsplit(request.path)
        given = parse_qs(url.query).get("token", [""])[0]
        cookie = SimpleCookie()
        try:
            cookie.load(h.get("Cookie", ""))
        except Exception:  # a malformed cookie header: as no cookie
            cookie = SimpleCookie()
        jar = cookie.get(self.cookie_name(port))
        origins = h.get_all("Origin")
        if len(origins) > 1:
            return self._refuse(connection, "one Origin header expected")
        has_token = self._same(given) or (jar is not None and self._same(jar.value))
        if not self._own_host(host):
            return self._refuse(connection, f"host {host!r} is not this studio's")
        if h.get("Upgrade", "").lower() == "websocket":
            origin = origins[0] if origins else None
            if origin is not None and urlsplit(origin).netloc != host:
                return self._refuse(connection, f"origin {origin!r} is not this studio's")
            if not has_token:
                return self._refuse(connection, "no token (open the URL blunf studio printed)")
            return None
        if not has_token:
            return self._refuse(connection, "no token: open the URL blunf studio printed")
        return None

    def cookie(self, port: int) -> str:
        return f"{self.cookie_name(port)}={self.token}; Path=/; HttpOnly; SameSite=Strict"

    def _same(self, given: str) -> bool:
        return bool(given) and hmac.compare_digest(given.encode(), self.token.encode())

    def _own_host(self, host: str) -> bool:
        if self.hosts is None:
            return True
        name = urlsplit(f"//{host}").hostname or ""
        return name in self.hosts

    def _refuse(self, connection: Any, why: str) -> Response:
        self.refused += 1
        return connection.respond(http.HTTPStatus.FORBIDDEN, f"blunf studio: {why}\n")


_patch_lock = threading.Lock()


@contextmanager
def guarded(guard: Guard) -> Iterator[None]:
    """While in this block, a websockets server started (viser's) runs `guard.check` before
    its own `process_request`, and its page's responses set the token's cookie."""
    original = ws_server.serve

    class serve(original):  # type: ignore[misc, valid-type]
        def __init__(self, *args: Any, process_request: Callable | None = None, **kw: Any):
            super().__init__(*args, process_request=_wrap(guard, process_request), **kw)

    with _patch_lock:
        ws_server.serve = serve  # type: ignore[misc]
        try:
            yield
        finally:
            ws_server.serve = original  # type: ignore[misc]


def _wrap(guard: Guard, inner: Callable | None) -> Callable:
    def process_request(connection: Any, request: Request) -> Response | None:
        refused = guard.check(connection, request)
        if refused is not None:
            return refused
        response = inner(connection, request) if inner is not None else None
        if response is not None and response.status_code == http.HTTPStatus.OK:
            response.headers["Set-Cookie"] = guard.cookie(connection.local_address[1])
        return response

    return process_request
