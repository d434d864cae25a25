"""``trafficweaving drive``: serve the app with uvicorn on a socket bound here (so a port in use is
a one-line error before anything loads), print the URL and open it in the user's browser.

Loopback only unless ``--host`` says otherwise; off loopback the server makes a key
(:mod:`.lobby`): its link, printed at the start, creates rooms, every room is joined only with
its own token, and the server says so when it starts. Everywhere, only requests for this
server's own hosts are served (:mod:`.hosts`: ``Host`` and ``Origin``, ``--allowed-host`` adds
names), and every connection is bounded (:mod:`.limits`: header timeout, caps per client address
and in total sized from ``RLIMIT_NOFILE``, stalled peers dropped; here: header size, frame size,
pings)."""

from __future__ import annotations

import errno
import ipaddress
import os
import socket
import threading
import time
import webbrowser
from dataclasses import dataclass, replace
from typing import Callable, Sequence

import uvicorn

from ..errors import InputError
from ..planning.mpc import NonBlockingMPCPolicy
from .app import build_robot, create_app
from .hosts import HostPolicy, parse_allowed_host
from .limits import ACCEPT_BACKLOG, ConnectionLimits, protocols
from .lobby import Lobby, new_token
from .recording import Recorder
from .room import DriveConfig

WS_MAX_FRAME_BYTES = 1 << 20
"""Largest WebSocket frame the server reads, bytes (1 MiB). Messages up to it that break the
protocol's own limit get an ``error`` reply; a larger frame closes the connection (code 1009),
which ends the trial like a closed tab."""
MAX_HEADER_BYTES = 16 * 1024
"""Largest request line and headers the server reads, bytes (16 KiB; a larger one gets HTTP 400)."""
WS_PING_S = 20.0
"""Seconds between the server's WebSocket pings, and to answer one before the connection is dropped."""


def default_threads() -> int:
    """Torch threads for the planner: all cores but one, which is left to the simulation loop,
    the server and the browser (1 on a 2-core machine)."""
    return max(1, (os.cpu_count() or 1) - 1)


def bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host``:``port`` (0: any free port); InputError when the host
    is unknown or the port cannot be had (in use, or privileged)."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except (socket.gaierror, UnicodeError) as exc:
        raise InputError(f"--host {host}: not an address of this machine ({exc})") from None
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(64)
    except OSError as exc:
        sock.close()
        reason = "is in use" if exc.errno == errno.EADDRINUSE else f"cannot be bound ({exc.strerror or exc})"
        raise InputError(f"--port {port}: port {port} on {host} {reason} (expected a free port; try another "
                         f"--port, or 0 for any free one)") from None
    return sock


def url_of(sock: socket.socket) -> str:
    """``http://HOST:PORT/`` of a bound socket."""
    host, port = sock.getsockname()[:2]
    shown = f"[{host}]" if ipaddress.ip_address(host).version == 6 else host
    return f"http://{shown}:{port}/"


def is_loopback(host: str) -> bool:
    try:
        return all(ipaddress.ip_address(info[4][0]).is_loopback
                   for info in socket.getaddrinfo(host, None, type=socket.SOCK_STREAM))
    except (socket.gaierror, ValueError, UnicodeError):
        return False


@dataclass
class DriveServer:
    """A drive app ready to serve on its bound socket: :meth:`run` serves until stopped
    (``server.should_exit = True`` from another thread, or a signal), :meth:`close` frees the
    socket and the planner thread. ``url`` opens the page (with the key off loopback)."""

    server: uvicorn.Server
    sock: socket.socket
    robot: NonBlockingMPCPolicy | None
    lobby: Lobby
    url: str

    def run(self) -> None:
        self.server.run(sockets=[self.sock])

    def close(self) -> None:
        if self.robot is not None:
            self.robot.close()
        self.sock.close()


def build_server(config: DriveConfig, host: str, port: int, out: str, allowed_hosts: Sequence[str] = (),
                 limits: ConnectionLimits | None = None) -> DriveServer:
    """Bind ``host``:``port`` (InputError when it cannot be had, or an ``allowed_hosts`` entry is not
    ``NAME[:PORT]``), load the robot (robot mode; its planner thread with ``config.threads`` torch
    threads, None: :func:`default_threads`) and make the app recording into ``out``, answering for
    the hosts of :class:`~.hosts.HostPolicy` and bounded by ``limits`` (None:
    :meth:`~.limits.ConnectionLimits.for_this_process`); off loopback with a new key (:mod:`.lobby`)."""
    allowed = [parse_allowed_host(name) for name in allowed_hosts]
    config = replace(config, threads=config.threads or default_threads())
    recorder = Recorder(out)
    sock = bind(host, port)
    try:
        robot = build_robot(config.model, config.deadline, config.threads) if config.mode == "robot" else None
    except BaseException:
        sock.close()
        raise
    key = None if is_loopback(host) else new_token()
    lobby = Lobby(config, recorder, robot, key)
    http, ws = protocols(limits or ConnectionLimits.for_this_process())
    app = create_app(lobby, HostPolicy(host, sock.getsockname(), allowed))
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", http=http, ws=ws, backlog=ACCEPT_BACKLOG,
                                           h11_max_incomplete_event_size=MAX_HEADER_BYTES,
                                           ws_max_size=WS_MAX_FRAME_BYTES, ws_ping_interval=WS_PING_S,
                                           ws_ping_timeout=WS_PING_S, timeout_graceful_shutdown=5))
    return DriveServer(server, sock, robot, lobby, url_of(sock) + ("" if key is None else f"?key={key}"))


def serve(config: DriveConfig, host: str, port: int, out: str, allowed_hosts: Sequence[str] = (),
          open_browser: bool = True, say: Callable[[str], None] = print) -> None:
    """Serve the drive app until interrupted (Ctrl-C / SIGTERM end it gracefully: a running trial
    ends as ``disconnected`` and is recorded), with ``config.threads`` torch threads for the
    planner (None: :func:`default_threads`), answering also for ``allowed_hosts``
    (``--allowed-host``). ``say`` prints the URL and warnings."""
    drive = build_server(config, host, port, out, allowed_hosts)
    try:
        say(f"trafficweaving drive ({config.mode} mode): open {drive.url} — trials are recorded in {out} "
            f"(Ctrl-C to stop)")
        if config.mode == "human-human":
            say("each page there opens a room for two drivers and shows its join link, for the second browser")
        if drive.lobby.key is not None:
            anywhere = "; put this machine's network address in it, or a name given with --allowed-host" \
                if ipaddress.ip_address(drive.sock.getsockname()[0]).is_unspecified else ""
            say(f"serving on {host}, not loopback: pages need the link above (its key creates rooms{anywhere}) or a "
                f"room's join link (its token); every other request is refused. Share only join links, on a network "
                f"you trust (plain HTTP)")
        if open_browser:
            threading.Thread(target=_open_when_up, args=(drive.server, drive.url), daemon=True).start()
        drive.run()
    finally:
        drive.close()


def _open_when_up(server: uvicorn.Server, url: str, timeout: float = 30.0) -> None:
    """Open ``url`` in the user's browser once ``server`` has started."""
    waited = 0.0
    while not server.started and waited < timeout:
        time.sleep(0.05)
        waited += 0.05
    if server.started:
        webbrowser.open(url)
