"""Human–human rooms against a real server (uvicorn, the app, WebSocket clients): two pages in one
room drive a trial of the study protocol and record it with both participants and the session;
the protocol's rounds; tokens, the server's key off loopback and the Origin check; a bounded
flood of pages and messages, a driver who disconnects, and `stats` on the folder."""

import json
import urllib.error
import urllib.request
from contextlib import ExitStack

import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from helpers_web import client, drive_server, lane_change_steer, receive, send, ws_url
from trafficweaving.cli import main
from trafficweaving.data.trials import load_trials
from trafficweaving.scenario import MIN_TRIAL_STEPS, study_initial_conditions
from trafficweaving.web.app import BUSY_CLOSE_CODE
from trafficweaving.web.study import ROUND, StudySchedule

IC = 4  # car A left at 29 m/s, car B right at 27 m/s 6 m ahead: A passes, then both swap


def controls(seq, car, throttle=0.0, brake=0.0, steer=0.0):
    return {"type": "controls", "seq": seq, "car": car, "throttle": throttle, "brake": brake, "steer": steer}


def next_of(ws, kind):
    """The next message of type ``kind`` (others skipped)."""
    while (message := receive(ws))["type"] != kind:
        pass
    return message


def join_query(room_message) -> str:
    return "?" + room_message["join"].split("?", 1)[1]


# ---------------------------------------------------------------- the protocol, without a server
def test_the_protocol_plays_rounds_of_the_18_starts_and_swaps_the_cars_every_round():
    schedule = StudySchedule(seed=5)
    played, seats = [], []
    for _ in range(2 * ROUND):
        played.append(schedule.next_initial_condition())
        seats.append(schedule.seats())
        schedule.advance()
    assert sorted(played[:ROUND]) == sorted(played[ROUND:]) == list(range(len(study_initial_conditions())))
    assert played[:ROUND] != played[ROUND:]  # each round its own order
    assert set(seats[:ROUND]) == {(0, 1)} and set(seats[ROUND:]) == {(1, 0)}
    assert schedule.progress() == {"round": 2, "position": 0, "done": 2 * ROUND,
                                   "next_initial_condition": int(schedule.order(2)[0]), "seats": [0, 1]}
    assert StudySchedule(seed=5).order(0).tolist() == schedule.order(0).tolist()
    assert StudySchedule(seed=6).order(0).tolist() != schedule.order(0).tolist()


