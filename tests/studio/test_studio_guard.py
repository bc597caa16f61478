"""Who may drive the studio: a real websocket client (the `websockets` package viser serves
with) opening the studio's socket with a foreign Origin, without the token or through a
foreign host name is refused before viser sees it; with the token and its own origin, it
connects and receives the page's state. The page itself needs the token too."""

from __future__ import annotations

import socket
import urllib.error
import urllib.request
from urllib.parse import urlsplit

import pytest
import viser
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from pipeline.studio.app import launch


@pytest.fixture(scope="module")
def studio(studio_run):
    _, run = studio_run  # tests/studio/conftest.py
    with socket.socket() as sk:
        sk.bind(("127.0.0.1", 0))
        port = sk.getsockname()[1]
    st, url = launch(run, "127.0.0.1", port)
    yield st, url
    st.running = False
    st.server.stop()


PROTOCOL = f"viser-v{viser.__version__}"


def _open(url: str, origin: str | None, cookie: str | None = None):
    """A websocket to `url` (its host name sent as given, the socket to the loopback)."""
    parts = urlsplit(url)
    sock = socket.create_connection(("127.0.0.1", parts.port), timeout=10)
    return connect(
        url, sock=sock, origin=origin, subprotocols=[PROTOCOL], open_timeout=10,
        additional_headers={"Cookie": cookie} if cookie else None,
    )  # fmt: skip


def test_the_printed_url_carries_a_token(studio) -> None:
    st, url = studio
    parts = urlsplit(url)
    assert parts.hostname == "127.0.0.1" and parts.port == st.server.get_port()
    assert parts.query == f"token={st.guard.token}" and len(st.guard.token) >= 32


def test_foreign_origin_or_no_token_is_refused(studio) -> None:
    st, url = studio
    port = st.server.get_port()
    ws = f"ws://127.0.0.1:{port}/"
    own = f"http://127.0.0.1:{port}"
    token = f"?token={st.guard.token}"
    clients = len(st.tabs.clients)
    refused = st.guard.refused
    cases = [
        (ws + token, "http://evil.example"),  # a foreign page, even knowing the token
        (ws + token, "http://127.0.0.1:1"),  # another local port is another origin
        (ws, own),  # its own origin, no token
        (ws + "?token=wrong", own),
        (ws, None),  # a program, no token
        # DNS rebinding: a foreign name resolved to the loopback, origin and host agreeing
        (f"ws://evil.example:{port}/{token}", f"http://evil.example:{port}"),
    ]
    for url_, origin in cases:
        with pytest.raises(InvalidStatus) as e:
            with _open(url_, origin):
                pass
        assert e.value.response.status_code == 403, (url_, origin)
    assert st.guard.refused == refused + len(cases)
    assert len(st.tabs.clients) == clients  # none of them reached the studio


def test_own_origin_with_the_token_connects(studio) -> None:
    st, url = studio
    port = st.server.get_port()
    ws = f"ws://127.0.0.1:{port}/?token={st.guard.token}"
    with _open(ws, f"http://127.0.0.1:{port}") as c:
        assert len(c.recv(timeout=10)) > 0  # the page's state, as viser sends it
    with _open(f"ws://localhost:{port}/?token={st.guard.token}", f"http://localhost:{port}") as c:
        assert len(c.recv(timeout=10)) > 0
    with _open(ws, None) as c:  # a program (no Origin) with the token
        assert len(c.recv(timeout=10)) > 0


def test_the_page_needs_the_token_then_keeps_it_in_a_cookie(studio) -> None:
    st, url = studio
    port = st.server.get_port()
    with pytest.raises(urllib.error.HTTPError) as e:
        urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10)
    assert e.value.code == 403
    with urllib.request.urlopen(url, timeout=10) as r:
        assert r.status == 200 and b"<html" in r.read(2000).lower()
        cookie = r.headers["Set-Cookie"]
    assert f"blunf-studio-{port}={st.guard.token}" in cookie
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie
    # the page's own socket (viser's client drops the URL's query) brings the cookie only
    jar = cookie.split(";")[0]
    with _open(f"ws://127.0.0.1:{port}/", f"http://127.0.0.1:{port}", cookie=jar) as c:
        assert len(c.recv(timeout=10)) > 0
    with urllib.request.urlopen(
        urllib.request.Request(f"http://127.0.0.1:{port}/", headers={"Cookie": jar}), timeout=10
    ) as r:
        assert r.status == 200


def test_any_address_needs_the_token_too(studio_run) -> None:
    _, run = studio_run
    with socket.socket() as sk:
        sk.bind(("127.0.0.1", 0))
        port = sk.getsockname()[1]
    st, url = launch(run, "0.0.0.0", port)
    try:
        port = st.server.get_port()
        assert urlsplit(url).hostname == socket.gethostname() and "token=" in url
        own = f"http://127.0.0.1:{port}"
        for url_, origin in [
            (f"ws://127.0.0.1:{port}/", own),
            (f"ws://127.0.0.1:{port}/?token={st.guard.token}", "http://evil.example"),
        ]:
            with pytest.raises(InvalidStatus, match="403"):
                with _open(url_, origin):
                    pass
        with _open(f"ws://127.0.0.1:{port}/?token={st.guard.token}", own) as c:
            assert len(c.recv(timeout=10)) > 0
    finally:
        st.running = False
        st.server.stop()
