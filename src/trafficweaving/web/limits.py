"""Bounds on the server's connections, on top of uvicorn's own (:mod:`.server` sets those: request
headers of at most 16 KiB, WebSocket frames of at most 1 MiB, a ping every 20 s that must be
answered within 20 s, a listen backlog of :data:`ACCEPT_BACKLOG`).

uvicorn closes a keep-alive connection only after a response; it lacks:

* **a header timeout**: a connection that has not sent a complete request's headers within
  ``header_timeout_s`` of connecting (or of its previous response) is closed, whether it sends
  nothing or a header a byte at a time;
* **caps**: at most ``total`` connections, ``per_address`` of them from one client address
  (:meth:`ConnectionLimits.for_this_process`: sized from the process's ``RLIMIT_NOFILE``, so
  the server never runs out of file descriptors). A connection beyond a cap closes the oldest
  *waiting* connection (one between requests) of that address, or of any address at the total
  cap; when every connection is serving a request or a WebSocket, the new one is closed. A page
  that drives is never closed to make room;
* **buffers**: each connection's kernel buffers are :data:`SOCKET_BUFFER_BYTES`;
* **a stall bound**: a peer that takes none of what the server sends for ``write_stall_s``
  (uvicorn stops writing at 64 KiB waiting) is dropped, and so is one that misses a WebSocket
  ping;
* **one log line** for a WebSocket text frame that is not UTF-8 (closed, code 1007), instead of
  uvicorn's traceback.

The app drops a WebSocket at once through the scope's :data:`DROP_EXTENSION` (a page whose
outgoing queue is full: :class:`~.room.Member`).
"""

from __future__ import annotations

import asyncio
import logging
import resource
import socket
from collections import Counter
from dataclasses import dataclass

from uvicorn.protocols.http.h11_impl import H11Protocol
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

log = logging.getLogger("trafficweaving.drive")

HEADER_TIMEOUT_S = 5.0
"""Seconds a connection has to send a complete request's headers."""
WRITE_STALL_S = 30.0
"""Seconds a peer may take nothing of what waits to be sent before it is dropped."""
ACCEPT_BACKLOG = 16
"""Connections waiting to be accepted (the listen backlog), also the most accepted at once."""
RESERVED_FDS = 64
"""File descriptors kept for everything but connections (recordings, threads, the event loop)."""
MAX_CONNECTIONS = 4096
"""Most connections at once, however high ``RLIMIT_NOFILE`` is."""
SOCKET_BUFFER_BYTES = 64 * 1024
"""Each connection's kernel send and receive buffers, bytes (``SO_SNDBUF``, ``SO_RCVBUF``; the
kernel doubles them): plenty for a page (tens of kB/s), and a bound on what a peer that does not
read, or floods, holds in the kernel."""
DROP_EXTENSION = "trafficweaving.drop"
"""Key of the WebSocket scope's ``extensions`` holding a callable that drops the connection now."""


