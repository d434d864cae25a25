"""Helpers shared by the browser-drive test modules (test_web_protocol, test_web_browser): a real
drive server (uvicorn, the app, the robot's planner) on a free loopback port in a thread, a
WebSocket client, and a scripted driver."""

from __future__ import annotations

import json
import threading
import time
from contextlib import contextmanager

from websockets.sync.client import connect

from trafficweaving.scenario import LANE_CENTRE_Y, LANE_DIVIDER_Y
from trafficweaving.web.server import build_server
from trafficweaving.web.room import DriveConfig


@contextmanager
def drive_server(out, mode: str = "robot", countdown: int = 0, max_rooms: int = 64, host: str = "127.0.0.1",
                 allowed_hosts=(), limits=None):
    """A running drive server on ``host`` recording into ``out``; yields its URL
    (``http://127.0.0.1:PORT/``; off loopback with ``?key=...``). ``allowed_hosts`` and ``limits``:
    as ``build_server``'s."""
    server = build_server(DriveConfig(mode=mode, countdown_s=countdown, max_rooms=max_rooms), host, 0, str(out),
                          allowed_hosts, limits)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.server.started and time.monotonic() < deadline:
        time.sleep(0.02)
    assert server.server.started, "the drive server did not start"
    try:
        yield server.url
    finally:
        server.server.should_exit = True
        thread.join(15)
        server.close()


def ws_url(url: str) -> str:
    return url.replace("http://", "ws://") + "ws"


@contextmanager
def client(url: str, query: str = ""):
    """A WebSocket connection to the server at ``url`` (``query``: e.g. a join link's
    ``?room=N&token=T``), the welcome message already read (in ``.welcome``); it buffers every
    message it has not read yet, so that closing it never waits on an unread backlog."""
    with connect(ws_url(url) + query, max_size=None, max_queue=None, open_timeout=10) as ws:
        ws.welcome = receive(ws)
        assert ws.welcome["type"] == "welcome", ws.welcome
        yield ws


def receive(ws, timeout: float = 20.0) -> dict:
    return json.loads(ws.recv(timeout=timeout))


def send(ws, message) -> None:
    ws.send(message if isinstance(message, (str, bytes)) else json.dumps(message))


def lane_change_steer(state, start_y: float) -> float:
    """A scripted driver's steering, in [-1, 1] (negative: left), for a car in ``state [6]`` that
    started at ``start_y``: towards the centre of the other lane, proportional to the distance."""
    target = LANE_CENTRE_Y["left"] if start_y < LANE_DIVIDER_Y else LANE_CENTRE_Y["right"]
    return max(-1.0, min(1.0, 0.5 * (state[1] - target) + 0.3 * state[3]))
