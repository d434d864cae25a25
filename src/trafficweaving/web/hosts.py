"""Which hosts the server answers for: the ``Host`` header of every request and the ``Origin`` of
every WebSocket, checked once, before the app (:class:`HostCheck`).

A request is served only when its ``Host`` names this server with its port: a loopback name
(``localhost``, any ``127.0.0.0/8`` or ``[::1]`` literal) when it arrived on a loopback address,
the address it arrived on, the ``--host`` it was started with, or a name given with
``--allowed-host NAME[:PORT]``. Anything else, a missing ``Host`` too, is refused (HTTP 400; a
WebSocket at the handshake, HTTP 403): a page of another site whose name an attacker points at
this machine (DNS rebinding) sends its own name, so it never reaches a page, a room or a message.
A WebSocket's ``Origin``, when sent (browsers always do), must be ``http://`` and a host the
same rules allow, so another site open in the same browser cannot drive or record trials.
"""

from __future__ import annotations

import ipaddress
import re
from typing import Iterable

from starlette.responses import PlainTextResponse
from starlette.types import ASGIApp, Receive, Scope, Send

from ..errors import InputError

_HOST = re.compile(r"\[(?P<ip6>[0-9A-Fa-f:.]+)\](?::(?P<port6>\d{1,5}))?|(?P<name>[^:\[\]/?#@\s]+)(?::(?P<port>\d{1,5}))?")
_LABEL = r"[a-z0-9](?:[a-z0-9-]{0,61}[a-z0-9])?"
_NAME = re.compile(rf"{_LABEL}(?:\.{_LABEL})*")
REFUSED_CLOSE_CODE = 1008
"""Close code for a refused WebSocket; closed before the handshake completes, the client sees
HTTP 403."""


def _address(text: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
    """``text`` as an IP address (an IPv4-mapped IPv6 address as its IPv4 one), None when it is not one."""
    try:
        address = ipaddress.ip_address(text)
    except ValueError:
        return None
    mapped = getattr(address, "ipv4_mapped", None)
    return mapped or address


def split_host(text: str) -> tuple[str, int | None] | None:
    """``(name, port)`` of a ``Host`` value ``NAME``, ``NAME:PORT``, ``[IPv6]`` or ``[IPv6]:PORT``:
    the name lower-case, an address in its canonical form, the port None when absent; None when
    ``text`` is not one of these."""
    match = _HOST.fullmatch(text)
    if match is None:
        return None
    if match["ip6"] is not None:
        address = _address(match["ip6"])
        if not isinstance(address, ipaddress.IPv6Address):
            return None
        name, port = str(address), match["port6"]
    else:
        name, port = match["name"].lower(), match["port"]
        address = _address(name)
        if address is not None:
            name = str(address)
        elif len(name) > 253 or not _NAME.fullmatch(name):
            return None
    if port is not None and not 1 <= int(port) <= 65535:
        return None
    return name, None if port is None else int(port)


def parse_allowed_host(value: str) -> tuple[str, int | None]:
    """``--allowed-host NAME`` or ``NAME:PORT`` (an IPv6 address bare, or in brackets with a port)
    as ``(name, port)``, the port None for the server's own; InputError when it is neither."""
    address = _address(value)
    parsed = (str(address), None) if isinstance(address, ipaddress.IPv6Address) else split_host(value)
    if parsed is None:
        raise InputError(f"--allowed-host {value!r}: expected a host name or address, optionally with :PORT in "
                         f"1..65535 (e.g. lab-pc.local or lab-pc.local:8000)")
    return parsed


class HostPolicy:
    """The hosts a server on ``host`` (the ``--host`` given), bound to ``bound`` (its socket's
    address and port), answers for; ``allowed`` adds ``(name, port)`` pairs from
    :func:`parse_allowed_host` (port None: the server's)."""

    def __init__(self, host: str, bound: tuple, allowed: Iterable[tuple[str, int | None]] = ()):
        self.port = int(bound[1])
        self.names: set[tuple[str, int]] = {(name, self.port if port is None else port) for name, port in allowed}
        for name in (host, str(bound[0])):
            parsed = split_host(f"[{name}]" if ":" in name else name)
            address = None if parsed is None else _address(parsed[0])
            if parsed is not None and not (address is not None and address.is_unspecified):
                self.names.add((parsed[0], self.port))

    def allows(self, host: str | None, arrived: str | None) -> bool:
        """Whether a request whose ``Host`` is ``host`` (None: none sent) that arrived on the
        local address ``arrived`` is for this server."""
        parsed = None if host is None else split_host(host)
        if parsed is None:
            return False
        name, port = parsed[0], 80 if parsed[1] is None else parsed[1]
        if (name, port) in self.names:
            return True
        if port != self.port or arrived is None:
            return False
        local = _address(arrived)
        if local is not None and name == str(local):
            return True
        address = _address(name)
        return local is not None and local.is_loopback and (name == "localhost" or (address is not None
                                                                                   and address.is_loopback))

    def allows_origin(self, origin: str | None, arrived: str | None) -> bool:
        """Whether a WebSocket's ``Origin`` (None: not sent, as by a non-browser client) is a page
        of this server: ``http://`` and a host :meth:`allows`."""
        if origin is None:
            return True
        scheme, _, rest = origin.partition("://")
        return scheme.lower() == "http" and self.allows(rest, arrived)


class HostCheck:
    """ASGI middleware refusing every HTTP request and WebSocket that ``policy`` does not allow
    (module docstring), before ``app`` sees it."""

    def __init__(self, app: ASGIApp, policy: HostPolicy):
        self.app, self.policy = app, policy

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] in ("http", "websocket"):
            hosts = [value for name, value in scope["headers"] if name == b"host"]
            host = hosts[0].decode("latin-1") if len(hosts) == 1 else None
            arrived = (scope.get("server") or (None,))[0]
            allowed = self.policy.allows(host, arrived)
            if scope["type"] == "websocket":
                origins = [value for name, value in scope["headers"] if name == b"origin"]
                allowed = allowed and len(origins) <= 1 and self.policy.allows_origin(
                    origins[0].decode("latin-1") if origins else None, arrived)
                if not allowed:
                    await send({"type": "websocket.close", "code": REFUSED_CLOSE_CODE})
                    return
            elif not allowed:
                shown = repr(host) if host is None or len(host) <= 80 else repr(host[:77] + "...")
                await PlainTextResponse(f"refused: Host {shown} is not this server (open the address the server "
                                        f"printed, or start it with --allowed-host NAME)\n", status_code=400)(
                    scope, receive, send)
                return
        await self.app(scope, receive, send)
