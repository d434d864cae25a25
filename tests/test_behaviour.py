"""Tests of the marginal driving-behaviour statistics on small hand-built trial sets."""

import numpy as np
import pytest

from trafficweaving.data.behaviour import (
    STATISTICS,
    behaviour_samples,
    compare_behaviour,
    format_comparison,
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
    assert all(np.isfinite(v).all() for v in s.values())
    assert len(behaviour_samples(trials, "robot")["speed"]) == 80


def test_cosine_lane_change_duration_and_crossing_x():
    t0, duration, x0, v = 1.0, 2.1, -120.0, 30.0  # midpoint (divider crossing) at 2.05 s
    left_to_right = car(T, x0, v, cosine_change(T, t0, duration, Y_L, Y_R))
    right_to_left = car(T, x0 - 10.0, v, cosine_change(T, t0, duration, Y_R, Y_L))
    s = behaviour_samples(make_trials([[left_to_right, right_to_left]], [50]))
    # The cosine is within 0.4 m of a lane centre for a fraction acos(1 - 0.8 / 4.26) / π of the change
    edge = np.arccos(1.0 - 2 * 0.4 / (Y_L - Y_R)) / np.pi * duration
    assert len(s["lane_change_duration"]) == 2
    np.testing.assert_allclose(s["lane_change_duration"], duration - 2 * edge, atol=DT + 1e-9)
    np.testing.assert_allclose(np.sort(s["lane_change_x"]),
                               [x0 - 10.0 + v * (t0 + duration / 2), x0 + v * (t0 + duration / 2)], atol=1e-6)


def test_lane_change_steps_exactly():
    y = np.full(20, Y_L)
    y[5:] = [-2.0, -2.5, -3.5, -4.5, -5.5, -5.8, -6.0, -6.09, -6.09, -6.09, -6.09, -6.09, -6.09, -6.09, -6.09]
    x = np.linspace(-50.0, -31.0, 20)  # 1 m per step
    a = np.zeros((20, 6))
    a[:, 0], a[:, 1], a[:, 2] = x, y, 10.0
    s = behaviour_samples(make_trials([[a, a]], [20], roles=[["human", "robot"]]))
    # last within 0.4 m of the left centre: step 5 (-2.0); first within 0.4 m of the right: step 10
    np.testing.assert_allclose(s["lane_change_duration"], [0.5])
    # from step 5 to the crossing at step 7.46
    np.testing.assert_allclose(s["lane_change_lead_time"], [0.246], atol=1e-9)
    # divider -3.96 crossed between step 7 (-3.5) and 8 (-4.5): 0.46 of the way
    np.testing.assert_allclose(s["lane_change_x"], [x[7] + 0.46], atol=1e-9)


def test_incomplete_lane_change_is_skipped_for_duration_only():
    y = cosine_change(T, 3.0, 2.0, Y_L, Y_R)  # done at 5 s, recording cut at 4.5 s
    a = car(T, -120.0, 30.0, y)
    b = car(T, -125.0, 30.0, np.full_like(T, Y_R))
    s = behaviour_samples(make_trials([[a, b]], [45]))
    assert s["lane_change_duration"].size == 0
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