# ---------------------------------------------------------------- two pages, one room
@pytest.mark.slow
def test_two_pages_drive_a_protocol_trial_in_one_room(tmp_path):
    with drive_server(tmp_path, mode="human-human") as url, client(url) as a:
        assert a.welcome["mode"] == "human-human" and a.welcome["seat"] == 0
        room = receive(a)
        assert room["type"] == "room" and room["seats"] == [True, False] and room["join"].startswith("/?room=")
        first_ic = room["study"]["next_initial_condition"]
        send(a, {"type": "start"})
        assert "has not joined" in next_of(a, "error")["error"]
        with client(url, join_query(room)) as b:
            assert b.welcome["seat"] == 1
            assert next_of(a, "room")["seats"] == [True, True]
            send(a, {"type": "participant", "driver": 11})
            send(b, {"type": "participant", "driver": 22})
            while next_of(b, "room")["participants"] != [11, 22]:
                pass
            send(b, {"type": "start", "drivers": [1, 2]})
            assert "participant" in next_of(b, "error")["error"]
            send(b, {"type": "start"})  # either page may start; the protocol picks the start
            started_a, started_b = next_of(a, "started"), next_of(b, "started")
            assert started_a["cars"] == [0] and started_b["cars"] == [1]  # round 0: the room's first page drives A
            assert started_a["drivers"] == [11, 22] and started_a["roles"] == ["human", "human"]
            assert started_a["initial_condition"]["index"] == first_ic
            assert (started_a["round"], started_a["position"]) == (0, 0)
            start_y = [car[1] for car in started_a["states"]]
            seq = 0
            while (message := receive(a))["type"] != "ended":
                if message["type"] != "state":
                    continue
                seq += 1
                cars, step = message["cars"], message["step"]
                send(a, controls(seq, 0, throttle=1.0, steer=lane_change_steer(cars[0], start_y[0]) if step > 8 else 0))
                send(b, controls(seq, 1, brake=0.5 if step < 12 else 0.0,
                                 steer=lane_change_steer(cars[1], start_y[1]) if step > 15 else 0.0))
                if step == 3:
                    send(b, controls(10**6, 0, throttle=1.0))  # car A is the other page's
            assert "driven by the other page" in next_of(b, "error")["error"]
            assert next_of(b, "ended") == message
            assert message["reason"] in ("finished", "collision", "off_road"), message
            progress = next_of(a, "room")["study"]
            assert progress["done"] == 1 and progress["position"] == 1

    trials = load_trials(message["file"])
    assert list(trials.roles[0]) == ["human", "human"] and list(trials.drivers[0]) == [11, 22]
    np.testing.assert_allclose(trials.states[0, :, 0], study_initial_conditions()[first_ic].start_states())
    record = trials.metadata["drive"]
    assert record["room"] == {"number": room["room"], "session": room["session"], "participants": [11, 22],
                              "seats": [0, 1], "round": 0, "position": 0}
    assert set(record["controls"]["log"]) == {"0", "1"}
    assert "token" not in json.dumps(record) and room["join"].split("token=")[1] not in json.dumps(record)


# ---------------------------------------------------------------- who may come in
def test_a_room_needs_its_token_and_the_page_its_origin(tmp_path):
    with drive_server(tmp_path, mode="human-human") as url, client(url) as a:
        room = receive(a)
        number, token = room["room"], room["join"].split("token=")[1]
        for query in (f"?room={number}", f"?room={number}&token={'x' * len(token)}", f"?room=99&token={token}",
                      f"?token={token}", f"?room=1e9&token={token}", f"?room=%C2%B2&token={token}"):
            with pytest.raises(InvalidStatus) as refused:
                connect(ws_url(url) + query, open_timeout=5)
            assert refused.value.response.status_code == 403, query
        with pytest.raises(InvalidStatus):
            connect(ws_url(url) + join_query(room), origin="http://evil.example", open_timeout=5)
        with pytest.raises(InvalidStatus):
            connect(ws_url(url), origin="http://evil.example", open_timeout=5)
        with client(url, join_query(room)) as b:
            assert b.welcome["seat"] == 1
            with connect(ws_url(url) + join_query(room), open_timeout=5) as third:  # a full room: told, closed
                assert "is full" in receive(third)["error"]
                with pytest.raises(ConnectionClosed) as closed:
                    third.recv(timeout=5)
                assert closed.value.rcvd.code == BUSY_CLOSE_CODE


@pytest.mark.slow
def test_off_loopback_every_request_needs_the_key_or_a_rooms_token(tmp_path):
    with drive_server(tmp_path, mode="human-human", host="0.0.0.0") as url:
        assert "?key=" in url
        base, key_query = url.split("?")
        local = base.replace("0.0.0.0", "127.0.0.1")
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(local, timeout=10)
        assert refused.value.code == 403
        assert b"<canvas" in urllib.request.urlopen(f"{local}?{key_query}", timeout=10).read()
        with pytest.raises(InvalidStatus) as refused:
            connect(ws_url(local), open_timeout=5)  # creating a room without the key
        assert refused.value.response.status_code == 403
        with pytest.raises(InvalidStatus):
            connect(ws_url(local) + "?key=wrong", open_timeout=5)
        with client(local, f"?{key_query}") as a:
            room = receive(a)
            assert b"<canvas" in urllib.request.urlopen(local + join_query(room), timeout=10).read()
            with pytest.raises(InvalidStatus):
                connect(ws_url(local) + join_query(room)[:-2], open_timeout=5)
            with client(local, join_query(room)) as b:  # the join link alone lets the second driver in
                assert b.welcome["seat"] == 1


