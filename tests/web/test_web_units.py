"""The browser drive's parts without a server: the control mapping and its limits, the person as
an agent, the client-message checks, one trial's end rule and record, the recorder, the CLI."""

import json
import socket

import numpy as np
import pytest

from trafficweaving.cli import main
from trafficweaving.data.trials import load_trials
from trafficweaving.scenario import DT, LANE_CENTRE_Y, MIN_TRIAL_STEPS, study_initial_conditions
from trafficweaving.sim.world import World
from trafficweaving.web.controls import ControlLimits, ControlMapper, Controls
from trafficweaving.web.person import PersonAgent
from trafficweaving.web.protocol import MAX_MESSAGE_BYTES, Abort, ControlsMessage, ProtocolError, Start, parse
from trafficweaving.web.recording import Recorder
from trafficweaving.web.trial import Trial, TrialSetup

LIMITS = ControlLimits()
CRUISE = np.array([-100.0, LANE_CENTRE_Y["right"], 29.0, 0.0, 0.0, 0.0])


def drive_alone(controls_at, steps, start=CRUISE):
    """One car driven by a person whose controls at step t are ``controls_at(t, state)``, in the
    world (trapezoid rule); its states ``[steps + 1, 6]``."""
    person = PersonAgent(LIMITS)
    other = np.array([-300.0, LANE_CENTRE_Y["left"], 29.0, 0.0, 0.0, 0.0])
    world = World(np.stack([start, other])[None], max_steps=steps + 1)
    person.reset(np.random.default_rng(0), world.states[:, :, 0], 0)
    for t in range(steps):
        person.controls = controls_at(t, world.history[0, 0, -1])
        world.step(np.stack([person.act(world.history), np.zeros((1, 2))], axis=1))
    return world.history[0, 0], person


# ---------------------------------------------------------------- controls
def test_pedals_ramp_to_their_limits_through_the_lag():
    states, _ = drive_alone(lambda t, s: Controls(throttle=1.0), 40)
    xdd = states[1:, 4]
    assert 0 < xdd[0] < 0.5 * (LIMITS.max_accel - LIMITS.coast_decel)  # smoothed: no step
    assert np.all(np.diff(xdd) >= 0)
    assert xdd[-1] == pytest.approx(LIMITS.max_accel - LIMITS.coast_decel, abs=1e-3)
    released, _ = drive_alone(lambda t, s: Controls(), 40)
    assert released[-1, 4] == pytest.approx(-LIMITS.coast_decel, abs=1e-3)


def test_brakes_stop_the_car_and_never_reverse_it():
    states, _ = drive_alone(lambda t, s: Controls(brake=1.0), 80)
    assert states[:, 2].min() >= -1e-9
    assert states[-1, 2] == pytest.approx(0.0, abs=1e-6)
    assert states[:, 4].min() >= -LIMITS.max_brake - LIMITS.coast_decel - 1e-9


def test_steering_sets_the_lateral_speed_within_the_limits_and_recentring_straightens():
    def controls(t, state):
        return Controls(steer=-1.0 if t < 25 else 0.0)  # full left for 2.5 s, then centred

    states, _ = drive_alone(controls, 50)
    yd, ydd = states[:, 3], states[:, 5]
    assert np.abs(ydd).max() <= LIMITS.max_lateral_accel + 1e-9
    assert yd[25] == pytest.approx(LIMITS.max_lateral_speed, abs=0.05)  # left is +y
    assert yd.max() < 1.1 * LIMITS.max_lateral_speed  # the lag overshoots a little
    assert abs(yd[-1]) < 0.05  # straight again


def test_a_lane_change_takes_a_few_seconds():
    left = LANE_CENTRE_Y["left"]

    def controls(t, state):  # steer left until across the divider, then let go
        return Controls(steer=-1.0 if state[1] < left - 2.0 else 0.0)

    states, _ = drive_alone(controls, 40)
    reached = np.flatnonzero(states[:, 1] > left - 0.5)[0] * DT
    assert 1.5 < reached < 4.0
    assert abs(states[-1, 1] - left) < 0.5 and states[:, 1].max() < -1.0  # into the lane, on the road


def test_the_mapper_smooths_from_the_cars_present_acceleration():
    mapper = ControlMapper(LIMITS)
    mapper.reset(np.array([0.0, 0.0, 30.0, 0.0, -2.0, 0.0]))
    first = mapper.step(Controls(), np.array([0.0, 0.0, 30.0, 0.0, -2.0, 0.0]))
    assert -2.0 < first[0] < -LIMITS.coast_decel


def test_the_person_agent_logs_the_controls_each_step_used():
    states, person = drive_alone(lambda t, s: Controls(throttle=0.25 * (t % 4), steer=0.1), 8)
    assert [c.throttle for c in person.log] == [0.0, 0.25, 0.5, 0.75] * 2


# ---------------------------------------------------------------- client messages
def test_good_messages_parse():
    assert parse('{"type": "abort"}') == Abort()
    assert parse(json.dumps({"type": "start"})) == Start(None, None, None)
    assert parse(json.dumps({"type": "start", "initial_condition": 17, "robot_car": 1, "drivers": [5]})) == \
        Start(17, 1, (5,))
    message = parse(json.dumps({"type": "controls", "seq": 3, "car": 1, "throttle": 1, "brake": 0.5, "steer": -1}))
    assert message == ControlsMessage(3, 1, Controls(1.0, 0.5, -1.0))


