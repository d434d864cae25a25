"""Tests of the marginal driving-behaviour statistics on small hand-built trial sets."""

import numpy as np
import pytest

from trafficweaving.data.behaviour import (
    HOLD_TOLERANCE,
    STATISTICS,
    behaviour_samples,
    compare_behaviour,
    format_comparison,
    hold_runs,
    lane_change_events,
)
from trafficweaving.data.trials import TrialSet
from trafficweaving.scenario import DT, LANE_CENTRE_Y, LANE_DIVIDER_Y

Y_L, Y_R = LANE_CENTRE_Y["left"], LANE_CENTRE_Y["right"]


def make_trials(states, lengths, roles=None, start_lanes=None) -> TrialSet:
    """A TrialSet from ``states[n, 2, T, 6]``; steps past ``lengths`` are set to NaN."""
    states = np.array(states, dtype=float)
    n, _, t_max, _ = states.shape
    lengths = np.asarray(lengths)
    past = np.arange(t_max)[None, :] >= lengths[:, None]  # [n, T]
    states.transpose(0, 2, 1, 3)[past] = np.nan
    if start_lanes is None:
        start_lanes = np.where(states[:, :, 0, 1] > LANE_DIVIDER_Y, "left", "right")
    return TrialSet(
        states=states, lengths=lengths, trial_ids=np.arange(n, dtype=np.int32),
        roles=np.array(roles if roles is not None else [["human", "human"]] * n),
        start_lanes=np.asarray(start_lanes), drivers=np.full((n, 2), -1, dtype=np.int32),
        ic_dv=np.full(n, np.nan), ic_tco=np.full(n, np.nan), sources=np.array(["test"] * n),
    )


def car(t, x0, v, y, acc_x=None):
    """States ``[T, 6]`` of a car at speed ``v`` (plus ``acc_x`` integrated) with lateral path ``y``."""
    acc_x = np.zeros_like(t) if acc_x is None else acc_x
    xd = v + np.concatenate([[0.0], np.cumsum(0.5 * DT * (acc_x[1:] + acc_x[:-1]))])
    x = x0 + np.concatenate([[0.0], np.cumsum(0.5 * DT * (xd[1:] + xd[:-1]))])
    yd = np.gradient(y, DT)
    return np.stack([x, y, xd, yd, acc_x, np.gradient(yd, DT)], axis=-1)


def cosine_change(t, t0, duration, y_from, y_to):
    """Lateral path that moves from ``y_from`` to ``y_to`` along a half cosine between ``t0`` and
    ``t0 + duration`` (s)."""
    phase = np.clip((t - t0) / duration, 0.0, 1.0)
    return y_from + (y_to - y_from) * 0.5 * (1.0 - np.cos(np.pi * phase))


T = np.arange(50) * DT


def test_constant_speed_has_zero_acceleration_and_jerk():
    trials = make_trials([[car(T, -140.0, 29.0, np.full_like(T, Y_L)),
                           car(T, -145.0, 27.0, np.full_like(T, Y_R))]], [50])
    s = behaviour_samples(trials)
    assert set(s) == set(STATISTICS)
    np.testing.assert_allclose(np.sort(s["speed"]), np.sort(np.r_[np.full(50, 27.0), np.full(50, 29.0)]))
    for name in ("long_accel", "lat_accel", "long_jerk", "lat_jerk"):
        np.testing.assert_array_equal(s[name], 0.0)
    assert len(s["long_jerk"]) == 2 * 49
    assert s["lane_change_x"].size == 0 and s["lane_change_duration"].size == 0


def test_jerk_of_an_acceleration_ramp_and_padding_ignored():
    ramp = 0.5 * T  # xdd grows 0.5 m/s² per s: jerk 0.5 m/s³
    a = car(T, -140.0, 29.0, np.full_like(T, Y_L), acc_x=ramp)
    trials = make_trials([[a, a], [a, a]], [50, 30], roles=[["human", "robot"], ["robot", "human"]])
    s = behaviour_samples(trials, "human")
    assert len(s["speed"]) == 50 + 30 and len(s["long_jerk"]) == 49 + 29
    np.testing.assert_allclose(s["long_jerk"], 0.5, atol=1e-9)
    np.testing.assert_array_equal(s["long_hold"], 0.0)  # 0.05 m/s² per step: never held
    assert s["long_hold_run"].size == 0 and len(s["lat_hold"]) == 49 + 29
    assert all(np.isfinite(v).all() for v in s.values())
    assert len(behaviour_samples(trials, "robot")["speed"]) == 80


