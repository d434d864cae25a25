"""The WebSocket protocol between the page and the server: JSON text messages, one object each.

Client → server (every message is checked here; anything else is answered with an ``error``
message and otherwise ignored):

* ``{"type": "start", "initial_condition": K | null, "robot_car": C | null, "drivers": [...]}``
  starts a trial: initial condition ``K`` in 0..17 (null or absent: drawn at random), the robot
  driving car ``C`` (0 = car A, 1 = car B; null or absent: random; must be null in human–human
  mode), ``drivers`` (optional) the ids of the people driving, integers in 0..2³¹−1 or null: one
  in robot mode (the person's), two in human–human mode (car A's, car B's);
* ``{"type": "controls", "seq": N, "car": C, "throttle": T, "brake": B, "steer": S}``: the raw
  controls of the person driving car ``C``: ``throttle``, ``brake`` in [0, 1], ``steer`` in
  [-1, 1] (negative: left), ``seq`` an integer in 0..2⁵³ that increases from one message of a car
  to the next within a trial (a repeated or older ``seq`` is refused as out of order);
* ``{"type": "abort"}`` ends the running trial (it is recorded like any other), or leaves the
  planner's queue (robot mode);
* ``{"type": "participant", "driver": N | null}`` (human–human rooms): the participant id of the
  person at this page, an integer in 0..2³¹−1 (null: unknown), recorded in the ``driver`` column
  of the car they drive.

In a human–human room ``drivers`` is not sent with ``start`` (each page gives its own person's
id with ``participant``), and a null ``initial_condition`` means the study protocol's next one
(:mod:`.study`).

Limits: a message is at most :data:`MAX_MESSAGE_BYTES` bytes of UTF-8 text; numbers are finite
JSON numbers (``NaN``, ``Infinity`` are refused), integers are not floats or booleans; no keys
other than those above.

Server → client: ``welcome`` (the scenario, the control limits, the initial conditions, the
room; on connecting), ``room`` (who is in the room, the protocol's progress), ``queued`` (robot
mode: the place in the planner's queue), ``started``, ``countdown``, ``go``, ``state`` (every
step), ``plan`` (each plan the robot executes), ``ended`` (outcome, metrics, the file written) and
``error`` (:mod:`.room` builds them; ``docs/drive.md`` lists their fields).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

from ..scenario import study_initial_conditions
from .controls import Controls

PROTOCOL_VERSION = 2
MAX_MESSAGE_BYTES = 1024
"""Largest client message accepted, bytes of UTF-8 text (a controls message is about 100)."""
MAX_SEQ = 2**53
"""Largest ``seq`` (the largest integer a JavaScript number holds exactly)."""
DRIVER_ID_MAX = 2**31 - 1
"""Largest driver id (the dataset's int32 ``driver`` column)."""


class ProtocolError(ValueError):
    """A client message that is refused; the message says why, in one line, and ``kind`` is the
    refused message's ``type`` when it was read."""

    def __init__(self, message: str, kind: str | None = None):
        super().__init__(message)
        self.kind = kind


@dataclass(frozen=True)
class Start:
    """``start``: the initial condition's index and the robot's car (None: random), the people's
    driver ids (None: not given)."""

    initial_condition: int | None
    robot_car: int | None
    drivers: tuple[int | None, ...] | None


@dataclass(frozen=True)
class ControlsMessage:
    """``controls``: car ``car``'s raw controls, numbered ``seq``."""

    seq: int
    car: int
    controls: Controls


@dataclass(frozen=True)
class Abort:
    """``abort``: end the running trial."""


@dataclass(frozen=True)
class Participant:
    """``participant``: the id of the person at this page (None: unknown)."""

    driver: int | None


ClientMessage = Start | ControlsMessage | Abort | Participant
_FIELDS = {"start": {"type", "initial_condition", "robot_car", "drivers"},
           "controls": {"type", "seq", "car", "throttle", "brake", "steer"},
           "abort": {"type"},
           "participant": {"type", "driver"}}


_MISSING = object()


def _refuse_constant(name: str):
    raise ProtocolError(f"{name} is not a JSON number (expected finite numbers)")


def _integer(message: dict, key: str, low: int, high: int, nullable: bool = False) -> int | None:
    value = message.get(key, None if nullable else _MISSING)
    if value is None and nullable:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        expected = f"an integer in {low}..{high}" + (" or null" if nullable else "")
        raise ProtocolError(f"{key} must be {expected}, got {_short(value)}")
    return value


def _number(message: dict, key: str, low: float, high: float) -> float:
    value = message.get(key, _MISSING)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or not low <= value <= high:
        raise ProtocolError(f"{key} must be a number in [{low:g}, {high:g}], got {_short(value)}")
    return float(value)


def _short(value) -> str:
    """A value as JSON for a one-line message (``nothing`` when missing), at most 40 characters."""
    text = "nothing" if value is _MISSING else json.dumps(value)
    return text if len(text) <= 40 else text[:37] + "..."


def parse(text: str | bytes | None) -> ClientMessage:
    """The client message ``text`` (the WebSocket frame's text; bytes for a binary frame, None
    when it had neither), checked; :class:`ProtocolError` saying what is wrong otherwise."""
    if not isinstance(text, str):
        raise ProtocolError("expected a text message holding a JSON object, got a binary message")
    size = len(text.encode("utf-8", errors="replace"))
    if size > MAX_MESSAGE_BYTES:
        raise ProtocolError(f"message of {size} bytes (expected at most {MAX_MESSAGE_BYTES})")
    try:
        message = json.loads(text, parse_constant=_refuse_constant)
    except ProtocolError:
        raise
    except (ValueError, RecursionError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ProtocolError(f"not valid JSON ({reason})") from None
    if not isinstance(message, dict):
        raise ProtocolError(f"expected a JSON object, got a JSON {type(message).__name__}")
    kind = message.get("type")
    if kind not in _FIELDS:
        raise ProtocolError(f"type must be one of {', '.join(_FIELDS)}, got {_short(kind)}")
    try:
        return _fields(kind, message)
    except ProtocolError as exc:
        exc.kind = kind
        raise


def _fields(kind: str, message: dict) -> ClientMessage:
    """The message of ``kind`` from the JSON object ``message``, its fields checked."""
    unknown = sorted(set(message) - _FIELDS[kind])
    if unknown:
        raise ProtocolError(f"unknown field {_short(unknown[0])} in a {kind} message "
                            f"(expected only {', '.join(sorted(_FIELDS[kind]))})")
    if kind == "abort":
        return Abort()
    if kind == "participant":
        return Participant(_integer(message, "driver", 0, DRIVER_ID_MAX, nullable=True))
    if kind == "controls":
        return ControlsMessage(
            seq=_integer(message, "seq", 0, MAX_SEQ),
            car=_integer(message, "car", 0, 1),
            controls=Controls(_number(message, "throttle", 0.0, 1.0), _number(message, "brake", 0.0, 1.0),
                              _number(message, "steer", -1.0, 1.0)))
    drivers = message.get("drivers")
    if drivers is not None and (not isinstance(drivers, list) or not 1 <= len(drivers) <= 2):
        raise ProtocolError(f"drivers must be a list of 1 or 2 driver ids (integers or null), got {_short(drivers)}")
    ids = None if drivers is None else tuple(_integer({"drivers": d}, "drivers", 0, DRIVER_ID_MAX, nullable=True)
                                             for d in drivers)
    return Start(initial_condition=_integer(message, "initial_condition", 0, len(study_initial_conditions()) - 1,
                                            nullable=True),
                 robot_car=_integer(message, "robot_car", 0, 1, nullable=True),
                 drivers=ids)
