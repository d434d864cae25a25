"""Hostile input to `simulate`, `plot-episode` and `stats DIR`: crafted episode logs and drive
recordings, output paths that cannot be written, unbounded counts, unreachable Ray addresses and
the temporary files of a killed run. Each is refused before any work with exit status 2 and one
line naming the file or option, or cleaned up."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import threading
import time
from importlib.util import find_spec
from pathlib import Path

import pytest

from trafficweaving.atomic import TEMPORARY_NAME, atomic_write, same_file
from trafficweaving.cli import main
from trafficweaving.data.trials import TrialSet, load_trials
from trafficweaving.errors import InputError
from trafficweaving.sim.batch import MAX_EPISODES, episode_path, simulate

RUN = ["--robot", "rules", "--human", "constant-velocity", "--seed", "3", "--full-budget"]


def run(capsys, *argv) -> tuple[int, str]:
    """Exit status and stderr of the command (stdout must stay empty on errors)."""
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    if code == 2:
        assert out == "" and err.count("\n") == 1 and "Traceback" not in err, err
    return code, err


def refused(capsys, *argv) -> str:
    """The one-line error of a command that must exit with status 2."""
    code, err = run(capsys, *argv)
    assert code == 2, err
    return err


@pytest.fixture(scope="module")
def logged(tmp_path_factory) -> Path:
    """A finished run of 2 cheap episodes (rules robot, constant-velocity human)."""
    out = tmp_path_factory.mktemp("run")
    simulate(2, "rules", "constant-velocity", seed=3, out=out)
    return out


def copy_run(logged: Path, tmp_path: Path) -> Path:
    out = tmp_path / "run"
    shutil.copytree(logged, out)
    return out


def edit_record(path: Path, edit) -> None:
    """Rewrite the episode log at ``path`` with ``edit(record)`` applied to its JSON record."""
    trials = load_trials(path)
    edit(trials.metadata["episode"])
    trials.write_parquet(path)


def setter(key: str, value):
    """An edit setting the dotted ``key`` of a record to ``value`` (``...``: deleting it)."""
    def edit(record):
        *parents, last = key.split(".")
        for name in parents:
            record = record[name]
        if value is ...:
            del record[last]
        else:
            record[last] = value
    return edit


# ---------------------------------------------------------------- simulate: resuming a crafted log
@pytest.mark.parametrize("key, value, message", [
    ("robot_car", ..., "robot_car missing"),
    ("robot_car", 5, "robot_car 5"),
    ("robot_car", -1, "robot_car -1"),
    ("robot_car", "x", "robot_car 'x'"),
    ("robot_car", "flip", "robot_car"),  # 0 or 1, but not the car the roles label robot
    ("initial_condition", ..., "initial_condition missing"),
    ("initial_condition.dv", "fast", "initial_condition.dv 'fast'"),
    ("initial_condition.robot_lane", 3, "initial_condition.robot_lane 3"),
    ("latencies_s", [0.1, -1], "latencies_s [0.1, -1]"),
    ("spec", ..., "has no spec"),
    ("spec.seed", -1, "seed must be an integer in 0..4294967295, got -1"),
    ("spec.colour", "red", "unknown field 'colour'"),
])
def test_resuming_a_log_with_a_malformed_record_is_refused_naming_the_file(logged, tmp_path, capsys, key, value, message):
    out = copy_run(logged, tmp_path)
    log = episode_path(out, 1)
    if value == "flip":
        value = 1 - load_trials(log).metadata["episode"]["robot_car"]
    edit_record(log, setter(key, value))
    before = log.read_bytes()
    err = refused(capsys, "simulate", "--episodes", 2, *RUN, "--out", out)
    assert f"{log}: " in err and message in err
    assert log.read_bytes() == before  # left as it was


def test_resuming_a_log_holding_two_trials_is_refused(logged, tmp_path, capsys):
    out = copy_run(logged, tmp_path)
    first = load_trials(episode_path(out, 0))
    TrialSet.concatenate([first, first]).write_parquet(episode_path(out, 0))
    err = refused(capsys, "simulate", "--episodes", 2, *RUN, "--out", out)
    assert f"{episode_path(out, 0)}: 2 trials" in err


# ---------------------------------------------------------------- simulate: outputs checked before work
@pytest.mark.parametrize("layout, culprit", [
    ("parent is a file", "is not a folder"),
    ("episodes is a file", "episodes: is a file"),
    ("summary is a folder", "summary.json: is a folder"),
    ("an episode log is a folder", "episode_000001.parquet: is a folder"),
])
def test_unwritable_outputs_are_refused_before_the_first_episode(tmp_path, capsys, layout, culprit):
    out = tmp_path / "run"
    if layout == "parent is a file":
        out.parent.joinpath("file").write_text("")
        out = tmp_path / "file" / "run"
    elif layout == "episodes is a file":
        out.mkdir()
        (out / "episodes").write_text("")
    elif layout == "summary is a folder":
        (out / "summary.json").mkdir(parents=True)
    else:
        episode_path(out, 1).mkdir(parents=True)
    err = refused(capsys, "simulate", "--episodes", 2, *RUN, "--out", out)
    assert err.startswith("trafficweaving simulate: error: --out ") and culprit in err
    assert not episode_path(out, 0).exists()  # no episode was run


# ---------------------------------------------------------------- simulate: bounded counts
def test_episodes_and_workers_are_bounded(tmp_path, capsys):
    out = tmp_path / "run"
    err = refused(capsys, "simulate", "--episodes", 10**23, *RUN, "--out", out)
    assert f"argument --episodes: expected an integer in 1..{MAX_EPISODES}, got {10**23}" in err
    err = refused(capsys, "simulate", "--episodes", 1, "--workers", 10**9, *RUN, "--out", out)
    assert f"workers must be an integer in 1..{4 * (os.cpu_count() or 1)}, got {10**9}" in err
    with pytest.raises(InputError, match=f"episodes must be an integer in 1..{MAX_EPISODES}"):
        simulate(MAX_EPISODES + 1, "rules", "constant-velocity", out=out)
    assert not out.exists()
    code = main(["simulate", "--help"])
    assert code == 0 and f"1..{MAX_EPISODES}" in capsys.readouterr().out


# ---------------------------------------------------------------- simulate: a killed run's temporary files
def test_a_resumed_run_removes_the_temporary_files_a_killed_run_left(logged, tmp_path, capsys):
    out = copy_run(logged, tmp_path)
    ended = subprocess.Popen(["true"])
    ended.wait()  # its process id is now free: a run killed with SIGKILL
    hexa = "0123456789abcdef" * 2
    stale = [out / "episodes" / f".episode_000001.parquet.{ended.pid}.{hexa}.tmp",
             out / f".summary.json.{ended.pid}.{hexa}.tmp"]
    with subprocess.Popen(["sleep", "60"]) as running:
        kept = [out / "episodes" / f".episode_000001.parquet.{running.pid}.{hexa}.tmp",  # a running process's
                out / "episodes" / f".notes.txt.{ended.pid}.{hexa}.tmp",  # not an episode's
                out / "episodes" / f"episode_000001.parquet.{ended.pid}.{hexa}.tmp"]  # not the temporary files' form
        for path in stale + kept:
            path.write_text("partial")
        try:
            assert run(capsys, "simulate", "--episodes", 2, *RUN, "--out", out, "--json")[0] == 0
        finally:
            running.kill()
    assert not any(path.exists() for path in stale) and all(path.exists() for path in kept)


def test_the_temporary_name_pattern_is_the_one_atomic_write_uses(tmp_path):
    with atomic_write(tmp_path / "episode_000003.parquet") as f:
        f.write(b"x")
        (name,) = [p.name for p in tmp_path.iterdir()]
    match = TEMPORARY_NAME.fullmatch(name)
    assert match and match["name"] == "episode_000003.parquet" and int(match["pid"]) == os.getpid()


# ---------------------------------------------------------------- simulate --engine ray --address
def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def server():
    """A TCP server on 127.0.0.1 answering each connection with ``reply`` (None: silence)."""
    listener = socket.create_server(("127.0.0.1", 0))
    state = {"reply": None, "open": []}

    def serve():
        while True:
            try:
                conn, _ = listener.accept()
            except OSError:
                return
            state["open"].append(conn)
            if state["reply"] is not None:
                conn.sendall(state["reply"])

    threading.Thread(target=serve, daemon=True).start()
    yield listener.getsockname()[1], state
    listener.close()
    for conn in state["open"]:
        conn.close()


@pytest.mark.slow
@pytest.mark.skipif(find_spec("ray") is None, reason="Ray is not installed (extra `ray`)")
def test_a_ray_address_is_checked_in_form_and_must_answer_promptly(tmp_path, capsys, server, monkeypatch):
    out = tmp_path / "run"
    base = ["simulate", "--episodes", 1, *RUN, "--engine", "ray", "--out", out, "--address"]
    err = refused(capsys, *base, "not an address")
    assert "address 'not an address' is not a Ray address (expected auto, local, HOST:PORT" in err
    assert "is not a Ray address" in refused(capsys, *base, "127.0.0.1:99999")
    began = time.monotonic()
    err = refused(capsys, *base, f"127.0.0.1:{closed_port()}")
    assert "Connection refused" in err and "answering within 5 s" in err and time.monotonic() - began < 10
    port, state = server
    state["reply"] = b"HTTP/1.0 400 Bad Request\r\n\r\n"  # something else listens there
    assert "what answers there is not a Ray cluster" in refused(capsys, *base, f"127.0.0.1:{port}")
    state["reply"] = None  # a listener that never answers
    monkeypatch.setattr("trafficweaving.sim.batch.RAY_CONNECT_TIMEOUT_S", 0.5)
    began = time.monotonic()
    err = refused(capsys, *base, f"localhost:{port}")
    assert "address 'localhost:" in err and time.monotonic() - began < 5
    assert not out.exists()


# ---------------------------------------------------------------- plot-episode
@pytest.mark.parametrize("key, value, message", [
    ("spec", ..., "the episode record has no spec"),
    ("spec", [1, 2], "the episode spec [1, 2] is not an object"),
    ("spec.colour", "red", "unknown field 'colour'"),
    ("spec.seed", -1, "seed must be an integer in 0..4294967295, got -1"),
    ("spec.budget", [0, 4, 8], "first_stage_samples must be a positive integer, got 0"),
    ("spec.budget", "large", "budget must be null or [first_stage_samples"),
    ("spec.budget", [1, 1, 10**12], "human futures a plan (expected at most"),
    ("spec.deadline", -1, "deadline must be a finite number of seconds > 0, got -1"),
    ("spec.robot", "robot9", "robot 'robot9' is unknown"),
    ("index", -3, "episode index -3"),
])
def test_plot_episode_gif_refuses_a_malformed_episode_record_naming_the_file(logged, tmp_path, capsys, key, value,
                                                                           message):
    log = tmp_path / "episode.parquet"
    shutil.copy(episode_path(logged, 0), log)
    edit_record(log, setter(key, value))
    err = refused(capsys, "plot-episode", log, "--out", tmp_path / "f.png", "--gif", tmp_path / "a.gif")
    assert f"{log}: " in err and message in err
    assert not (tmp_path / "f.png").exists() and not (tmp_path / "a.gif").exists()


def test_plot_episode_refuses_the_figure_and_the_animation_at_one_path(logged, tmp_path, capsys, monkeypatch):
    log = episode_path(logged, 0)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    for out, gif in [("same.png", "./same.png"), ("real/same.png", "link/same.png"),
                     ("real/x.png", "real/../real/x.png")]:
        err = refused(capsys, "plot-episode", log, "--out", out, "--gif", gif)
        assert f"--gif {Path(gif)}: the same file as --out" in err
    assert sorted(p.name for p in tmp_path.rglob("*.png")) == []
    (tmp_path / "real" / "fig.png").write_text("")
    os.link(tmp_path / "real" / "fig.png", tmp_path / "hard.png")
    assert same_file("real/fig.png", "hard.png") and not same_file("real/fig.png", "real/other.png")


def test_plot_episode_checks_its_outputs_and_the_animation_length_before_work(logged, tmp_path, capsys, monkeypatch):
    log = episode_path(logged, 0)
    (tmp_path / "file").write_text("")
    err = refused(capsys, "plot-episode", log, "--out", tmp_path / "file" / "f.png")
    assert "--out " in err and "is not a folder" in err
    err = refused(capsys, "plot-episode", log, "--out", tmp_path / "f.png", "--gif", tmp_path / "file" / "a.gif")
    assert "--gif " in err and "is not a folder" in err
    monkeypatch.setattr("trafficweaving.viz.episode_figures.MAX_ANIMATION_STEPS", 10)
    err = refused(capsys, "plot-episode", log, "--out", tmp_path / "f.png", "--gif", tmp_path / "a.gif")
    assert f"--gif: trial 0 of {log} has" in err and "(expected at most 10, one frame each)" in err
    assert not (tmp_path / "f.png").exists()


# ---------------------------------------------------------------- stats DIR
def recording(logged: Path, folder: Path, number: int, drive) -> Path:
    """A one-trial recording ``drive_NNNNNN.parquet`` in ``folder`` with the ``drive`` record given."""
    trials = load_trials(episode_path(logged, 0))
    trials.metadata = {} if drive is ... else {"drive": drive}
    path = folder / f"drive_{number:06d}.parquet"
    trials.write_parquet(path)
    return path


GOOD = {"mode": "human-human", "started_at": "2025-01-01T10:00:00Z", "reason": "finished",
        "room": {"session": "s1", "participants": ["p1", None], "round": 0}}


@pytest.mark.parametrize("drive, message", [
    ({**GOOD, "room": {**GOOD["room"], "session": ["a"]}}, "room.session ['a'] in the drive record"),
    ({**GOOD, "room": "lobby"}, "room 'lobby' in the drive record"),
    ({**GOOD, "room": {**GOOD["room"], "round": -1}}, "room.round -1"),
    ({**GOOD, "room": {**GOOD["room"], "participants": "p1"}}, "room.participants 'p1'"),
    ({**GOOD, "started_at": 5}, "started_at 5"),
    ({**GOOD, "reason": ["finished"]}, "reason ['finished']"),
    ([1], "drive [1] in the drive record"),
])
def test_stats_of_a_drive_folder_refuses_a_malformed_record_naming_the_file(logged, tmp_path, capsys, drive, message):
    recording(logged, tmp_path, 1, GOOD)
    recording(logged, tmp_path, 2, ...)  # made before drive records: fine
    bad = recording(logged, tmp_path, 3, drive)
    err = refused(capsys, "stats", tmp_path)
    assert f"{bad}: {message}" in err


def test_stats_of_a_drive_folder_refuses_a_dataset_of_many_trials(logged, tmp_path, capsys):
    assert run(capsys, "stats", tmp_path / "none")[0] == 2
    recording(logged, tmp_path, 1, GOOD)
    assert run(capsys, "stats", tmp_path, "--json")[0] == 0
    trials = load_trials(episode_path(logged, 0))
    TrialSet.concatenate([trials, trials]).write_parquet(tmp_path / "drive_000002.parquet")
    err = refused(capsys, "stats", tmp_path)
    assert f"{tmp_path / 'drive_000002.parquet'}: 2 trials" in err


def test_demo_trials_are_bounded(tmp_path, capsys):
    from trafficweaving.sim.generate import MAX_TRIALS

    err = refused(capsys, "demo", "--trials", 10**10, "--out", tmp_path / "demo")
    assert f"argument --trials: expected an integer in 1..{MAX_TRIALS}, got {10**10}" in err
    assert not (tmp_path / "demo").exists()


def test_demo_refuses_an_output_folder_below_a_file_before_work(tmp_path, capsys):
    (tmp_path / "afile").write_text("")
    err = refused(capsys, "demo", "--trials", 1, "--out", tmp_path / "afile" / "demo")
    assert f"--out {tmp_path / 'afile' / 'demo'}: {tmp_path / 'afile'} is not a folder" in err
    assert "simulating" not in err