@pytest.mark.parametrize("text, words", [
    ("", "JSON"),
    ("{", "JSON"),
    ("null", "object"),
    ('{"type": 1}', "type"),
    ('{"type": "abort", "now": true}', "unknown field"),
    ('{"type": "controls", "seq": 1, "car": 1, "throttle": NaN, "brake": 0, "steer": 0}', "NaN"),
    ('{"type": "controls", "seq": 1, "car": 1, "throttle": -Infinity, "brake": 0, "steer": 0}', "Infinity"),
    ('{"type": "controls", "seq": 1, "car": 1, "throttle": 0, "brake": 2e308, "steer": 0}', "brake"),
    ('{"type": "controls", "seq": 1, "car": 1, "throttle": 0, "brake": false, "steer": 0}', "brake"),
    ('{"type": "controls", "seq": 1, "car": 1, "throttle": 0, "brake": 0, "steer": 1.0001}', "steer"),
    ('{"type": "controls", "seq": 1, "car": "1", "throttle": 0, "brake": 0, "steer": 0}', "car"),
    ('{"type": "controls", "seq": 9007199254740993, "car": 1, "throttle": 0, "brake": 0, "steer": 0}', "seq"),
    ('{"type": "controls", "car": 1, "throttle": 0, "brake": 0, "steer": 0}', "seq must be"),
    ('{"type": "start", "initial_condition": -1}', "initial_condition"),
    ('{"type": "start", "robot_car": 0.0}', "robot_car"),
    ('{"type": "start", "drivers": [1, 2, 3]}', "drivers"),
    ('{"type": "start", "drivers": [2147483648]}', "drivers"),
    ("[" * 500 + "]" * 500, "object"),
])
def test_bad_messages_are_refused_with_a_reason(text, words):
    with pytest.raises(ProtocolError, match=words):
        parse(text)


def test_size_and_frame_kind_limits():
    padded = json.dumps({"type": "abort", "x": "y" * MAX_MESSAGE_BYTES})
    with pytest.raises(ProtocolError, match=f"at most {MAX_MESSAGE_BYTES}"):
        parse(padded)
    with pytest.raises(ProtocolError, match=f"at most {MAX_MESSAGE_BYTES}"):
        parse('{"type": "abort"}' + " " * MAX_MESSAGE_BYTES)
    with pytest.raises(ProtocolError, match="binary"):
        parse(b'{"type": "abort"}')
    with pytest.raises(ProtocolError) as refused:
        parse('{"type": "controls", "seq": 1}')
    assert refused.value.kind == "controls"


# ---------------------------------------------------------------- one trial
def test_two_idle_people_drive_to_the_end_without_swapping(tmp_path):
    trial = Trial(5, TrialSetup("human-human", 0, None, (2, 3), 0), (PersonAgent(), PersonAgent()))
    while trial.end_reason is None:
        trial.step()
    assert trial.end_reason == "finished" and trial.recordable
    metrics = trial.metrics()
    assert metrics["outcome"] == "no_lane_swap" and metrics["swapped"] == [False, False]
    path = Recorder(tmp_path).write(trial.trial_set({"drive": {"note": "test"}}), trial.number)
    assert path.name == "drive_000005.parquet"
    trials = load_trials(path)
    assert trials.trial_ids[0] == 5 and list(trials.roles[0]) == ["human", "human"]
    assert list(trials.drivers[0]) == [2, 3] and trials.sources[0] == "drive-000005"
    ic = study_initial_conditions()[0]
    assert trials.ic_dv[0] == ic.dv_left_minus_right and trials.ic_tco[0] == ic.tco
    assert trials.metadata["drive"] == {"note": "test"}
    assert Recorder(tmp_path).next_number() == 6
    recorder = Recorder(tmp_path)  # rooms that start at once get different numbers before either writes
    assert [recorder.reserve(), recorder.reserve()] == [6, 7]


def test_a_collision_ends_the_trial_at_once():
    a, b = PersonAgent(), PersonAgent()
    same_speed = next(k for k, ic in enumerate(study_initial_conditions()) if ic.dv_ab == 0)
    trial = Trial(1, TrialSetup("human-human", same_speed, None, (-1, -1), 0), (a, b))
    a.controls, b.controls = Controls(steer=1.0), Controls(steer=-1.0)  # side by side, into each other
    while trial.end_reason is None:
        trial.step()
    assert trial.end_reason == "collision" and trial.step_index < MIN_TRIAL_STEPS
    assert not trial.recordable  # too short for the dataset format
    assert trial.metrics()["collision"]


def test_leaving_the_road_ends_the_trial():
    a, b = PersonAgent(), PersonAgent()
    trial = Trial(1, TrialSetup("human-human", 0, None, (-1, -1), 0), (a, b))
    a.controls = Controls(steer=-1.0 if trial.start[0, 1] > -4 else 1.0)  # off its own side of the road
    while trial.end_reason is None:
        trial.step()
    assert trial.end_reason == "off_road"
    trial.stop("aborted")
    assert trial.end_reason == "off_road"  # the first reason stays


# ---------------------------------------------------------------- the command
def test_drive_refuses_a_port_in_use_and_bad_options_with_one_line(capsys, tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        for args, words in (([f"--port={port}"], "is in use"),
                            (["--port=70000"], "--port"),
                            (["--mode=robot-robot"], "--mode"),
                            (["--deadline=0.5"], "--deadline"),
                            (["--model=nope.pt", "--port=0"], "nope.pt"),
                            (["--host=no.such.host.invalid"], "--host"),
                            ([f"--out={tmp_path / 'file'}"], "is a file")):
            (tmp_path / "file").write_text("")
            assert main(["drive", "--no-browser", *args]) == 2, args
            err = capsys.readouterr().err
            assert words in err and len(err.strip().splitlines()) == 1, err
