"""Perturbed replays (``--human replay:FILE@T,V``, sim/humans.py ``perturbed_start``): the robot's
start shifted in time and speed by the episode's first draws, the recorded human unchanged; the
spec's parsing and its errors."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from trafficweaving.cli import main
from trafficweaving.data.trials import load_trials
from trafficweaving.envs.traffic_weaving import TrafficWeavingEnv
from trafficweaving.errors import InputError
from trafficweaving.scenario import colliding
from trafficweaving.sim.episodes import EpisodeSpec, run_episode
from trafficweaving.sim.humans import (MAX_SHIFT_S, MAX_SPEED_OFFSET_MPS, HumanSpec, ReplayDriver, check_perturbation,
                                       human_agent, parse_human_spec, replay_start)


@pytest.fixture(scope="module")
def hitl_file(hitl_trials, tmp_path_factory):
    """The authors' 30 human-in-the-loop trials (robot and human) as a Parquet file."""
    path = tmp_path_factory.mktemp("hitl") / "hitl.parquet"
    hitl_trials.write_parquet(path)
    return path


class Braking:
    """A robot that brakes at 6 m/s² from the start."""

    def reset(self, rng, start, me):
        pass

    def act(self, history):
        return np.tile([-6.0, 0.0], (len(history), 1))


def test_perturbation_specs_parse(tmp_path):
    assert parse_human_spec("replay:d.parquet@1.5,2") == HumanSpec("replay", path="d.parquet", perturbation=(1.5, 2.0))
    assert parse_human_spec("replay:d.parquet#12@0,.5") == HumanSpec("replay", path="d.parquet", trial=12,
                                                                     perturbation=(0.0, 0.5))
    assert parse_human_spec(f"replay:d@{MAX_SHIFT_S:g},{MAX_SPEED_OFFSET_MPS:g}").perturbation == (3.0, 5.0)
    odd = tmp_path / "a@1,2"  # an existing file is a FILE, '@' or not
    odd.write_bytes(b"")
    assert parse_human_spec(f"replay:{odd}") == HumanSpec("replay", path=str(odd))
    assert parse_human_spec(f"replay:{odd}@1,1") == HumanSpec("replay", path=str(odd), perturbation=(1.0, 1.0))


@pytest.mark.parametrize("tail", ["x,1", "1", "", "-1,2", "1,-2", "nan,1", "inf,1", "1e0,1", " 1,2", "1,2,3", "١,1"])
def test_a_malformed_perturbation_is_one_line(tail, tmp_path, capsys):
    spec = f"replay:{tmp_path}/d.parquet@{tail}"
    with pytest.raises(InputError) as info:
        parse_human_spec(spec)
    assert str(info.value).startswith(f"human '{spec}': no such file, and {tail!r} after its last '@' is not T,V "
                                      f"(expected replay:FILE, replay:FILE#K, replay:FILE@T,V or replay:FILE#K@T,V")
    code = main(["simulate", "--episodes", "1", "--robot", "rules", "--human", spec, "--out", str(tmp_path / "run")])
    out, err = capsys.readouterr()
    assert code == 2 and out == "" and err.count("\n") == 1 and str(info.value) in err


@pytest.mark.parametrize("tail", ["3.01,1", "1,5.5", "10,0"])
def test_a_perturbation_out_of_range_is_refused(tail):
    spec = f"replay:d.parquet#2@{tail}"
    with pytest.raises(InputError) as info:
        parse_human_spec(spec)
    assert str(info.value).startswith(f"human '{spec}': perturbation ")
    assert "out of range (expected T,V: a time shift T in 0..3 s and a speed offset V in 0..5 m/s)" in str(info.value)
    for bad in ((True, 1.0), (float("nan"), 1.0), (1.0, float("inf")), (-0.5, 1.0), ("1", 1.0)):
        with pytest.raises(InputError, match="^trials: perturbation .* is out of range"):
            check_perturbation(*bad, name="trials")


