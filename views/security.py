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

Two more guards keep a page's input from exhausting the app: an upload larger than
:data:`MAX_UPLOAD_BYTES` is refused when it starts (before any part is buffered), as is a part
that goes beyond the size its upload declared; and :func:`safe_upload_name` turns any uploaded
file name into one that can be stored (no folders, no NUL or control characters, at most
:data:`MAX_UPLOAD_NAME` characters). :func:`check_listen` tries the address before the server
starts, so that a port or host that cannot be used is a one-line error, not a server thread that
dies while the app waits for it. :func:`check_host` refuses a host that other machines can reach
(``0.0.0.0``) unless the caller allows it, with a warning: the origin check keeps hostile web
pages out, but a client on the network needs no web page.

viser builds its websockets server inside ``ViserServer.__init__`` with no hook for either, so
:func:`secure_viser_server` wraps ``websockets.asyncio.server.serve`` only while the server is
being built (viser calls it from its server thread before ``__init__`` returns; a lock keeps two
builds from overlapping) and puts the origin check in front of viser's own ``process_request``.
"""

from __future__ import annotations

import errno
import http
import ipaddress
import logging
import re
import socket
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

MAX_UPLOAD_BYTES = 100_000_000
"""Largest upload (bytes): a 24-megapixel 16-bit grey TIFF is 48 MB. viser buffers an upload's
parts and then joins them, so an upload holds about twice its size while it arrives; larger
frames are opened from their folder instead."""

MAX_UPLOAD_NAME = 100
"""Longest stored upload name (characters, suffix kept); longer names are shortened."""

_UNSAFE = re.compile(r"[\x00-\x1f\x7f/\\]")
"""Characters never kept in a stored upload name: NUL and other control characters, separators."""


class ServeError(RuntimeError):
    """The app cannot listen on the host and port asked for (a one-line message)."""


def check_listen(host: str, port: int) -> None:
    """Check that a server can listen on ``host:port`` before one is started.

    A port in use is accepted (viser then takes the next free one); any other failure is not.

    Raises:
        ServeError: a port outside 0 to 65535, a host that does not resolve, or an address that
            cannot be bound (not this machine's, or a privileged port), naming it.
    """
    if not 0 <= port <= 65535:
        raise ServeError(f"--port {port}: not a TCP port (0 to 65535)")
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except (socket.gaierror, UnicodeError) as exc:
        raise ServeError(f"--host {host!r}: not a host name or address of this machine ({exc})") from None
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(address)
        except OSError as exc:
            if exc.errno != errno.EADDRINUSE:
                raise ServeError(f"cannot listen on {host}:{port} ({exc.strerror or exc})") from None


def is_local_host(host: str) -> bool:
    """Whether ``host`` names this machine's loopback interface only (``127.0.0.1``, ``::1``,
    ``localhost``, or a name that resolves to loopback addresses alone): no other machine can
    reach a server listening there. ``0.0.0.0`` and ``::`` (every interface) are not local."""
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        pass
    try:
        found = {info[4][0] for info in socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)}
    except (socket.gaierror, UnicodeError):
        return False
    return bool(found) and all(ipaddress.ip_address(a.split("%")[0]).is_loopback for a in found)


def check_host(host: str, allow_remote: bool) -> str | None:
    """Refuse a host other machines can reach unless ``allow_remote``; a warning to print when it
    is allowed.

    Anyone who reaches the app can browse, read and export into any folder this user can, and
    start runs: the origin check keeps other web pages out, not other machines.

    Returns:
        None for a local host (:func:`is_local_host`), else the warning.
    Raises:
        ServeError: a host other machines can reach, without ``allow_remote``.
    """
    if is_local_host(host):
        return None
    exposed = (f"--host {host} exposes the app to the network: any client that reaches it can browse and "
               f"read files, export into any folder and run jobs as this user")
    if not allow_remote:
        raise ServeError(f"{exposed}; add --allow-remote to do so on a network you trust")
    return f"{exposed} (--allow-remote)"


def safe_upload_name(name: str) -> str:
    """An uploaded file's name as it is stored: its last path part, without NUL, control
    characters or separators, shortened to :data:`MAX_UPLOAD_NAME` characters (its suffix kept);
    ``upload`` when nothing is left."""
    base = _UNSAFE.sub("_", re.split(r"[/\\]", name)[-1]).strip(" .") or "upload"
    if len(base) <= MAX_UPLOAD_NAME:
        return base
    stem, dot, suffix = base.rpartition(".")
    if not dot or len(suffix) > 10:
        return base[:MAX_UPLOAD_NAME]
    return stem[:MAX_UPLOAD_NAME - len(suffix) - 1] + "." + suffix


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


def _notify(server: viser.ViserServer, client_id: int, title: str, text: str) -> None:
    client = server.get_clients().get(client_id)
    if client is not None:
        client.add_notification(title, text, auto_close_seconds=8.0, color="red")


def _guard_uploads(server: viser.ViserServer) -> None:
    """Refuse uploads over :data:`MAX_UPLOAD_BYTES` when they start, and drop an upload whose
    parts go beyond its declared size, in front of viser's own handlers."""
    gui = server.gui
    websock = server._websock_server
    start_upload = gui._handle_file_transfer_start
    add_part = gui._handle_file_transfer_part
    transfers = gui._current_file_upload_states

    def start(client_id: int, message: _messages.FileTransferStartUpload) -> None:
        if message.size_bytes > MAX_UPLOAD_BYTES or message.size_bytes < 0:
            name = safe_upload_name(message.filename)
            log.warning("refused an upload of %d bytes (%s)", message.size_bytes, name)
            _notify(server, client_id, "Upload refused",
                    f"{name}: {message.size_bytes / 1e6:.1f} MB, more than the "
                    f"{MAX_UPLOAD_BYTES / 1e6:.0f} MB an upload may have; open its folder instead")
            return
        start_upload(client_id, message)

    def part(client_id: int, message: _messages.FileTransferPart) -> None:
        state = transfers.get(message.transfer_uuid)
        if state is not None and state["transferred_bytes"] + len(message.content) > state["total_bytes"]:
            transfers.pop(message.transfer_uuid, None)
            log.warning("dropped an upload whose parts exceed its declared %d bytes", state["total_bytes"])
            return
        add_part(client_id, message)

    websock.unregister_handler(_messages.FileTransferStartUpload)
    websock.register_handler(_messages.FileTransferStartUpload, start)
    websock.unregister_handler(_messages.FileTransferPart)
    websock.register_handler(_messages.FileTransferPart, part)


def secure_viser_server(host: str, port: int, label: str) -> viser.ViserServer:
    """A ``viser.ViserServer`` on ``host:port`` with the origin check, no share URL and the
    upload guards.

    Args:
        host: interface to listen on.
        port: TCP port (0: any free port; viser takes the next free one if taken).
        label: the panel's label.
    Returns:
        The running server; stop it with ``server.stop()``.
    Raises:
        ServeError: the server cannot listen on ``host:port`` (:func:`check_listen`).
        RuntimeError: viser built its server without ``websockets.asyncio.server.serve`` (another
            viser version), so the origin check is not in place; the server is stopped.
    """
    check_listen(host, port)
    with _origin_guarded_serve() as guarded:
        server = viser.ViserServer(host=host, port=port, label=label, verbose=False)
    if not guarded:
        server.stop()
        raise RuntimeError(f"viser {viser.__version__} did not build its websocket server through "
                           "websockets.asyncio.server.serve: the origin check cannot be installed")
    websock = server._websock_server  # viser exposes no public hook for its message handlers
    websock.unregister_handler(_messages.ShareUrlRequest)
    websock.register_handler(_messages.ShareUrlRequest, _refuse_share)
    _guard_uploads(server)
    return server
