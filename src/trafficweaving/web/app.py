"""The web app: the page, its static files and the WebSocket the pages drive through.

``GET /`` serves the page (``static/index.html``: plain HTML, JavaScript and a canvas; nothing
is fetched from outside the server), ``/static/...`` its scripts and style, and ``/ws`` is the
WebSocket of :mod:`.protocol`. Each connection enters a room of the :class:`~.lobby.Lobby`: a new
one, or with ``?room=N&token=T`` the human–human room it was invited to. A WebSocket whose
``Origin`` is not the server itself, or that names a room without its token (or, off loopback,
creates one without the server's key), is refused at the handshake (HTTP 403), so that another
web site open in the same browser, or another machine without the link, cannot drive or record
trials. A page beyond a full room or a full server is told so and closed (code 1013, try again
later).
"""

from __future__ import annotations

import asyncio
from importlib import resources
from pathlib import Path
from urllib.parse import urlsplit

from fastapi import FastAPI, Request, WebSocket
from fastapi.responses import FileResponse, PlainTextResponse, Response
from fastapi.staticfiles import StaticFiles
from starlette.websockets import WebSocketDisconnect

from ..planning.mpc import NonBlockingMPCPolicy
from ..planning.planner import example_history
from ..sim.robots import robot_planner
from .lobby import Lobby, Refused
from .room import Member

STATIC = Path(str(resources.files("trafficweaving.web") / "static"))
"""The page's files (package data)."""
BUSY_CLOSE_CODE = 1013
"""WebSocket close code for a page beyond a full room or a full server ("try again later")."""
REFUSED_CLOSE_CODE = 1008
"""Close code for a refused page (another origin, a room without its token); closed before the
handshake completes, the client sees HTTP 403."""


def build_robot(model: str, deadline: float, threads: int, device: str = "cpu") -> NonBlockingMPCPolicy:
    """The default planner (``sim.robots.robot_planner("planner")``: comfort first, against the human
    model ``model`` in real-time mode with ``deadline`` s per plan), planning in a background
    thread with ``threads`` torch threads; warmed up with a few plans there, so that the first plan
    of a trial does not pay for lazy initialisation and the deadline mode knows this machine's speed."""
    robot = NonBlockingMPCPolicy(robot_planner("planner", model, device=device), deadline=deadline, threads=threads)
    robot.warm_up(example_history())
    return robot


def _same_origin(websocket: WebSocket) -> bool:
    """Whether the connection comes from this server's own page (or from a client that sends no
    ``Origin``, which browsers always do)."""
    origin = websocket.headers.get("origin")
    return origin is None or urlsplit(origin).netloc == websocket.headers.get("host")


def create_app(lobby: Lobby) -> FastAPI:
    """The app serving ``lobby``'s rooms."""
    app = FastAPI(title="trafficweaving drive", docs_url=None, redoc_url=None, openapi_url=None)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    @app.get("/", include_in_schema=False)
    async def page(request: Request) -> Response:
        if not lobby.may_open_page(request.query_params):
            return PlainTextResponse("refused: this server is not on loopback; open the link it printed, or a "
                                     "room's join link\n", status_code=403)
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-store"})

    @app.websocket("/ws")
    async def drive(websocket: WebSocket) -> None:
        try:
            if not _same_origin(websocket):
                raise Refused(f"origin {websocket.headers.get('origin')}")
            room = lobby.admit(websocket.query_params)
        except Refused:
            await websocket.close(code=REFUSED_CLOSE_CODE)
            return
        await websocket.accept()
        member = Member(websocket.send_text)
        if room is None or lobby.rooms.get(room.number) is not room or not room.join(member):
            why = (f"the server is full ({lobby.config.max_rooms} rooms)" if room is None
                   else f"room {room.number} is full or closed (open a new room)")
            await websocket.send_json({"type": "error", "error": why, "for": None})
            await websocket.close(code=BUSY_CLOSE_CODE)
            if room is not None:
                lobby.discard_if_empty(room)
            return
        try:
            while True:
                event = await websocket.receive()
                if event["type"] == "websocket.disconnect":
                    break
                text = event.get("text")
                await room.receive(member, text if text is not None else event.get("bytes"))
                await asyncio.sleep(0)  # a flood of messages does not hold up the trial loops
        except WebSocketDisconnect:
            pass
        finally:
            await room.leave(member)
            lobby.discard_if_empty(room)

    return app
