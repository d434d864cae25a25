"""Replayed drivers start where their recordings start (sim/humans.py ``replay_start``), in the
Gymnasium environment, in ``generate --drivers`` and in ``simulate``; ``generate`` refuses a run
where most trials are rejected and bounds its counts; bad ``replay:FILE#K`` and environment
arguments are one-line errors."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest

import trafficweaving  # noqa: F401  (registers the environment)
import trafficweaving.sim.generate as generate
from trafficweaving.cli import main
from trafficweaving.data.trials import load_trials
from trafficweaving.dynamics import future_states
from trafficweaving.envs.traffic_weaving import HUMAN, ROBOT, TrafficWeavingEnv
from trafficweaving.errors import InputError
from trafficweaving.scenario import check_validity, on_road
from trafficweaving.sim.episodes import EpisodeSpec, run_episode
from trafficweaving.sim.generate import MAX_PAIRS, MAX_TRIALS, generate_trials
from trafficweaving.sim.humans import human_agent, replay_start
from trafficweaving.sim.world import run_episodes

IDLE = np.zeros(2, np.float32)  # the robot's accelerations: it holds its speed and its lane


@pytest.fixture(scope="module")
def hitl_file(hitl_trials, tmp_path_factory):
    """The authors' 30 human-in-the-loop trials (robot and human) as a Parquet file."""
    path = tmp_path_factory.mktemp("hitl") / "hitl.parquet"
    hitl_trials.write_parquet(path)
    return path


def drive_idle(env: TrafficWeavingEnv, seed: int) -> tuple[np.ndarray, dict]:
    """One episode of ``env`` with an idle robot: both cars' states ``[2, t+1, 6]`` and the last info."""
    env.reset(seed=seed)
    done = False
    while not done:
        _, _, terminated, truncated, info = env.step(IDLE)
        done = terminated or truncated
    return env.world.history[0], info


def one_line_error(capsys, argv) -> str:
    code = main(argv)
    out, err = capsys.readouterr()
    assert code == 2 and out == "" and err.count("\n") == 1 and "Traceback" not in err
    return err


# ------------------------------------------------------------------ the environment
@pytest.mark.slow
def test_a_replayed_human_in_the_env_drives_its_recorded_path_and_never_leaves_the_road(hitl_file):
    trials = load_trials(hitl_file)
    for k, trial in enumerate(trials.trial_ids):
        env = TrafficWeavingEnv(human=f"replay:{hitl_file}#{trial}", action_type="continuous")
        states, info = drive_idle(env, seed=k)
        human = int(np.flatnonzero(trials.roles[k] == "human")[0])
        recorded = trials.states[k, [1 - human, human]]  # [2, T, 6]: the robot takes the other car
        np.testing.assert_array_equal(states[:, 0], recorded[:, 0])
        n = min(int(trials.lengths[k]), states.shape[1])  # the steps replayed (an episode may end first)
        np.testing.assert_array_equal(states[HUMAN, 1:n, 4:6], recorded[HUMAN, 1:n, 4:6])
        # the path the recorded controls drive from the recorded start, to numerical precision ...
        path = future_states(recorded[HUMAN, 0], recorded[HUMAN, 1:n, 4:6])
        np.testing.assert_allclose(states[HUMAN, 1:n], path, rtol=0, atol=1e-9)
        # ... which is the recording's path: its positions are integrals of its accelerations up to
        # the recorder's rounding (and one 0.47 m jump in one recording)
        assert np.abs(states[HUMAN, :n, :2] - recorded[HUMAN, :n, :2]).max() < 0.5
        assert not info["off_road"] and on_road(states[:, :, 1]).all(), f"trial {trial} left the road"


def test_a_replay_matches_a_simulated_recording_to_numerical_precision(tmp_path):
    trials, _ = generate_trials(3, seed=1)
    trials.roles[:, 0] = "robot"
    path = tmp_path / "simulated.parquet"
    trials.write_parquet(path)
    for k in range(3):
        states, _ = drive_idle(TrafficWeavingEnv(human=f"replay:{path}#{k}", action_type="continuous"), seed=k)
        n = min(int(trials.lengths[k]), states.shape[1])
        assert n > 30
        np.testing.assert_allclose(states[HUMAN, :n], trials.states[k, 1, :n], rtol=0, atol=1e-9)
        np.testing.assert_array_equal(states[ROBOT, 0], trials.states[k, 0, 0])


