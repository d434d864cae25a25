"""Closed-loop realism (sim/realism.py, `trafficweaving realism`): the histogram likelihood, the
recording scored against itself, agents ranked on data they did or did not generate, the world
started from a recorded prefix, and the command's output and errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from trafficweaving.cli import main
from trafficweaving.scenario import CUTOFF_X, MIN_HISTORY
from trafficweaving.sim.generate import generate_trials
from trafficweaving.sim.humans import ReplayedCar, human_agent
from trafficweaving.sim.realism import (EXTENSION, FEATURES, GROUP_WEIGHTS, PSEUDOCOUNT, Feature, Streams, feature_likelihood,
                                        realism, roll_out)


@pytest.fixture(scope="module")
def trials():
    return generate_trials(6, seed=2)[0]


def fixed(spec: str):
    return lambda ids, other: [(ids, human_agent(spec, other=other))]


def test_histogram_likelihood_is_the_smoothed_bin_probability_of_the_real_value():
    feature = Feature("kinematic", 0.0, 10.0, True, "m/s", "test", bins=5)  # bins of 2 m/s, plus "did not happen"
    rolled = np.array([[[1.0, 3.0], [1.5, 3.5], [9.0, np.nan], [30.0, np.nan]]])  # [n=1, R=4, T=2]
    real = np.array([[0.5, np.nan]])  # step 1 is not scored
    cells = 6
    expected = (2 + PSEUDOCOUNT) / (4 + PSEUDOCOUNT * cells)  # two rollouts in bin 0
    np.testing.assert_allclose(feature_likelihood(real, rolled, feature), [expected])
    real = np.array([[9.9, 5.0]])  # bin 4 (9.0 and the clipped 30.0), then the empty bin 2
    both = np.sqrt((2 + PSEUDOCOUNT) / (4 + PSEUDOCOUNT * cells) * PSEUDOCOUNT / (4 + PSEUDOCOUNT * cells))
    np.testing.assert_allclose(feature_likelihood(real, rolled, feature), [both])
    once = Feature("road", 0.0, 10.0, False, "s", "test", bins=5)
    np.testing.assert_allclose(feature_likelihood(np.array([np.nan]), np.array([[np.nan, 1.0, np.nan]]), once),
                               [(2 + PSEUDOCOUNT) / (3 + PSEUDOCOUNT * cells)])  # "did not happen" is a bin


def test_the_recording_replayed_scores_as_high_as_the_histograms_allow(trials):
    streams = Streams.of(trials)
    rollouts = 4
    steps = np.minimum(np.arange(streams.states.shape[2]), streams.lengths[:, None] - 1)
    real_human = streams.states[np.arange(len(streams))[:, None], 1, steps, 4:6]
    agent = lambda ids, other: [(ids, ReplayedCar(np.repeat(real_human, rollouts, axis=0)))]  # noqa: E731
    result = realism(trials, agent, rollouts=rollouts, seed=0)
    summary = result.summary()
    best = rollouts / (rollouts + PSEUDOCOUNT * 21)  # every rollout in the real value's bin (20 bins + 1)
    assert summary["streams"] == 2 * len(trials) and summary["trials"] == len(trials)
    for name, value in summary["features"].items():
        assert value >= (best if FEATURES[name].bins == 20 else rollouts / (rollouts + PSEUDOCOUNT * 3)) - 1e-9, name
    assert summary["realism"] >= best - 1e-9 and set(summary["groups"]) == set(GROUP_WEIGHTS)
    for key in ("off_road", "collision"):
        assert summary[f"{key}_rate"] == summary[f"real_{key}_rate"]
    # a swap is judged where the car reaches the cutoff: past a recording that stops short of it
    # the rollout goes on, so only there may the replay swap where the recording had not yet
    reached = (streams.states[:, 1, :, 0] >= CUTOFF_X).any(axis=1)
    rolled_swap, real_swap = result.rolled_rates["swap"], result.real_rates["swap"]
    np.testing.assert_array_equal(rolled_swap[reached], real_swap[reached])
    assert (rolled_swap >= real_swap).all() and (~reached).any()


def test_rollouts_start_from_the_recorded_prefix_and_run_to_the_recorded_length_or_on_to_the_cutoff(trials):
    streams = Streams.of(trials)
    rolled = roll_out(streams, human_agent("constant-velocity"), 3, np.random.default_rng(0))
    assert len(rolled) == 3 * len(streams)
    np.testing.assert_array_equal(rolled.states[::3, :, :MIN_HISTORY], streams.states[:, :, :MIN_HISTORY])
    np.testing.assert_array_equal(rolled.recorded[::3], streams.lengths)
    x_end = rolled.states[np.arange(len(rolled)), 1, rolled.lengths - 1, 0]
    extended = rolled.lengths > rolled.recorded
    assert extended.any() and (rolled.lengths <= rolled.recorded + EXTENSION).all()
    assert ((x_end >= CUTOFF_X) | (rolled.lengths == rolled.recorded + EXTENSION))[extended].all()
    before = rolled.states[np.arange(len(rolled)), 1, rolled.lengths - 2, 0]
    assert (before[extended] < CUTOFF_X).all()  # it stops at the first step at the cutoff
    past = np.arange(rolled.states.shape[2])[None, :] >= rolled.lengths[:, None]
    assert np.isnan(rolled.states[:, :, :, 0][np.broadcast_to(past[:, None], rolled.states.shape[:3])]).all()
    driven = rolled.states[0, 1, MIN_HISTORY:rolled.lengths[0]]
    np.testing.assert_array_equal(driven[:, 4:6], 0.0)  # constant velocity: no acceleration
    # the other car replays its recording
    np.testing.assert_allclose(rolled.states[0, 0, :rolled.recorded[0]], streams.states[0, 0, :streams.lengths[0]], atol=1e-9)


def test_the_drivers_that_generated_the_data_are_more_realistic_than_constant_velocity(trials):
    synthetic = realism(trials, fixed("synthetic"), rollouts=8, seed=1).summary()
    constant = realism(trials, fixed("constant-velocity"), rollouts=8, seed=1).summary()
    assert synthetic["realism"] > constant["realism"] + 0.1
    assert constant["swap_rate"] == 0.0 and synthetic["swap_rate"] > 0.5
    assert synthetic["groups"]["kinematic"] > constant["groups"]["kinematic"]
    again = realism(trials, fixed("synthetic"), rollouts=8, seed=1).summary()
    assert again == synthetic  # seeded


def test_realism_command(tmp_path, capsys):
    data = tmp_path / "d.parquet"
    generate_trials(3, seed=4)[0].write_parquet(data)
    assert main(["realism", "--human", "rules", "--data", str(data), "--rollouts", "2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in ("realism", "groups", "features", "trials", "rollouts", "swap_rate", "off_road_rate", "collision_rate",
                "real_swap_rate", "real_off_road_rate", "real_collision_rate", "at_fault_collision_rate",
                "real_at_fault_collision_rate"):
        assert key in out
    assert out["trials"] == 3 and out["rollouts"] == 2 and 0.0 <= out["realism"] <= 1.0 and set(out["features"]) == set(FEATURES)
    assert main(["realism", "--data", str(data)]) == 2
    assert "needs one of --human" in capsys.readouterr().err
    assert main(["realism", "--human", "nobody", "--data", str(data)]) == 2
    assert "human 'nobody' is unknown" in capsys.readouterr().err
    assert main(["realism", "--folds", str(tmp_path), "--data", str(data)]) == 2
    assert "no fold_K.pt files" in capsys.readouterr().err


@pytest.mark.slow
def test_self_play_generates_the_study_with_a_learned_driver_in_both_cars(tmp_path, capsys):
    out = tmp_path / "self_play.parquet"
    assert main(["generate", "--trials", "2", "--drivers", "model:driver", "--seed", "1", "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["trials"] == 2 and report["drivers"] == "model:driver" and report["simulated"] >= 2
    assert main(["stats", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["trials"] == 2
    # drivers that never change lanes cannot play the study: a clear error, no file
    bad = tmp_path / "never.parquet"
    assert main(["generate", "--trials", "4", "--drivers", "constant-velocity", "--out", str(bad)]) == 2
    assert "trials simulated with drivers 'constant-velocity' were rejected (no_lane_swap" in capsys.readouterr().err and not bad.exists()