# ---------------------------------------------------------------- floods and a driver gone
@pytest.mark.slow
def test_a_flood_and_a_lost_driver_end_only_their_own_trial_and_stats_shows_the_pairs(tmp_path, capsys):
    with drive_server(tmp_path, mode="human-human", max_rooms=2) as url, ExitStack() as pages:
        a1 = pages.enter_context(client(url))
        b1 = pages.enter_context(client(url, join_query(receive(a1))))
        a2 = pages.enter_context(client(url))
        room2 = receive(a2)
        pages.enter_context(client(url, join_query(room2)))
        with connect(ws_url(url), open_timeout=5) as third_room:  # a bounded number of rooms
            assert "server is full" in receive(third_room)["error"]
            with pytest.raises(ConnectionClosed) as closed:
                third_room.recv(timeout=5)
            assert closed.value.rcvd.code == BUSY_CLOSE_CODE

        send(a2, {"type": "start", "initial_condition": 0})  # room 2: nobody touches the controls
        send(a1, {"type": "start", "initial_condition": IC})
        assert next_of(a1, "started")["cars"] == [0]
        send(a1, controls(1, 0, throttle=1.0))  # one message, then silence: the car keeps it
        refused = 0
        for k in range(1000):  # the other page floods its room
            send(b1, controls(k + 1, 1, steer=0.1) if k % 2 else "{not json")
            refused += k % 2 == 0
        while next_of(a1, "state")["step"] < MIN_TRIAL_STEPS + 5:
            pass
        errors = 0
        while True:
            message = receive(b1)
            if message["type"] == "error":
                errors += 1
            if message["type"] == "state" and errors == refused:
                break
        b1.close()  # a driver closes the tab: the trial ends for both, recorded, and the room says so
        ended = next_of(a1, "ended")
        assert ended["reason"] == "disconnected" and ended["file"]
        while next_of(a1, "room")["seats"] != [True, False]:
            pass
        other = next_of(a2, "ended")
        assert other["reason"] == "finished"

    lost = load_trials(ended["file"]).metadata["drive"]
    assert lost["reason"] == "disconnected" and lost["room"]["round"] is None  # a chosen start: off the protocol
    assert all(used == [1.0, 0.0, 0.0] for used in lost["controls"]["log"]["0"][1:])  # the last controls held
    calm = load_trials(other["file"]).metadata["drive"]
    assert calm["step_period"]["steps"] == other["steps"] - 1 and 0.09 < calm["step_period"]["mean_s"] < 0.13

    # stats on the folder: trials per pair (room session), the aborted one, Table I so far
    assert main(["stats", str(tmp_path), "--json"]) == 0
    stats = json.loads(capsys.readouterr().out)
    assert stats["files"] == 2 and stats["completed"] == 1 and stats["aborted"] == 1
    pairs = {pair["session"]: pair for pair in stats["pairs"]}
    assert (pairs[lost["room"]["session"]]["trials"], pairs[lost["room"]["session"]]["aborted"]) == (1, 1)
    calm_pair = pairs[room2["session"]]
    assert (calm_pair["trials"], calm_pair["completed"], calm_pair["aborted"], calm_pair["rounds"]) == (1, 1, 0, 0)
    assert calm_pair["mode"] == "human-human" and calm_pair["participants"] == [None, None]
    assert stats["human_human_completed"] == 1  # Table I so far: the completed trial alone
    assert sum(n for cells in stats["table1_counts"].values() for n in cells.values()) == 1
    assert main(["stats", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert room2["session"] in text and "Table I so far" in text
    (tmp_path / "empty").mkdir()
    assert main(["stats", str(tmp_path / "empty")]) == 2
    assert "no recorded trials" in capsys.readouterr().err