def test_the_perturbation_is_the_episodes_first_draws_whatever_the_robot(hitl_file):
    spec = EpisodeSpec("rules", f"replay:{hitl_file}@2,3", seed=4)
    plain = EpisodeSpec("rules", f"replay:{hitl_file}", seed=4)
    shifts = []
    for index in (0, 7, 31):
        ruled = run_episode(spec, index)
        braking = run_episode(spec, index, (Braking(), human_agent(spec.human)))
        start = ruled.trials.states[0, :, 0]
        np.testing.assert_array_equal(braking.trials.states[0, :, 0], start)  # the same start for every robot
        ic = ruled.record["initial_condition"]
        assert ic == braking.record["initial_condition"]
        rng = np.random.default_rng([4, index])
        assert ic["shift_s"] == rng.uniform(-2, 2) and ic["speed_offset_mps"] == rng.uniform(-3, 3)
        recorded = run_episode(plain, index)  # the recording's start
        assert {k: v for k, v in ic.items() if k not in ("shift_s", "speed_offset_mps")} == \
            recorded.record["initial_condition"]
        robot, human = recorded.trials.states[0, :, 0]
        np.testing.assert_array_equal(start[1], human)  # the recorded human starts where it did ...
        assert start[0, 0] == robot[0] + robot[2] * ic["shift_s"]  # ... the robot shifted in time ...
        assert start[0, 2] == robot[2] + ic["speed_offset_mps"]  # ... and in speed
        np.testing.assert_array_equal(start[0, [1, 3, 4, 5]], robot[[1, 3, 4, 5]])
        n = min(int(ruled.trials.lengths[0]), int(recorded.trials.lengths[0]))
        np.testing.assert_array_equal(ruled.trials.states[0, 1, :n], recorded.trials.states[0, 1, :n])  # unchanged
        assert not colliding(start[0], start[1])
        shifts.append(ic["shift_s"])
    assert len(set(shifts)) == 3


def test_zero_bounds_replay_exactly_as_the_plain_replay(hitl_file, tmp_path):
    for index in (0, 12):
        plain = run_episode(EpisodeSpec("rules", f"replay:{hitl_file}", seed=1), index)
        zero = run_episode(EpisodeSpec("rules", f"replay:{hitl_file}@0,0", seed=1), index)
        np.testing.assert_array_equal(zero.trials.states, plain.trials.states)
        assert zero.record["metrics"] == plain.record["metrics"]
        assert zero.record["initial_condition"] == {**plain.record["initial_condition"], "shift_s": 0.0,
                                                    "speed_offset_mps": 0.0}


def test_simulate_runs_a_perturbed_replay_and_resumes_it(hitl_file, tmp_path, capsys):
    argv = ["simulate", "--robot", "rules", "--human", f"replay:{hitl_file}#3@1.5,2", "--episodes", "2", "--out",
            str(tmp_path / "run"), "--json"]
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["episodes"] == 2 and summary["human"].endswith("#3@1.5,2")
    records = [load_trials(tmp_path / "run" / "episodes" / f"episode_00000{k}.parquet").metadata["episode"]
               for k in range(2)]
    assert [r["initial_condition"]["trial"] for r in records] == [3, 3]
    assert records[0]["initial_condition"]["shift_s"] != records[1]["initial_condition"]["shift_s"]
    assert main(argv) == 0 and json.loads(capsys.readouterr().out)["reused"] == 2


def test_the_environment_perturbs_the_robot_start_at_reset(hitl_file):
    plain, perturbed = (TrafficWeavingEnv(human=f"replay:{hitl_file}{tail}", action_type="continuous")
                        for tail in ("", "@1,1"))
    for seed in range(3):
        recorded, _ = plain.reset(seed=seed)
        shifted, _ = perturbed.reset(seed=seed)
        assert (shifted[6:] == recorded[6:]).all() and (shifted[[0, 2]] != recorded[[0, 2]]).all()
        again, _ = perturbed.reset(seed=seed)
        np.testing.assert_array_equal(again, shifted)


def test_a_perturbed_replay_needs_a_car_that_does_not_replay_and_cars_apart(hitl_trials):
    driver = ReplayDriver(hitl_trials, perturbation=(1.0, 1.0))
    rng = np.random.default_rng(0)
    with pytest.raises(InputError, match="every car here replays"):  # self-play: nothing to perturb
        replay_start([driver, driver], episodes=np.array([0]), rng=rng)
    states = hitl_trials.states.copy()
    states[:, :, 0, 1] = states[:, :1, 0, 1]  # both cars start in one lane, side by side
    states[:, :, 0, 0] = states[:, :1, 0, 0]
    same_lane = ReplayDriver(dataclasses.replace(hitl_trials, states=states), perturbation=(0.0, 1.0))
    with pytest.raises(InputError, match=f"trial {hitl_trials.trial_ids[2]}: the cars overlap at the perturbed start"):
        replay_start([None, same_lane], episodes=np.array([2]), rng=rng)
