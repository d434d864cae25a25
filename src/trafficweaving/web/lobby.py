"""The server's rooms: creating one, joining one with its token, and who may open the page.

Every room has a token (``secrets.token_urlsafe``: 128 random bits). A human–human room's join
link (``/?room=N&token=T``) is given to the page that created it, which shares it with the other
driver; a connection naming a room without its token is refused at the WebSocket handshake (HTTP
403), the same whether the room exists or not. A robot room is never joined: its page is its only
driver.

On loopback (the default) any page of this machine may create a room. Served on another address
(``--host``), creating a room needs the server's key too (``/?key=K``: the link the server prints
when it starts); the page (``/``) is served only to a request carrying the key or a live room's
token, and its scripts and style (``/static/...``) only to a browser holding the page pass, a
cookie set with the page. Every secret is compared in constant time. The ``Host`` and ``Origin``
checks (:mod:`.hosts`) come first, everywhere.
"""

from __future__ import annotations

import itertools
import secrets
from typing import Mapping

from ..planning.mpc import NonBlockingMPCPolicy
from .recording import Recorder
from .room import DriveConfig, PlannerQueue, Room


class Refused(Exception):
    """A request that may not have a room or the page; the message says why (for the server's
    log: the client only sees HTTP 403)."""


def new_token() -> str:
    """An unguessable token (128 random bits, URL-safe text)."""
    return secrets.token_urlsafe(16)


def same_secret(given: str, secret: str) -> bool:
    """Whether ``given`` (any text a client sent) is ``secret``, compared in constant time."""
    return secrets.compare_digest(given.encode("utf-8", "replace"), secret.encode())


class Lobby:
    """The rooms of one server (``config.mode``), recording to ``recorder``; ``robot`` is the
    planner agent the robot rooms share (None in human–human mode); ``key`` is the key that
    creates rooms and opens the page off loopback (None: not needed, on loopback); ``page_pass``
    is the cookie value that fetches the page's own files off loopback, given with the page to a
    request holding the key or a room's token (it opens nothing else)."""

    def __init__(self, config: DriveConfig, recorder: Recorder, robot: NonBlockingMPCPolicy | None,
                 key: str | None = None):
        self.config, self.recorder, self.robot, self.key = config, recorder, robot, key
        self.page_pass = None if key is None else new_token()
        self.planner = PlannerQueue() if robot is not None else None
        self.rooms: dict[int, Room] = {}
        self.numbers = itertools.count(1)

    def _keyed(self, query: Mapping[str, str]) -> bool:
        return self.key is None or same_secret(query.get("key", ""), self.key)

    def may_fetch_files(self, page_pass: str | None) -> bool:
        """Whether a request for the page's files (``/static/...``) holding the cookie value
        ``page_pass`` (None: no cookie) is served."""
        return self.page_pass is None or (page_pass is not None and same_secret(page_pass, self.page_pass))

    def _named_room(self, query: Mapping[str, str]) -> Room:
        """The room ``query`` names with its token; Refused otherwise."""
        name, token = query.get("room", ""), query.get("token", "")
        room = self.rooms.get(int(name)) if name.isascii() and name.isdigit() and len(name) < 10 else None
        if room is None or room.join_path is None or not same_secret(token, room.token):
            raise Refused(f"no room {name!r} with that token")
        return room

    def may_open_page(self, query: Mapping[str, str]) -> bool:
        """Whether a request for the page with ``query`` (the URL's parameters) is served."""
        if self._keyed(query):
            return True
        try:
            self._named_room(query)
        except Refused:
            return False
        return True

    def admit(self, query: Mapping[str, str]) -> Room | None:
        """The room a connection with ``query`` enters: the room it names with its token
        (``room``, ``token``), or a new room (needing ``key`` off loopback); Refused when neither
        is allowed, None when the server already has ``config.max_rooms`` rooms."""
        if "room" in query or "token" in query:
            return self._named_room(query)
        if not self._keyed(query):
            raise Refused("creating a room needs the server's key off loopback")
        if len(self.rooms) >= self.config.max_rooms:
            return None
        number = next(self.numbers)
        room = Room(number, new_token(), secrets.token_hex(6), self.config, self.recorder, self.robot, self.planner)
        self.rooms[number] = room
        return room

    def discard_if_empty(self, room: Room) -> None:
        """Close ``room`` once its last page has left (its progress lives on in its recordings)."""
        if room.empty and self.rooms.get(room.number) is room:
            del self.rooms[room.number]
