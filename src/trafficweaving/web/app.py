"""The web app: the page, its static files and the WebSocket the page drives through.

``GET /`` serves the page (``static/index.html``: plain HTML, JavaScript and a canvas; nothing
is fetched from outside the server), ``/static/...`` its script and style, and ``/ws`` is the
WebSocket of :mod:`.protocol`, one :class:`~.session.DriveSession` per connection. One page
drives at a time (the robot's planner is one): a second page is told so and closed (code 1013,
try again later). A WebSocket whose ``Origin`` is not the server itself is refused at the
handshake (HTTP 403), so that another web site open in the same browser cannot drive or record
trials.
"""

from __future__ import annotations

import asyncio
from importlib import resources
from pathlib import Path
from urllib.parse import urlsplit

from fastapi import FastAPI, WebSocket
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles
from starlette.websockets import WebSocketDisconnect

from ..planning.mpc import NonBlockingMPCPolicy
from ..planning.planner import example_history
from ..sim.robots import robot_planner
from .recording import Recorder
from .session import DriveConfig, DriveSession

STATIC = Path(str(resources.files("trafficweaving.web") / "static"))
"""The page's files (package data)."""
BUSY_CLOSE_CODE = 1013
"""WebSocket close code for a second page while one drives ("try again later")."""
FOREIGN_ORIGIN_CLOSE_CODE = 1008
"""Close code for a page from another origin ("policy violation"); closed before the handshake
completes, the client sees HTTP 403."""


def build_robot(model: str, deadline: float, threads: int, device: str = "cpu") -> NonBlockingMPCPolicy:
    """The default planner (``sim.robots.robot_planner("planner")``: decisive, against the human
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


def create_app(config: DriveConfig, recorder: Recorder, robot: NonBlockingMPCPolicy | None) -> FastAPI:
    """The app serving ``config``'s mode; trials go to ``recorder``; ``robot`` (robot mode only)
    is the planner agent (:func:`build_robot`)."""
    app = FastAPI(title="trafficweaving drive", docs_url=None, redoc_url=None, openapi_url=None)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    app.state.driving = False  # whether a page is driving (the event loop's single thread sets it)

    @app.get("/", include_in_schema=False)
    async def page() -> FileResponse:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-store"})

    @app.websocket("/ws")
    async def drive(websocket: WebSocket) -> None:
        if not _same_origin(websocket):
            await websocket.close(code=FOREIGN_ORIGIN_CLOSE_CODE)
            return
        await websocket.accept()
        if app.state.driving:
            await websocket.send_json({"type": "error", "error": "another page is driving (close it, then reload "
                                                                  "this one)", "for": None})
            await websocket.close(code=BUSY_CLOSE_CODE)
            return
        app.state.driving = True
        session = DriveSession(websocket.send_text, config, recorder, robot)
        try:
            await session.open()
            while True:
                event = await websocket.receive()
                if event["type"] == "websocket.disconnect":
                    break
                text = event.get("text")
                await session.receive(text if text is not None else event.get("bytes"))
                await asyncio.sleep(0)  # a flood of messages does not hold up the trial loop
        except WebSocketDisconnect:
            pass
        finally:
            await session.close("disconnected")
            app.state.driving = False

    return app
