"""The drive server's WebSocket protocol, driven directly against a real server (uvicorn, the
app, the shipped model's planner): every refused message gets one error reply and the trial goes
on; a flood of 1,000 messages; a closed connection ends the trial and keeps its record; the
recorded trials load with `stats`, `evaluate` and `simulate --human replay:FILE`."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from helpers_web import client, drive_server, lane_change_steer, receive, send, ws_url
from trafficweaving.cli import main
from trafficweaving.data.trials import load_trials
from trafficweaving.scenario import MIN_TRIAL_STEPS, study_initial_conditions
from trafficweaving.web.protocol import MAX_MESSAGE_BYTES
from trafficweaving.web.server import WS_MAX_FRAME_BYTES

IC = 4  # Δv = v_left - v_right = +2 m/s, tco 3 s: car A left at 29 m/s, car B right at 27 m/s 6 m ahead


def controls(seq, car, throttle=0.0, brake=0.0, steer=0.0):
    return {"type": "controls", "seq": seq, "car": car, "throttle": throttle, "brake": brake, "steer": steer}


def refused_messages(car):
    """Messages the server must refuse, each with a word its error must contain."""
    good = controls(10**9, car)
    return [
        ("not json {", "JSON"),
        ("[1, 2, 3]", "object"),
        ('"controls"', "object"),
        ("{}", "type"),
        (json.dumps({"type": "launch"}), "type"),
        (json.dumps({**good, "throttle": "full"}), "throttle"),
        (json.dumps({**good, "steer": None}), "steer"),
        (json.dumps(good).replace('"brake": 0.0', '"brake": NaN'), "number"),
        (json.dumps(good).replace('"brake": 0.0', '"brake": Infinity'), "number"),
        (json.dumps(good).replace('"brake": 0.0', '"brake": 1e400'), "brake"),
        (json.dumps({**good, "throttle": 1.5}), "throttle"),
        (json.dumps({**good, "steer": -2}), "steer"),
        (json.dumps({**good, "car": 2}), "car"),
        (json.dumps({**good, "car": True}), "car"),
        (json.dumps({**good, "seq": -1}), "seq"),
        (json.dumps({**good, "seq": 1.5}), "seq"),
        (json.dumps({**good, "extra": 1}), "unknown field"),
        (json.dumps({k: v for k, v in good.items() if k != "steer"}), "steer"),
        (json.dumps({**good, "pad": "x" * (MAX_MESSAGE_BYTES + 10)}), "bytes"),
        (json.dumps({**good, "pad": "x" * 200_000}), "bytes"),
        (b"\x00\x01binary", "binary"),
        (json.dumps({"type": "start", "initial_condition": 18}), "initial_condition"),
        (json.dumps({"type": "start", "drivers": "me"}), "drivers"),
    ]


def drive_to_the_end(ws, car, start_y, seq):
    """Answer every state with a scripted lane change (full throttle for a while) until the trial
    ends; returns (ended message, errors received, states seen, last seq)."""
    errors, states = [], []
    while True:
        message = receive(ws)
        if message["type"] == "error":
            errors.append(message)
        elif message["type"] == "state":
            states.append(message)
            me = message["cars"][car]
            seq += 1
            send(ws, controls(seq, car, throttle=1.0 if message["step"] < 20 else 0.2,
                              steer=lane_change_steer(me, start_y)))
        elif message["type"] == "ended":
            return message, errors, states, seq


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    out = tmp_path_factory.mktemp("drives")
    with drive_server(out) as url:
        yield url, out


@pytest.mark.slow
def test_the_page_and_its_files_are_served(server):
    import urllib.request

    url, _ = server
    page = urllib.request.urlopen(url, timeout=10).read().decode()
    assert "<canvas" in page and "http" not in page.replace(url, "").split("<body")[1]
    for name in ("drive", "draw", "input", "connection"):
        assert f"/static/{name}.js" in page
    script = urllib.request.urlopen(url + "static/connection.js", timeout=10).read().decode()
    assert "new WebSocket" in script


@pytest.mark.slow
def test_refused_messages_get_one_error_each_and_the_trial_goes_on(server):
    url, out = server
    with client(url) as ws:
        welcome = ws.welcome
        assert welcome["mode"] == "robot" and len(welcome["initial_conditions"]) == 18
        assert welcome["scenario"]["speed_alert"] == 38.0

        # out of order: nothing runs yet
        for message in (controls(1, 1), {"type": "abort"}):
            send(ws, message)
            reply = receive(ws)
            assert reply["type"] == "error" and "start first" in reply["error"]
        for text, word in refused_messages(car=1):
            send(ws, text)
            reply = receive(ws)
            assert reply["type"] == "error" and word.lower() in reply["error"].lower(), (text[:60], reply)

        send(ws, {"type": "start", "initial_condition": IC, "robot_car": 0, "drivers": [7]})
        started = receive(ws)
        assert started["type"] == "started" and started["roles"] == ["robot", "human"] and started["drivers"] == [-1, 7]
        start_y = started["states"][1][1]
        assert receive(ws)["type"] == "go"

        # a flood of 1,000 messages while the trial runs: three in four valid, the rest refused
        bad = refused_messages(car=1) + [(json.dumps(controls(10**9, 0)), "robot"),
                                         (json.dumps({"type": "start"}), "running")]
        seq, expected_errors = 0, 0
        for k in range(1000):
            if k % 4 == 3:
                send(ws, bad[(k // 4) % len(bad)][0])
                expected_errors += 1
            else:
                seq += 1
                send(ws, controls(seq, 1, throttle=1.0, steer=0.0))
        send(ws, controls(seq, 1))  # the same seq again: out of order
        expected_errors += 1

        ended, errors, states, seq = drive_to_the_end(ws, 1, start_y, seq)
        assert len(errors) == expected_errors  # (the answer to the last state, after the end, is ignored)
        assert all(e["type"] == "error" and e["error"] for e in errors)
        assert ended["reason"] in ("finished", "collision"), ended  # the planner is not perfect
        steps = [s["step"] for s in states]
        assert steps == sorted(set(steps)) and steps[-1] == ended["steps"] - 1  # in order, to the end
        assert states[-1]["planner"]["plans"] >= 10

    trials = load_trials(ended["file"])
    assert len(trials) == 1 and trials.lengths[0] == ended["steps"] >= MIN_TRIAL_STEPS
    assert list(trials.roles[0]) == ["robot", "human"] and list(trials.drivers[0]) == [-1, 7]
    ic = study_initial_conditions()[IC]
    np.testing.assert_allclose(trials.states[0, :, 0], ic.start_states())
    assert trials.ic_dv[0] == ic.dv_left_minus_right and trials.ic_tco[0] == ic.tco
    record = trials.metadata["drive"]
    assert record["reason"] == ended["reason"] and record["metrics"] == ended["metrics"]
    assert record["metrics"]["human_swapped"] or ended["reason"] == "collision"  # the scripted driver changed lanes
    assert len(record["controls"]["log"]["1"]) == ended["steps"] - 1
    assert all(used[0] == 1.0 for used in record["controls"]["log"]["1"][1:15])  # full throttle, as sent
    planner = record["planner"]
    assert len(planner["plans"]) >= 10 and planner["latency"]["plans"] == len(planner["latencies_s"])
    assert record["step_period"]["steps"] == ended["steps"] - 1
    assert 0.09 < record["step_period"]["mean_s"] < 0.13
    # the robot executed its plans: each plan's window 0 is the window the previous plan chose
    for previous, current in zip(planner["plans"], planner["plans"][1:]):
        if current["step"] == previous["step"] + 3:
            assert current["actions"][0] == previous["actions"][1]


@pytest.mark.slow
def test_a_closed_connection_ends_the_trial_and_keeps_what_was_recorded(server):
    url, out = server
    with client(url) as ws:
        send(ws, {"type": "start", "initial_condition": IC, "robot_car": 1})
        started = receive(ws)
        steps = 0
        while steps < MIN_TRIAL_STEPS + 5:
            message = receive(ws)
            if message["type"] == "state":
                steps = message["step"]
                send(ws, controls(steps, 0, throttle=0.5))
        # a frame over the server's limit (1 MiB) closes the connection, like a closed tab
        send(ws, "x" * (WS_MAX_FRAME_BYTES + 1))
        with pytest.raises(ConnectionClosed) as closed:
            while True:
                receive(ws)
        assert closed.value.rcvd.code == 1009
    # the page went away mid-trial; the next page gets the planner (at once, or once the server has
    # seen the page go) and finds the record
    with client(url) as ws:
        send(ws, {"type": "start", "initial_condition": 0, "robot_car": 0})
        while (message := receive(ws))["type"] == "queued":
            assert message["position"] == 1
        assert message["type"] == "started"
        send(ws, {"type": "abort"})
        while (message := receive(ws))["type"] != "ended":
            pass
        assert message["reason"] == "aborted" and message["file"] is None and "not recorded" in message["note"]
    path = out / f"drive_{started['trial']:06d}.parquet"
    trials = load_trials(path)
    record = trials.metadata["drive"]
    assert record["reason"] == "disconnected" and trials.lengths[0] >= MIN_TRIAL_STEPS + 5
    assert list(trials.roles[0]) == ["human", "robot"]


@pytest.mark.slow
def test_a_second_page_waits_for_the_planner_in_a_queue(server):
    url, _ = server
    with client(url) as first, client(url) as second, client(url) as third:
        send(first, {"type": "start", "initial_condition": IC, "robot_car": 0})
        assert receive(first)["type"] == "started"
        send(second, {"type": "start", "initial_condition": IC, "robot_car": 0})
        assert receive(second) == {"type": "queued", "position": 1}
        send(third, {"type": "start", "initial_condition": IC, "robot_car": 0})
        assert receive(third) == {"type": "queued", "position": 2}
        assert receive(second) == {"type": "queued", "position": 1}  # told again when the queue changed
        send(second, {"type": "controls", "seq": 1, "car": 1, "throttle": 0, "brake": 0, "steer": 0})
        assert "start first" in receive(second)["error"]  # no trial yet while queued
        send(second, {"type": "abort"})  # leaves the queue
        left = receive(second)
        assert left["type"] == "ended" and left["trial"] is None and "queue" in left["note"]
        assert receive(third) == {"type": "queued", "position": 1}
        send(first, {"type": "abort"})
        while receive(first)["type"] != "ended":
            pass
        started = receive(third)  # the planner's turn passed to the next page waiting
        assert started["type"] == "started" and started["roles"] == ["robot", "human"] and started["cars"] == [1]
        send(third, {"type": "abort"})
        while receive(third)["type"] != "ended":
            pass


def test_a_page_from_another_origin_is_refused(server):
    url, _ = server
    with pytest.raises(InvalidStatus):
        connect(ws_url(url), origin="http://evil.example", open_timeout=5)


def _cli(capsys, *args):
    code = main(list(args))
    out, err = capsys.readouterr()
    assert code == 0, err
    return json.loads(out)


@pytest.mark.slow
def test_recorded_trials_load_with_stats_evaluate_and_simulate(server, tmp_path, capsys):
    url, out = server
    files = sorted(out.glob("drive_*.parquet"))
    if not files:  # run on its own: record a trial first
        with client(url) as ws:
            send(ws, {"type": "start", "initial_condition": IC, "robot_car": 0})
            started = receive(ws)
            ended, *_ = drive_to_the_end(ws, 1, started["states"][1][1], 0)
        files = [Path(ended["file"])]
    recorded = load_trials(files[0])
    stats = _cli(capsys, "stats", str(files[0]), "--json")
    assert stats["trials"] == 1 and stats["steps"]["min"] == recorded.lengths[0]
    evaluation = _cli(capsys, "evaluate", "--model", "default", "--data", str(files[0]), "--json",
                      "--coverage-samples", "10", "--ade-samples", "5", "--samples", "10")
    assert evaluation["instances"] == recorded.lengths[0] - 19 and math.isfinite(evaluation["nll_exact"])
    summary = _cli(capsys, "simulate", "--robot", "rules", "--human", f"replay:{files[0]}", "--episodes", "1",
                   "--out", str(tmp_path / "sim"), "--json")
    assert summary["episodes"] == 1
    episode = load_trials(tmp_path / "sim" / "episodes" / "episode_000000.parquet")
    human = list(recorded.roles[0]).index("human")
    np.testing.assert_allclose(episode.states[0, 1, 0], recorded.states[0, human, 0])  # it replays the recording