def test_the_env_draws_the_replayed_trial_at_reset_and_starts_from_it(hitl_file):
    trials = load_trials(hitl_file)
    env = gym.make("TrafficWeaving-v0", human=f"replay:{hitl_file}").unwrapped
    played = []
    for seed in range(12):
        observation, _ = env.reset(seed=seed)
        trial = int(env.driver.played[0])
        human = int(np.flatnonzero(trials.roles[trial] == "human")[0])
        np.testing.assert_allclose(observation, trials.states[trial, [1 - human, human], 0].reshape(-1), rtol=1e-6)
        played.append(trial)
    assert len(set(played)) > 5
    assert env.human.bound is None  # the env's own agent stays unbound; each episode replays a bound copy


def test_simulate_starts_a_replay_where_the_recording_starts(hitl_file):
    trials = load_trials(hitl_file)
    for index in (3, 33):  # the recordings in turn: episode 33 replays trial 3 again
        episode = run_episode(EpisodeSpec("rules", f"replay:{hitl_file}", seed=0), index)
        human = int(np.flatnonzero(trials.roles[3] == "human")[0])
        assert episode.record["robot_car"] == ROBOT and episode.record["initial_condition"]["trial"] == 3
        np.testing.assert_array_equal(episode.trials.states[0, :, 0], trials.states[3, [1 - human, human], 0])
        n = min(int(trials.lengths[3]), int(episode.trials.lengths[0]))
        np.testing.assert_array_equal(episode.trials.states[0, HUMAN, 1:n, 4:6], trials.states[3, human, 1:n, 4:6])


# ------------------------------------------------------------------ generate
@pytest.fixture(scope="module")
def replay_reasons(hitl_file) -> np.ndarray:
    """The validity outcome (:data:`~trafficweaving.scenario.VALIDITY_REASONS` index) of each real
    trial replayed by both cars from its start, on to the end of the road, ``[30]``."""
    cars = [human_agent(f"replay:{hitl_file}") for _ in (0, 1)]
    replay = replay_start(cars, episodes=np.arange(30))
    return check_validity(*run_episodes(replay.start, replay.cars, np.random.default_rng(0)).recorded())[0]


def test_generate_with_replay_drivers_replays_the_recordings_and_rejects_almost_none(hitl_file, replay_reasons,
                                                                                    tmp_path, capsys):
    out = tmp_path / "replays.parquet"
    assert main(["generate", "--trials", "28", "--drivers", f"replay:{hitl_file}", "--out", str(out), "--json"]) == 0
    payload = json.loads(capsys.readouterr().out)
    assert payload["simulated"] == 30 and payload["rejected"] == 2  # the real trials' recorded collision, one late swap
    assert payload["rejected_by_reason"] == {"collision": 1, "off_road": 0, "no_lane_swap": 1, "cutoff_not_reached": 0}
    assert (replay_reasons != 0).sum() == 2
    real, generated = load_trials(hitl_file), load_trials(out)
    for i, k in enumerate(np.flatnonzero(replay_reasons == 0)[:28]):
        human = int(np.flatnonzero(real.roles[k] == "human")[0])
        recorded = real.states[k, [human, 1 - human]]  # the recorded human drives car A, the other car car B
        n = min(int(generated.lengths[i]), int(real.lengths[k]))
        np.testing.assert_array_equal(generated.states[i, :, 0], recorded[:, 0])
        np.testing.assert_array_equal(generated.states[i, :, 1:n, 4:6], recorded[:, 1:n, 4:6])
        assert generated.roles[i].tolist() == real.roles[k, [human, 1 - human]].tolist()


def test_a_run_where_most_trials_are_rejected_is_refused(hitl_file, tmp_path, capsys):
    real = load_trials(hitl_file)
    collided = int(real.trial_ids[check_validity(real.states, real.lengths)[0] == 1][0])  # a recorded collision
    out = tmp_path / "x.parquet"
    err = one_line_error(capsys, ["generate", "--trials", "2", "--drivers", f"replay:{hitl_file}#{collided}",
                                  "--out", str(out), "--json"])
    assert err.startswith("trafficweaving generate: error: 21 of the 21 trials simulated with drivers")
    assert "were rejected (collision 21; expected drivers that swap lanes safely in at least 50% of trials)" in err
    assert not out.exists()