@dataclass(frozen=True)
class ConnectionLimits:
    """Most connections at once (``total``), and from one client address (``per_address``);
    ``header_timeout_s`` and ``write_stall_s`` (module docstring)."""

    total: int
    per_address: int
    header_timeout_s: float = HEADER_TIMEOUT_S
    write_stall_s: float = WRITE_STALL_S

    @classmethod
    def for_this_process(cls, header_timeout_s: float = HEADER_TIMEOUT_S,
                         write_stall_s: float = WRITE_STALL_S) -> "ConnectionLimits":
        """Caps that fit this process's open-file limit: all of it but :data:`RESERVED_FDS` and
        what a burst of accepts can open before the caps see it (at most :data:`MAX_CONNECTIONS`,
        at least 8), half of that per address."""
        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
        soft = MAX_CONNECTIONS * 2 if soft == resource.RLIM_INFINITY else soft
        total = max(8, min(MAX_CONNECTIONS, soft - RESERVED_FDS - 4 * ACCEPT_BACKLOG))
        return cls(total, max(1, total // 2), header_timeout_s, write_stall_s)


def _close(transport: asyncio.Transport) -> None:
    """Close ``transport``; at once when output waits (a peer that does not read never takes it)."""
    if transport.get_write_buffer_size():
        transport.abort()
    else:
        transport.close()


class ConnectionGuard:
    """The connections of one server against its :class:`ConnectionLimits`: each counted under its
    client address; those waiting for a request, oldest first, are the ones closed to make room."""

    def __init__(self, limits: ConnectionLimits):
        self.limits = limits
        self.address: dict[asyncio.Transport, str] = {}
        self.count: Counter[str] = Counter()
        self.waiting: dict[asyncio.Transport, None] = {}  # insertion order: oldest first

    def admit(self, transport: asyncio.Transport, address: str) -> bool:
        """Count a new connection from ``address``, waiting for its request, closing the oldest
        waiting one at a cap; False (not counted) when there is none to close."""
        if self.count[address] >= self.limits.per_address and not self._evict(address):
            return False
        if len(self.address) >= self.limits.total and not self._evict(None):
            return False
        self.address[transport] = address
        self.count[address] += 1
        self.waiting[transport] = None
        return True

    def _evict(self, address: str | None) -> bool:
        for transport in self.waiting:
            if address is None or self.address[transport] == address:
                self.release(transport)
                _close(transport)
                return True
        return False

    def set_waiting(self, transport: asyncio.Transport, waiting: bool) -> None:
        """Mark ``transport`` as waiting for a request (closable to make room), or as serving one."""
        self.waiting.pop(transport, None)
        if waiting and transport in self.address:
            self.waiting[transport] = None

    def release(self, transport: asyncio.Transport) -> None:
        """``transport`` is closed: no longer counted (a no-op when it was not)."""
        address = self.address.pop(transport, None)
        self.waiting.pop(transport, None)
        if address is not None:
            self.count[address] -= 1
            if not self.count[address]:
                del self.count[address]


class _StallBound:
    """Mixin for a uvicorn protocol: drops the connection when writing has been paused (the peer
    takes nothing) for ``write_stall_s``."""

    guard: ConnectionGuard
    stall_timer: asyncio.TimerHandle | None = None

    def pause_writing(self) -> None:
        super().pause_writing()
        self._stop_stall_timer()
        self.stall_timer = self.loop.call_later(self.guard.limits.write_stall_s, self._stalled)

    def resume_writing(self) -> None:
        self._stop_stall_timer()
        super().resume_writing()

    def _stop_stall_timer(self) -> None:
        self.stall_timer = _cancelled(self.stall_timer)

    def _stalled(self) -> None:
        self.stall_timer = None
        log.warning("drive: dropped the connection of %s: it took nothing sent to it for %g s", _peer(self),
                    self.guard.limits.write_stall_s)
        self.transport.abort()


def _cancelled(timer: asyncio.TimerHandle | None) -> None:
    """Cancel ``timer`` (None: no timer); None, for the attribute that held it."""
    if timer is not None:
        timer.cancel()


def _peer(protocol) -> str:
    client = getattr(protocol, "client", None)
    return "%s:%d" % client[:2] if client else "a client"


class BoundedH11(_StallBound, H11Protocol):
    """uvicorn's HTTP/1.1 protocol under the :class:`ConnectionGuard`'s caps, with a header
    timeout."""

    request_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        if not self.guard.admit(transport, self.client[0] if self.client else ""):
            transport.close()
            return
        sock = transport.get_extra_info("socket")
        if sock is not None:
            for option in (socket.SO_SNDBUF, socket.SO_RCVBUF):
                sock.setsockopt(socket.SOL_SOCKET, option, SOCKET_BUFFER_BYTES)
        self._wait_for_request()

    def connection_lost(self, exc: Exception | None) -> None:
        self._stop_request_timer()
        self._stop_stall_timer()
        self.guard.release(self.transport)
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self._serving():
            self._serve()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._serve() if self._serving() else self._wait_for_request()

    def handle_websocket_upgrade(self, event) -> None:
        self._serve()
        self._stop_stall_timer()
        super().handle_websocket_upgrade(event)

    def _serving(self) -> bool:
        return self.cycle is not None and not self.cycle.response_complete

    def _serve(self) -> None:
        self._stop_request_timer()
        self.guard.set_waiting(self.transport, False)

    def _wait_for_request(self) -> None:
        self._stop_request_timer()
        self.guard.set_waiting(self.transport, True)
        self.request_timer = self.loop.call_later(self.guard.limits.header_timeout_s, self._request_timed_out)

    def _stop_request_timer(self) -> None:
        self.request_timer = _cancelled(self.request_timer)

    def _request_timed_out(self) -> None:
        self.request_timer = None
        if not self._serving() and not self.transport.is_closing():
            _close(self.transport)


class BoundedWebSockets(_StallBound, WebSocketsSansIOProtocol):
    """uvicorn's WebSocket protocol (the connection upgraded from :class:`BoundedH11`, still
    counted by the guard) with the stall bound, a drop callable in the scope, one log line for a
    text frame that is not UTF-8, and a missed ping dropping the connection at once."""

    def connection_lost(self, exc: Exception | None) -> None:
        self._stop_stall_timer()
        self.guard.release(self.transport)
        super().connection_lost(exc)

    def handle_connect(self, event) -> None:
        super().handle_connect(event)
        scope = getattr(self, "scope", None)  # set when the handshake goes to the app
        if scope is not None:
            scope["extensions"][DROP_EXTENSION] = self.transport.abort

    def send_receive_event_to_app(self) -> None:
        if self.curr_msg_data_type == "text" and not self.close_sent:
            try:
                b"".join(self.frames).decode()
            except UnicodeDecodeError:
                self.frames = []
                log.warning("drive: closed the WebSocket of %s: a text message that is not UTF-8 (code 1007)",
                            _peer(self))
                self.conn.send_close(1007)
                self.handle_parser_exception()
                return
        super().send_receive_event_to_app()

    def keepalive_timeout(self) -> None:
        super().keepalive_timeout()
        self.transport.abort()


def protocols(limits: ConnectionLimits) -> tuple[type[BoundedH11], type[BoundedWebSockets]]:
    """The HTTP and WebSocket protocol classes for one server (``uvicorn.Config(http=..., ws=...)``),
    sharing one :class:`ConnectionGuard` with ``limits``."""
    guard = ConnectionGuard(limits)
    return (type("DriveH11", (BoundedH11,), {"guard": guard}),
            type("DriveWebSockets", (BoundedWebSockets,), {"guard": guard}))
