"""The app's server refuses foreign web pages and share requests (a real websocket client, a live server)."""

from __future__ import annotations

import logging
import time
import types
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import ClassVar

import msgspec.msgpack
import pytest
import viser
import viser._viser
from websockets.exceptions import InvalidStatus
from websockets.sync.client import ClientConnection, connect
from websockets.typing import Origin, Subprotocol

import views.security
from app import serve
from views.security import origin_allowed, secure_viser_server

SUBPROTOCOL = Subprotocol(f"viser-v{viser.__version__}")
SHARE_REQUEST = msgspec.msgpack.encode({"type": "ShareUrlRequest"})


def _connect(port: int, origin: str | None, host: str = "127.0.0.1") -> ClientConnection:
    return connect(f"ws://{host}:{port}", origin=Origin(origin) if origin else None,
                   subprotocols=[SUBPROTOCOL], open_timeout=20)


def _wait_for(condition: Callable[[], bool], timeout: float = 30.0) -> bool:
    """Poll ``condition`` until it holds or ``timeout`` (a generous wait, not a speed check) runs out."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


class FakeTunnel:
    """Stands in for viser's ``ViserTunnel`` (which connects to share.viser.studio): records the
    attempt and reports failure at once, so nothing leaves the machine."""

    created: ClassVar[list[int]] = []

    def __init__(self, share_domain: str, local_port: int) -> None:
        FakeTunnel.created.append(local_port)

    def on_connect(self, callback: Callable) -> Callable:
        return callback

    def on_disconnect(self, callback: Callable) -> Callable:
        return callback

    def get_status(self) -> str:
        return "failed"

    def get_url(self) -> None:
        return None

    def close(self) -> None:
        pass


@pytest.fixture
def tunnels(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    FakeTunnel.created = []
    monkeypatch.setattr(viser._viser, "ViserTunnel", FakeTunnel)
    return FakeTunnel.created


@pytest.fixture
def app_port(tmp_path: Path) -> Iterator[int]:
    """The real app on 127.0.0.1 and a free port (an empty folder: it runs with an error notice)."""
    server, app = serve(tmp_path, port=0)
    try:
        yield server.get_port()
    finally:
        app.close()
        server.stop()


@pytest.mark.parametrize(("origin", "host", "allowed"), [
    (None, "127.0.0.1:8080", True),
    ("http://127.0.0.1:8080", "127.0.0.1:8080", True),
    ("http://localhost:8080", "localhost:8080", True),
    ("http://[::1]:8080", "[::1]:8080", True),
    ("http://evil.example.com", "127.0.0.1:8080", False),
    ("http://evil.example.com:8080", "evil.example.com:8080", False),  # DNS rebinding
    ("http://localhost:8080", "127.0.0.1:8080", False),
    ("http://127.0.0.1:9999", "127.0.0.1:9999", False),  # another port's page
    ("https://127.0.0.1:8080", "127.0.0.1:8080", False),
    ("null", "127.0.0.1:8080", False),
    ("http://127.0.0.1:8080/x", "127.0.0.1:8080", False),
    ("http://127.0.0.1:bad", "127.0.0.1:8080", False),
])
def test_origin_rule(origin: str | None, host: str, allowed: bool) -> None:
    assert origin_allowed(origin, host, 8080) is allowed


@pytest.mark.parametrize("origin", ["http://evil.example.com", "null", "http://127.0.0.1:1"])
def test_foreign_origin_is_refused_at_the_handshake(app_port: int, origin: str, caplog) -> None:
    with caplog.at_level(logging.WARNING, logger="views.security"):
        with pytest.raises(InvalidStatus) as refused:
            _connect(app_port, origin)
    assert refused.value.response.status_code == 403
    assert "refused a websocket from origin" in caplog.text


@pytest.mark.parametrize(("origin", "host"), [
    ("http://127.0.0.1:{port}", "127.0.0.1"),
    ("http://localhost:{port}", "localhost"),
    (None, "127.0.0.1"),
])
def test_own_origin_is_served(app_port: int, origin: str | None, host: str) -> None:
    with _connect(app_port, origin.format(port=app_port) if origin else None, host) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        assert isinstance(ws.recv(timeout=30), bytes)  # the app's scene and panels arrive


def test_share_request_is_refused(app_port: int, tunnels: list[int], caplog) -> None:
    with caplog.at_level(logging.WARNING, logger="views.security"), \
            _connect(app_port, f"http://127.0.0.1:{app_port}") as ws:
        ws.recv(timeout=30)
        ws.send(SHARE_REQUEST)
        assert _wait_for(lambda: "refused a share-URL request" in caplog.text)
        ws.send(SHARE_REQUEST)
        assert _wait_for(lambda: caplog.text.count("refused a share-URL request") == 2)
    assert tunnels == []


def test_plain_viser_would_accept_both(tunnels: list[int]) -> None:
    """The control: the same foreign client and share request against an unguarded viser server
    get through (so the tests above exercise the real attack)."""
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        port = server.get_port()
        with _connect(port, "http://evil.example.com") as ws:
            ws.recv(timeout=30)
            ws.send(SHARE_REQUEST)
            assert _wait_for(lambda: tunnels == [port])
    finally:
        server.stop()


def test_server_refuses_to_start_unguarded(monkeypatch: pytest.MonkeyPatch) -> None:
    """Should viser stop building its server through ``websockets.asyncio.server.serve`` (here:
    the wrapper is installed where viser does not look), the app fails closed."""
    monkeypatch.setattr(views.security, "ws_server", types.SimpleNamespace(serve=None))
    with pytest.raises(RuntimeError, match="origin check cannot be installed"):
        secure_viser_server("127.0.0.1", 0, "blurcalib")