@pytest.mark.parametrize("rejected_every, refused", [(2, False), (3, True)])
def test_generate_refuses_when_more_than_half_are_rejected(monkeypatch, rejected_every, refused):
    """Every trial but one in ``rejected_every`` is rejected: a half is kept, a third is refused."""
    def check(states, lengths):
        reason, cut = check_validity(states, lengths)
        return np.where(np.arange(len(reason)) % rejected_every, 2, reason), cut
    monkeypatch.setattr(generate, "check_validity", check)
    if refused:
        with pytest.raises(ValueError, match=r"^1\d of the 21 trials simulated with drivers 'synthetic' were rejected "
                                             r"\(off_road 14.*at least 50% of trials\)$"):
            generate_trials(2, seed=0)
    else:
        trials, report = generate_trials(2, seed=0)
        assert len(trials) == 2 and report.rejected["off_road"] == 1


def test_generate_bounds_its_counts(tmp_path, capsys):
    out = str(tmp_path / "x.parquet")
    err = one_line_error(capsys, ["generate", "--trials", str(MAX_TRIALS + 1), "--out", out])
    assert f"argument --trials: expected an integer in 1..{MAX_TRIALS}, got {MAX_TRIALS + 1}" in err
    err = one_line_error(capsys, ["generate", "--pairs", str(MAX_PAIRS + 1), "--out", out])
    assert f"argument --pairs: expected an integer in 1..{MAX_PAIRS}, got {MAX_PAIRS + 1}" in err
    for kwargs in ({"n_trials": MAX_TRIALS + 1}, {"n_trials": 2, "pairs": MAX_PAIRS + 1}, {"n_trials": 2.0}):
        with pytest.raises(InputError, match="must be"):
            generate_trials(**kwargs)


# ------------------------------------------------------------------ bad specs and arguments
@pytest.mark.parametrize("suffix", ["²", "٣", "1e3", "-1", "", "99999999999", " 1"])
def test_a_bad_trial_id_is_one_line(hitl_file, tmp_path, capsys, suffix):
    spec = f"replay:{hitl_file}#{suffix}"
    with pytest.raises(InputError, match="is not a trial id .*ASCII digits"):
        gym.make("TrafficWeaving-v0", human=spec)
    err = one_line_error(capsys, ["simulate", "--episodes", "1", "--robot", "rules", "--human", spec,
                                  "--out", str(tmp_path / "run")])
    assert f"human '{spec}': no such file, and {suffix!r} after its last '#' is not a trial id" in err


@pytest.mark.parametrize("command", [["simulate", "--episodes", "1", "--robot", "rules", "--human", "replay:/dev/null"],
                                     ["stats", "/dev/null"]])
def test_a_device_file_is_named_as_not_a_regular_file(tmp_path, capsys, command):
    err = one_line_error(capsys, [*command, *(["--out", str(tmp_path / "run")] if command[0] == "simulate" else [])])
    assert "/dev/null: not a regular file (expected a trafficweaving Parquet dataset)" in err


def test_a_file_with_a_hash_in_its_name_is_a_file(hitl_trials, tmp_path):
    path = tmp_path / "trials#a" / "real#2.parquet"
    path.parent.mkdir()
    hitl_trials.write_parquet(path)
    assert gym.make("TrafficWeaving-v0", human=f"replay:{path}").unwrapped.human.trial is None
    assert gym.make("TrafficWeaving-v0", human=f"replay:{path}#7").unwrapped.human.trial == 7


@pytest.mark.parametrize("kwargs, message", [
    ({"human": None}, "human None is not a spec (expected one of: synthetic"),
    ({"human": 3}, "human 3 is not a spec"),
    ({"action_type": None}, "action_type must be 'discrete' or 'continuous', got None"),
    ({"action_type": np.array([1, 2])}, "action_type must be 'discrete' or 'continuous'"),
    ({"render_mode": 3}, "render_mode must be None or 'rgb_array', got 3"),
])
def test_environment_arguments_are_checked_at_construction(kwargs, message):
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")) as error:
        TrafficWeavingEnv(**kwargs)
    assert "\n" not in str(error.value)
    if "human" in kwargs:  # through gym.make as well (which checks render modes itself)
        with pytest.raises(InputError, match="is not a spec"):
            gym.make("TrafficWeaving-v0", **kwargs)