def test_constant_controls_are_one_hold_run_per_agent():
    trials = make_trials([[car(T, -140.0, 29.0, np.full_like(T, Y_L)),
                           car(T, -145.0, 27.0, np.full_like(T, Y_R))]], [50])
    s = behaviour_samples(trials)
    np.testing.assert_array_equal(s["long_hold"], 1.0)
    np.testing.assert_array_equal(s["lat_hold_run"], [49.0, 49.0])  # runs never join across agents


def test_hold_runs_of_a_staircase():
    acc = np.array([[0.0, 0.0, 0.0, 0.5, 0.5 + HOLD_TOLERANCE / 2, 1.0, 1.5, 1.5, 2.0, 2.0],
                    [1.0, 1.0, 1.0, 1.0, 3.0, 3.0, 3.0, 3.0, 3.0, 3.0]])
    recorded = np.arange(10)[None, :] < np.array([[10], [5]])  # agent 1: 5 steps recorded
    held, runs = hold_runs(acc, recorded)
    # agent 0 pairs: H H . H . . H . H; agent 1 pairs: H H H .
    np.testing.assert_array_equal(held, [1, 1, 0, 1, 0, 0, 1, 0, 1, 1, 1, 1, 0])
    np.testing.assert_array_equal(runs, [2, 1, 1, 1, 3])


def test_cosine_lane_change_timing_and_crossing_x():
    t0, duration, x0, v = 1.0, 2.1, -120.0, 30.0  # midpoint (divider crossing) at 2.05 s
    left_to_right = car(T, x0, v, cosine_change(T, t0, duration, Y_L, Y_R), acc_x=np.full_like(T, -1.5))
    right_to_left = car(T, x0 - 10.0, v, cosine_change(T, t0, duration, Y_R, Y_L), acc_x=np.full_like(T, 1.5))
    trials = make_trials([[left_to_right, right_to_left]], [50])
    events = lane_change_events(trials)
    np.testing.assert_array_equal(events.trial, [0, 0])
    np.testing.assert_array_equal(events.agent, [0, 1])
    # sideways speed passes 0.2 m/s within the first step of the change (peak 4.26 π / 4.2 m/s)
    np.testing.assert_allclose(events.start * DT, t0, atol=DT + 1e-9)
    np.testing.assert_allclose(events.crossing * DT, t0 + duration / 2, atol=0.02)
    # the cosine is within 0.4 m of the target centre for a fraction acos(1 - 0.8 / 4.26) / π
    edge = np.arccos(1.0 - 2 * 0.4 / (Y_L - Y_R)) / np.pi * duration
    np.testing.assert_allclose(events.end * DT, t0 + duration - edge, atol=DT + 1e-9)
    s = behaviour_samples(trials)
    np.testing.assert_allclose(s["lane_change_sideways_time"], duration / 2, atol=DT + 0.02)
    np.testing.assert_allclose(s["lane_change_duration"], duration - edge, atol=2 * DT)
    np.testing.assert_allclose(s["long_accel_abs_near_crossing"], [1.5, 1.5])
    x_cross = lambda x_start, acc: x_start + v * 2.05 + 0.5 * acc * 2.05**2  # noqa: E731
    np.testing.assert_allclose(np.sort(s["lane_change_x"]), [x_cross(x0 - 10.0, 1.5), x_cross(x0, -1.5)], atol=0.05)


