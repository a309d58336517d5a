"""A viser server that only browser pages of its own origin can drive, and that never shares itself.

The app listens on 127.0.0.1, but any web page the user opens can make the browser open a
websocket to ``ws://127.0.0.1:PORT``: without a check, that page could set the folder and pattern
fields (reading files as the app's user) and send viser's share-URL request, which makes the
server open a public tunnel (``share.viser.studio``). viser 1.1 checks neither, so
:func:`secure_viser_server` adds both checks on the server side (hiding the share button is only
cosmetic):

* **Origin check at the websocket handshake.** A browser sends an ``Origin`` header with every
  websocket handshake, and a page cannot forge it. A handshake is accepted only when its
  ``Origin`` is ``http://HOST:PORT`` with the same host and port as its ``Host`` header (the
  app's own page), the port is the one the server is bound to, and the host is ``localhost`` or
  an IP literal (a DNS name could be rebound to 127.0.0.1 by a hostile page). Anything else,
  ``Origin: null`` included, gets ``403 Forbidden`` before the websocket opens, so the page never
  sees a message. A handshake *without* ``Origin`` is accepted: only non-browser clients omit
  it, and those can write any ``Origin`` they like anyway, so refusing them would protect
  nothing (a local process can read the user's files directly).
* **No share URL.** viser's ``ShareUrlRequest`` handler is removed and replaced by one that
  refuses and logs; no tunnel is ever created, whatever a client sends.

viser builds its websockets server inside ``ViserServer.__init__`` with no hook for either, so
:func:`secure_viser_server` wraps ``websockets.asyncio.server.serve`` only while the server is
being built (viser calls it from its server thread before ``__init__`` returns; a lock keeps two
builds from overlapping) and puts the origin check in front of viser's own ``process_request``.
"""

from __future__ import annotations

import http
import ipaddress
import logging
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any
from urllib.parse import urlsplit

import viser
import websockets.asyncio.server as ws_server
from viser import _messages
from websockets.asyncio.server import ServerConnection
from websockets.http11 import Request, Response

log = logging.getLogger(__name__)

_BUILD_LOCK = threading.Lock()
"""Serialises the builds that temporarily wrap ``websockets.asyncio.server.serve``."""

ProcessRequest = Callable[[ServerConnection, Request], Response | None]


def _host_port(netloc: str) -> tuple[str, int | None] | None:
    """``(host, port)`` of ``host[:port]`` (IPv6 in brackets), lower case; None if malformed."""
    try:
        parts = urlsplit(f"//{netloc}")
        return (parts.hostname or ""), parts.port
    except ValueError:
        return None


def _is_literal_or_localhost(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


def origin_allowed(origin: str | None, host_header: str | None, port: int) -> bool:
    """Whether a websocket handshake with this ``Origin`` may drive a server bound to ``port``.

    Args:
        origin: the handshake's ``Origin`` header (None: absent, a non-browser client).
        host_header: the handshake's ``Host`` header.
        port: the TCP port the server is bound to.
    Returns:
        True for a missing ``Origin``, or for ``http://HOST:PORT`` equal to the ``Host`` header,
        on the bound port, with ``HOST`` ``localhost`` or an IP literal; False otherwise.
    """
    if origin is None:
        return True
    parts = urlsplit(origin)
    if parts.scheme != "http" or parts.path not in ("", "/") or parts.query or parts.fragment:
        return False
    own = _host_port(parts.netloc)
    asked = _host_port(host_header or "")
    if own is None or asked is None or own != asked:
        return False
    host, origin_port = own
    return origin_port == port and _is_literal_or_localhost(host)


def _guard_origin(inner: ProcessRequest | None) -> ProcessRequest:
    """``process_request`` that refuses foreign-origin websocket handshakes, then calls ``inner``."""

    def process_request(connection: ServerConnection, request: Request) -> Response | None:
        if request.headers.get("Upgrade", "").lower() == "websocket":
            origins = request.headers.get_all("Origin")
            hosts = request.headers.get_all("Host")
            port = connection.local_address[1]
            if (len(origins) > 1 or len(hosts) != 1
                    or not origin_allowed(origins[0] if origins else None, hosts[0], port)):
                log.warning("refused a websocket from origin %s (Host %s)", ", ".join(origins) or "-",
                            ", ".join(hosts) or "-")
                return connection.respond(http.HTTPStatus.FORBIDDEN, "foreign origin refused\n")
        return inner(connection, request) if inner is not None else None

    return process_request


@contextmanager
def _origin_guarded_serve() -> Iterator[list[int]]:
    """While active, every websockets server built gets the origin guard in its handshake; yields
    a list that gets one entry per guarded server."""
    with _BUILD_LOCK:
        original = ws_server.serve
        guarded: list[int] = []

        def serve(*args: Any, process_request: ProcessRequest | None = None, **kwargs: Any
                  ) -> ws_server.serve:
            guarded.append(1)
            return original(*args, process_request=_guard_origin(process_request), **kwargs)

        ws_server.serve = serve  # type: ignore[assignment,misc]
        try:
            yield guarded
        finally:
            ws_server.serve = original  # type: ignore[misc]


def _refuse_share(client_id: int, _message: _messages.ShareUrlRequest) -> None:
    log.warning("refused a share-URL request from client %d: this app is never shared", client_id)


def secure_viser_server(host: str, port: int, label: str) -> viser.ViserServer:
    """A ``viser.ViserServer`` on ``host:port`` with the origin check and no share URL.

    Args:
        host: interface to listen on.
        port: TCP port (0: any free port; viser takes the next free one if taken).
        label: the panel's label.
    Returns:
        The running server; stop it with ``server.stop()``.
    Raises:
        RuntimeError: viser built its server without ``websockets.asyncio.server.serve`` (another
            viser version), so the origin check is not in place; the server is stopped.
    """
    with _origin_guarded_serve() as guarded:
        server = viser.ViserServer(host=host, port=port, label=label, verbose=False)
    if not guarded:
        server.stop()
        raise RuntimeError(f"viser {viser.__version__} did not build its websocket server through "
                           "websockets.asyncio.server.serve: the origin check cannot be installed")
    websock = server._websock_server  # viser exposes no public hook for its message handlers
    websock.unregister_handler(_messages.ShareUrlRequest)
    websock.register_handler(_messages.ShareUrlRequest, _refuse_share)
    return server
