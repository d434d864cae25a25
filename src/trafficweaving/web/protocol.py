"""The WebSocket protocol between the drive page and the server, both directions: the one home of
every message, its fields, their units and when it is sent.

The page connects to the WebSocket ``/ws`` (``/ws?room=N&token=T`` joins the human–human room of a
join link; off loopback ``?key=K`` too, :mod:`.lobby`). Each message is one JSON object in one text
frame, its ``type`` first. Cars are numbered 0 (car A) and 1 (car B); a car's state is
``[x, y, xd, yd, xdd, ydd]`` (m, m/s, m/s²; ``STATE_NAMES``).

Page → server (:func:`parse` checks each one; anything else is answered with an ``error`` and
otherwise ignored):

* ``start`` (:class:`Start`), to start a trial: ``initial_condition`` 0..17 (null or absent: drawn at
  random; in a human–human room the study protocol's next one, :mod:`.study`), ``robot_car`` 0 or
  1 (the car the robot drives; null or absent: random; must be null in a human–human room),
  ``drivers`` (optional; robot rooms only) a list of one driver id, the person's: an integer in
  0..2³¹−1 or null;
* ``controls`` (:class:`ControlsMessage`), every :data:`CONTROL_INTERVAL_S` while a trial runs: the
  raw controls of the person driving car ``car``: ``throttle`` and ``brake`` in [0, 1], ``steer``
  in [-1, 1] (negative: left), ``seq`` an integer in 0..2⁵³ that increases from one message of a
  car to the next within a trial;
* ``abort`` (:class:`Abort`): end the running trial (it is recorded like any other), or leave the
  planner's queue (robot rooms);
* ``participant`` (:class:`Participant`; human–human rooms, between trials): ``driver``, the id of
  the person at this page (an integer in 0..2³¹−1, null: unknown), recorded in the ``driver``
  column of the car they drive.

A page message is at most :data:`MAX_MESSAGE_BYTES` bytes of UTF-8 text; its numbers are finite
JSON numbers (``NaN``, ``Infinity`` refused), integers are neither floats nor booleans, and it has
no keys but its type's. The room (:mod:`.room`) also refuses, the same way: ``controls`` before the
first trial, for the robot's car, for the other page's car, or with a ``seq`` not above the car's
last; ``start`` while a trial runs, or in a human–human room before the second page joined;
``abort`` without a running trial; ``participant`` in a robot room or while a trial runs.
``controls`` that arrive after a trial ended are ignored.

Server → page (built by the functions of the same names, encoded by :func:`encode`):

* :func:`welcome`, once, on connecting: the scenario, the control limits, the 18 starts and the
  limits of this protocol;
* :func:`room` (human–human rooms), whenever a page comes or goes, a participant id is set or a
  trial ends: who is in the room and the study protocol's progress;
* :func:`queued` (robot rooms), whenever the place changes while a trial waits for the planner;
* :func:`started` when a trial starts (after the wait for the planner), then :func:`countdown` once
  a second, then :func:`go`;
* :func:`state` after every step (0.1 s); skipped while the page lags behind;
* :func:`plan` (robot rooms) for each plan the robot executes, before the ``state`` of its step;
* :func:`ended` when a trial ends, or a wait for the planner is left;
* :func:`error` for each refused page message, and for a page beyond a full room or server (then
  closed with code 1013).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np

from ..scenario import (CAR_LENGTH, CAR_WIDTH, COLLISION_DX, COLLISION_DY, CUTOFF_X, DT, LANE_CENTRE_Y,
                        LANE_DIVIDER_Y, RECORD_END_X, REPLAN_PERIOD_S, ROAD_END_X, ROAD_Y_MAX, ROAD_Y_MIN,
                        SPEED_ALERT, START_X, study_initial_conditions)
from .controls import Controls

PROTOCOL_VERSION = 2
MAX_MESSAGE_BYTES = 1024
"""Largest page message accepted, bytes of UTF-8 text (a controls message is about 100)."""
MAX_SEQ = 2**53
"""Largest ``seq`` (the largest integer a JavaScript number holds exactly)."""
DRIVER_ID_MAX = 2**31 - 1
"""Largest driver id (the dataset's int32 ``driver`` column)."""
CONTROL_INTERVAL_S = 0.05
"""How often the page sends each car's controls while a trial runs, s (20 per second)."""
PLAN_FUTURES_SHOWN = 16
"""Sampled human futures of each plan sent to the page."""


# ---------------------------------------------------------------------- page → server
class ProtocolError(ValueError):
    """A page message that is refused; the message says why, in one line, and ``kind`` is the
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
    """The page message ``text`` (the WebSocket frame's text; bytes for a binary frame, None
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


# ---------------------------------------------------------------------- server → page
def encode(message: dict) -> str:
    """The text frame of a server ``message`` (non-finite floats as null: JSON has no NaN)."""
    return json.dumps(finite(message), allow_nan=False)


def finite(value):
    """``value`` (JSON-ready dicts, lists, numbers) with every non-finite float as None."""
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def welcome(mode: str, controls: dict, deadline_s: float, out: str, seat: int) -> dict:
    """``welcome``: everything the page draws and checks comes from here. ``protocol``
    (:data:`PROTOCOL_VERSION`); ``mode`` (``robot`` or ``human-human``: the server's kind of room);
    ``scenario``: ``dt`` (s), ``lane_centre_y`` (per lane), ``lane_divider_y``, ``road_y_min``,
    ``road_y_max``, ``car_length``, ``car_width``, ``road_end_x``, ``cutoff_x``, ``record_end_x``,
    ``start_x``, ``collision_dx``, ``collision_dy`` (m) and ``speed_alert`` (m/s); ``controls``: the
    person's control limits (:meth:`~.controls.ControlLimits.as_dict`); ``initial_conditions``: per
    start ``index``, ``dv_ab`` (car B's speed minus car A's, m/s), ``dv`` (left lane's minus right
    lane's, m/s), ``tco`` (s), ``lanes`` (car A's, car B's), ``states`` (``[2, 6]``); ``planning``
    (robot rooms; null otherwise): ``period_s`` and ``deadline_s`` (the planner's real-time
    deadline), s; ``limits``: ``max_message_bytes``, ``max_seq``; ``control_interval_s``
    (:data:`CONTROL_INTERVAL_S`); ``out`` (the folder trials are recorded in); ``seat`` (this
    page's, 0 or 1)."""
    ics = study_initial_conditions()
    return {
        "type": "welcome",
        "protocol": PROTOCOL_VERSION,
        "mode": mode,
        "scenario": {"dt": DT, "lane_centre_y": LANE_CENTRE_Y, "lane_divider_y": LANE_DIVIDER_Y,
                     "road_y_min": ROAD_Y_MIN, "road_y_max": ROAD_Y_MAX, "car_length": CAR_LENGTH,
                     "car_width": CAR_WIDTH, "road_end_x": ROAD_END_X, "cutoff_x": CUTOFF_X,
                     "record_end_x": RECORD_END_X, "start_x": START_X, "speed_alert": SPEED_ALERT,
                     "collision_dx": COLLISION_DX, "collision_dy": COLLISION_DY},
        "controls": controls,
        "initial_conditions": [{"index": k, "dv_ab": ic.dv_ab, "dv": ic.dv_left_minus_right + 0.0, "tco": ic.tco,
                                "lanes": [ic.lane_a, ic.lane_b], "states": ic.start_states().tolist()}
                               for k, ic in enumerate(ics)],
        "planning": None if mode != "robot" else {"period_s": REPLAN_PERIOD_S, "deadline_s": deadline_s},
        "limits": {"max_message_bytes": MAX_MESSAGE_BYTES, "max_seq": MAX_SEQ},
        "control_interval_s": CONTROL_INTERVAL_S,
        "out": out,
        "seat": seat,
    }


def room(number: int, session: str, join: str, seats: list[bool], participants: list[int | None],
         study: dict) -> dict:
    """``room`` (human–human rooms): the room's ``number``, its ``session`` id, ``join`` (the join
    link's path and query, holding the room's token), ``seats`` (whether each is taken),
    ``participants`` (the participant id per seat, null: not given) and ``study``: the protocol's
    progress (``round``, ``position``, ``done``, ``next_initial_condition``, ``seats``: the seat
    driving car A and car B; :meth:`~.study.StudySchedule.progress`)."""
    return {"type": "room", "room": number, "session": session, "join": join, "seats": seats,
            "participants": participants, "study": study}


def queued(position: int) -> dict:
    """``queued`` (robot rooms): the trial's ``position`` in the queue for the planner (1: next)."""
    return {"type": "queued", "position": position}


def started(trial: int, initial_condition: dict, robot_car: int | None, roles: list[str],
            drivers: list[int], round_: int | None, position: int | None, states: list, countdown_s: int,
            cars: list[int]) -> dict:
    """``started``: the ``trial`` number, the ``initial_condition`` (``index``, ``dv`` m/s, ``tco``
    s, ``lanes``), ``robot_car`` (null: none), each car's ``roles`` and ``drivers`` (-1: the robot
    or unknown), the trial's ``round`` and ``position`` in the study protocol (null off it), the
    start ``states`` (``[2, 6]``), ``countdown_s`` (whole seconds before the first step) and
    ``cars`` (the cars this page drives)."""
    return {"type": "started", "trial": trial, "initial_condition": initial_condition, "robot_car": robot_car,
            "roles": roles, "drivers": drivers, "round": round_, "position": position, "states": states,
            "countdown_s": countdown_s, "cars": cars}


def countdown(seconds: int) -> dict:
    """``countdown``: whole ``seconds`` left before the trial's first step."""
    return {"type": "countdown", "seconds": seconds}


def go() -> dict:
    """``go``: the countdown is over; the steps follow."""
    return {"type": "go"}


def state(step: int, cars: np.ndarray, planner: dict | None = None) -> dict:
    """``state``: the present ``step``, ``t`` (s, rounded to ms), both ``cars``' states (``[2, 6]``)
    and, in robot rooms, ``planner`` (:func:`planner_counts`)."""
    message = {"type": "state", "step": step, "t": round(step * DT, 3), "cars": cars.tolist()}
    if planner is not None:
        message["planner"] = planner
    return message


def planner_counts(plans: int, late: int, latency_s: float | None) -> dict:
    """A ``state``'s ``planner``: the ``plans`` executed, the ``late`` windows (started without
    their plan) and the last finished plan's ``latency_s`` (s; null: none yet)."""
    return {"plans": plans, "late": late, "latency_s": latency_s}


def plan(step: int, actions: np.ndarray, robot: np.ndarray, humans: np.ndarray, latency_s: float,
         futures: int) -> dict:
    """``plan`` (robot rooms), for a plan the robot executes: ``step`` (the step it was made at),
    ``actions`` (its window actions, ``[5]`` integers), ``robot`` (the robot's planned positions,
    ``[15, 2]`` of ``[x, y]``, m, from ``robot [15, 6]`` states), ``humans`` (up to
    :data:`PLAN_FUTURES_SHOWN` sampled human futures, ``[k, 15, 2]``, from ``humans [n, 15, 6]``),
    ``latency_s`` (s) and ``futures`` (the human futures it simulated)."""
    return {"type": "plan", "step": step, "actions": [int(a) for a in actions], "robot": robot[:, :2].tolist(),
            "humans": humans[:PLAN_FUTURES_SHOWN, :, :2].tolist(), "latency_s": latency_s, "futures": futures}


def ended(trial: int | None, reason: str, steps: int, metrics: dict | None, file: str | None, note: str) -> dict:
    """``ended``: the ``trial`` number (null when the page left the planner's queue before
    driving), the ``reason`` it ended (:data:`~.trial.END_REASONS`), its ``steps``, its ``metrics``
    (:meth:`~.trial.Trial.metrics`; null without two steps), the ``file`` it was recorded in (null:
    not recorded) and a one-line ``note`` saying so."""
    return {"type": "ended", "trial": trial, "reason": reason, "steps": steps, "metrics": metrics, "file": file,
            "note": note}


def error(why: str, kind: str | None) -> dict:
    """``error``: ``error``, why a page message was refused (one line), and ``for``, the refused
    message's ``type`` (null when it was not read, or for a page refused a room)."""
    return {"type": "error", "error": why, "for": kind}