def test_lane_change_events_steps_exactly():
    """Start, crossing and end on hand-written steps: a human left-to-right change, a robot ignored."""
    y = np.full(20, Y_L)
    y[5:] = [-1.9, -2.1, -3.5, -4.5, -5.5, -5.8, -6.0, -6.09, -6.09, -6.09, -6.09, -6.09, -6.09, -6.09, -6.09]
    yd = np.zeros(20)
    yd[2:12] = [-0.1, 0.05, -0.2, -0.5, -1.0, -5.0, -10.0, -10.0, -3.0, -2.0]  # m/s, towards the right: < 0
    a = np.zeros((20, 6))
    a[:, 0], a[:, 1], a[:, 2], a[:, 3] = np.linspace(-50.0, -31.0, 20), y, 10.0, yd
    a[:, 4] = np.where(np.arange(20) < 8, 4.0, -2.0)
    trials = make_trials([[a, a]], [20], roles=[["human", "robot"]])
    events = lane_change_events(trials)
    assert len(events.start) == 1 and events.agent[0] == 0
    # last step before the crossing with sideways speed at most 0.2 m/s: step 4 (-0.2)
    np.testing.assert_array_equal(events.start, [4.0])
    # divider -3.96 crossed between step 7 (-3.5) and 8 (-4.5): 0.46 of the way
    np.testing.assert_allclose(events.crossing, [7.46], atol=1e-9)
    # first within 0.4 m of the right centre at or after the crossing: step 10 (-5.8)
    np.testing.assert_array_equal(events.end, [10.0])
    s = behaviour_samples(trials)
    np.testing.assert_allclose(s["lane_change_sideways_time"], [0.346], atol=1e-9)
    np.testing.assert_allclose(s["lane_change_duration"], [0.6], atol=1e-9)
    np.testing.assert_allclose(s["lane_change_x"], [a[7, 0] + 0.46], atol=1e-9)
    # window 7.46 - 25 .. 7.46 + 5: steps 0..12 recorded: 8 steps at 4, 5 at -2
    np.testing.assert_allclose(s["long_accel_abs_near_crossing"], [(8 * 4.0 + 5 * 2.0) / 13])


def test_lane_change_events_of_agents_that_do_not_cross_or_do_not_arrive():
    y = cosine_change(T, 3.0, 2.0, Y_L, Y_R)  # done at 5 s, recording cut at 4.5 s
    a = car(T, -120.0, 30.0, y)
    b = car(T, -125.0, 30.0, np.full_like(T, Y_R))  # stays in its lane
    trials = make_trials([[a, b]], [45])
    events = lane_change_events(trials)
    assert np.isfinite(events.start[0]) and np.isfinite(events.crossing[0]) and np.isnan(events.end[0])
    assert np.isnan([events.start[1], events.crossing[1], events.end[1]]).all()
    s = behaviour_samples(trials)
    assert s["lane_change_duration"].size == 0 and s["lane_change_sideways_time"].size == 1
    np.testing.assert_allclose(s["lane_change_x"], [-120.0 + 30.0 * 4.0], atol=1e-6)


def test_compare_identical_and_shifted_samples():
    rng = np.random.default_rng(0)
    real = {"speed": rng.normal(29.0, 2.0, 500), "lane_change_x": np.array([]), "only_real": np.ones(3)}
    same = compare_behaviour(real, real)
    assert set(same) == {"speed", "lane_change_x", "only_real"}
    assert same["speed"]["wasserstein"] == 0.0
    shifted = compare_behaviour({"speed": real["speed"] + 1.5}, real)
    row = shifted["speed"]
    assert set(shifted) == {"speed"} and row["unit"] == "m/s"
    assert row["wasserstein"] == pytest.approx(1.5)
    assert row["wasserstein_over_std"] == pytest.approx(1.5 / real["speed"].std())
    assert row["sim"]["mean"] == pytest.approx(row["real"]["mean"] + 1.5)
    assert row["real"]["count"] == 500
    assert row["real"]["p5"] < row["real"]["p50"] < row["real"]["p95"]
    empty = same["lane_change_x"]
    assert empty["real"]["count"] == 0 and empty["wasserstein"] is None and empty["real"]["mean"] is None
    assert same["only_real"]["wasserstein_over_std"] is None  # zero std


def test_format_comparison_markdown():
    rng = np.random.default_rng(1)
    real = {"speed": rng.normal(29.0, 2.0, 100), "lane_change_duration": np.array([])}
    text = format_comparison(compare_behaviour(real, real), labels=("simulated", "HITL"))
    lines = text.splitlines()
    assert len(lines) == 4 and lines[0].startswith("| statistic") and "HITL" in lines[0]
    assert all(line.count("|") == 11 for line in lines)
    assert lines[2].startswith("| speed | m/s | 100 | 100 |")
    assert "–" in lines[3]
