"""The drive's server → page messages, built in one module (``web/protocol.py``): the exact text of
each type (pinned), non-finite numbers sent as null, the plan and state shapes, and no message
built anywhere else in ``web/``."""

import hashlib
import json
import re
from pathlib import Path

import numpy as np

import trafficweaving.web
from trafficweaving.web import protocol
from trafficweaving.web.controls import ControlLimits

IC = {"index": 4, "dv": 2.0, "tco": 3.0, "lanes": ["left", "right"]}
STATES = [[-151.0, -1.83, 29.0, 0.0, 0.0, 0.0], [-145.0, -6.09, 27.0, 0.0, 0.0, 0.0]]
STUDY = {"round": 0, "position": 0, "done": 0, "next_initial_condition": 7, "seats": [0, 1]}


def test_welcome_is_pinned_for_both_kinds_of_room():
    limits = ControlLimits().as_dict()
    robot = protocol.encode(protocol.welcome("robot", limits, 0.25, "drives", 0))
    humans = protocol.encode(protocol.welcome("human-human", limits, 0.25, "drives", 0))
    assert hashlib.sha256(robot.encode()).hexdigest() == \
        "13f39e48302a6ac38c40d1aaccca21754b7bcaa838fb65f106a5cf7912a7ced3"
    assert hashlib.sha256(humans.encode()).hexdigest() == \
        "a15a44280fe4dbe7a01a632b25e83187a8d6c449e5964b468ee03fb3c062d065"
    message = json.loads(robot)
    assert list(message) == ["type", "protocol", "mode", "scenario", "controls", "initial_conditions", "planning",
                             "limits", "control_interval_s", "out", "seat"]
    assert message["planning"] == {"period_s": 0.3, "deadline_s": 0.25} and json.loads(humans)["planning"] is None


def test_every_other_message_is_pinned():
    pinned = [
        (protocol.started(1, IC, 0, ["robot", "human"], [-1, 7], None, None, STATES, 2, [1]),
         '{"type": "started", "trial": 1, "initial_condition": {"index": 4, "dv": 2.0, "tco": 3.0, "lanes": '
         '["left", "right"]}, "robot_car": 0, "roles": ["robot", "human"], "drivers": [-1, 7], "round": null, '
         '"position": null, "states": [[-151.0, -1.83, 29.0, 0.0, 0.0, 0.0], [-145.0, -6.09, 27.0, 0.0, 0.0, '
         '0.0]], "countdown_s": 2, "cars": [1]}'),
        (protocol.room(3, "sess3", "/?room=3&token=tok3", [True, True], [11, None], STUDY),
         '{"type": "room", "room": 3, "session": "sess3", "join": "/?room=3&token=tok3", "seats": [true, true], '
         '"participants": [11, null], "study": {"round": 0, "position": 0, "done": 0, '
         '"next_initial_condition": 7, "seats": [0, 1]}}'),
        (protocol.queued(1), '{"type": "queued", "position": 1}'),
        (protocol.countdown(2), '{"type": "countdown", "seconds": 2}'),
        (protocol.go(), '{"type": "go"}'),
        (protocol.ended(None, "aborted", 0, None, None, "left the planner's queue before driving"),
         '{"type": "ended", "trial": null, "reason": "aborted", "steps": 0, "metrics": null, "file": null, '
         '"note": "left the planner\'s queue before driving"}'),
        (protocol.error("abort without a running trial (send start first)", "abort"),
         '{"type": "error", "error": "abort without a running trial (send start first)", "for": "abort"}'),
    ]
    for message, text in pinned:
        assert protocol.encode(message) == text


def test_state_and_plan_carry_positions_in_their_documented_shapes():
    cars = np.arange(12.0).reshape(2, 6)
    state = json.loads(protocol.encode(protocol.state(7, cars, protocol.planner_counts(2, 1, float("nan")))))
    assert state == {"type": "state", "step": 7, "t": 0.7, "cars": cars.tolist(),
                     "planner": {"plans": 2, "late": 1, "latency_s": None}}  # NaN is sent as null
    assert "planner" not in protocol.state(7, cars)  # human-human rooms
    rng = np.random.default_rng(0)
    robot, humans = rng.normal(size=(15, 6)), rng.normal(size=(40, 15, 6))
    plan = protocol.plan(3, np.array([3, 5, 7, 1, 2], dtype=np.int64), robot, humans, 0.2, 1000)
    assert list(plan) == ["type", "step", "actions", "robot", "humans", "latency_s", "futures"]
    assert plan["actions"] == [3, 5, 7, 1, 2] and all(type(a) is int for a in plan["actions"])
    assert np.array_equal(plan["robot"], robot[:, :2])
    assert np.array_equal(plan["humans"], humans[:protocol.PLAN_FUTURES_SHOWN, :, :2])


def test_no_server_message_is_built_outside_the_protocol_module():
    types = "welcome|room|queued|started|countdown|go|state|plan|ended|error"
    literal = re.compile(rf"""["']type["']\s*:\s*["']({types})["']""")
    web = Path(trafficweaving.web.__file__).parent
    for path in web.glob("*.py"):
        if path.name != "protocol.py":
            assert not literal.search(path.read_text()), path.name
    assert literal.search((web / "protocol.py").read_text())
