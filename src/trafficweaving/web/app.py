"""The web app: the page, its static files and the WebSocket the pages drive through.

``GET /`` serves the page (``static/index.html``: plain HTML, JavaScript and a canvas; nothing
is fetched from outside the server), ``/static/...`` its scripts and style, and ``/ws`` is the
WebSocket of :mod:`.protocol`. Each connection enters a room of the :class:`~.lobby.Lobby`: a new
one, or with ``?room=N&token=T`` the human–human room it was invited to.

What is checked, in order: the request's ``Host`` and a WebSocket's ``Origin`` (:mod:`.hosts`:
HTTP 400, or 403 at the handshake); off loopback, the key or a live room's token for the page and
the page pass cookie it sets for ``/static/...`` (HTTP 403); a WebSocket naming a room without its
token, or creating one off loopback without the key (403 at the handshake). So neither another
web site open in the same browser, nor one whose name points at this machine, nor another machine
without the link can drive or record trials. A page beyond a full room or a full server is told
so and closed (code 1013, try again later); a page that does not read what it is sent is dropped
(:class:`~.room.Member`).
"""

from __future__ import annotations

import asyncio
import logging
from importlib import resources
from pathlib import Path

from fastapi import FastAPI, Request, WebSocket
from fastapi.responses import FileResponse, PlainTextResponse, Response
from fastapi.staticfiles import StaticFiles
from starlette.types import Receive, Scope, Send
from starlette.websockets import WebSocketDisconnect

from ..planning.mpc import NonBlockingMPCPolicy
from ..planning.planner import example_history
from ..sim.robots import robot_planner
from . import protocol
from .hosts import REFUSED_CLOSE_CODE, HostCheck, HostPolicy
from .limits import DROP_EXTENSION
from .lobby import Lobby, Refused
from .room import Member

log = logging.getLogger("trafficweaving.drive")

STATIC = Path(str(resources.files("trafficweaving.web") / "static"))
"""The page's files (package data)."""
BUSY_CLOSE_CODE = 1013
"""WebSocket close code for a page beyond a full room or a full server ("try again later")."""
REFUSED_PAGE = "refused: this server is not on loopback; open the link it printed, or a room's join link\n"
"""The body of a refused page or page file (HTTP 403)."""


def build_robot(model: str, deadline: float, threads: int, device: str = "cpu") -> NonBlockingMPCPolicy:
    """The default planner (``sim.robots.robot_planner("planner")``: comfort first, against the human
    model ``model`` with a real-time deadline of ``deadline`` s per plan), planning in a background
    thread with ``threads`` torch threads; warmed up with a few plans there, so that the first plan
    of a trial does not pay for lazy initialisation and the planner has measured this machine's
    sampling rate, which sizes its samples to the deadline."""
    robot = NonBlockingMPCPolicy(robot_planner("planner", model, device=device), deadline=deadline, threads=threads)
    robot.warm_up(example_history())
    return robot


def create_app(lobby: Lobby, hosts: HostPolicy) -> FastAPI:
    """The app serving ``lobby``'s rooms to the hosts ``hosts`` allows."""
    app = FastAPI(title="trafficweaving drive", docs_url=None, redoc_url=None, openapi_url=None)
    app.add_middleware(HostCheck, policy=hosts)
    page_pass_cookie = f"trafficweaving-drive-{hosts.port}"
    files = StaticFiles(directory=STATIC)

    async def page_files(scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and not lobby.may_fetch_files(Request(scope).cookies.get(page_pass_cookie)):
            await PlainTextResponse(REFUSED_PAGE, status_code=403)(scope, receive, send)
            return
        await files(scope, receive, send)

    app.mount("/static", page_files, name="static")

    @app.get("/", include_in_schema=False)
    async def page(request: Request) -> Response:
        if not lobby.may_open_page(request.query_params):
            return PlainTextResponse(REFUSED_PAGE, status_code=403)
        response = FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-store"})
        if lobby.page_pass is not None:
            response.set_cookie(page_pass_cookie, lobby.page_pass, path="/static", httponly=True, samesite="strict")
        return response

    @app.websocket("/ws")
    async def drive(websocket: WebSocket) -> None:
        try:
            room = lobby.admit(websocket.query_params)
        except Refused:
            await websocket.close(code=REFUSED_CLOSE_CODE)
            return
        await websocket.accept()
        member = Member(websocket.send_text, _dropper(websocket))
        if room is None or lobby.rooms.get(room.number) is not room or not room.join(member):
            why = (f"the server is full ({lobby.config.max_rooms} rooms)" if room is None
                   else f"room {room.number} is full or closed (open a new room)")
            await websocket.send_json(protocol.error(why, None))
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


def _dropper(websocket: WebSocket):
    """What drops ``websocket``'s connection at once (logged in one line): the server's
    :data:`~.limits.DROP_EXTENSION`, or None under a server without it."""
    drop = websocket.scope.get("extensions", {}).get(DROP_EXTENSION)
    if drop is None:
        return None
    client = websocket.client

    def dropped() -> None:
        log.warning("drive: dropped the page of %s: messages for it piled up unsent (it does not read them)",
                    f"{client.host}:{client.port}" if client else "a client")
        drop()

    return dropped
