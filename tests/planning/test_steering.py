"""Lateral steering (planning/steering.py): minimum energy, its free final time, and jerk-limited."""

import numpy as np
import pytest

from trafficweaving.planning.steering import jerk_limited_steer, optimal_time, steer, steering_cost
from trafficweaving.scenario import DT

from helpers_planning import LEFT, RIGHT


STATES = np.array([[RIGHT, 0.0, 0.0], [LEFT, 0.4, -0.5], [-3.5, -1.2, 2.0], [-5.0, 0.8, 0.3]])
TARGETS = np.array([LEFT, RIGHT, RIGHT, LEFT])


def test_steering_reaches_the_target_at_rest_and_holds_it():
    T = optimal_time(STATES, TARGETS)
    end = steer(STATES, TARGETS, np.stack([T, T + 0.5, T + 3.0], axis=-1))
    np.testing.assert_allclose(end[..., 0], TARGETS[:, None].repeat(3, 1), atol=1e-9)
    np.testing.assert_allclose(end[..., 1:], 0.0, atol=1e-9)


def test_steering_time_minimises_the_cost():
    T = optimal_time(STATES, TARGETS)
    for k in range(len(T)):
        grid = np.linspace(0.05, 12.0, 120_001)
        brute = steering_cost(np.repeat(STATES[k:k + 1], len(grid), 0), np.full(len(grid), TARGETS[k]), grid)
        assert steering_cost(STATES[k], TARGETS[k], T[k]) <= brute.min() + 1e-9
        assert abs(T[k] - grid[brute.argmin()]) < 1e-3


def test_steering_is_the_minimum_energy_jerk_and_integrates_consistently():
    state, target = STATES[2], TARGETS[2]
    T = float(optimal_time(state, target))
    times = np.linspace(0.0, T, 20_001)[:-1]  # up to the final time, where the hold begins
    path = steer(state, target, times)  # [K, 4]: y, yd, ydd, yddd
    dt = times[1] - times[0]
    for lower, upper in ((2, 3), (1, 2), (0, 1)):  # integrate each derivative (trapezoid) and compare
        integrated = path[0, lower] + np.concatenate([[0.0], np.cumsum(0.5 * dt * (path[1:, upper] + path[:-1, upper]))])
        np.testing.assert_allclose(integrated, path[:, lower], atol=1e-6)
    energy = np.trapezoid(path[:, 3] ** 2, times)
    assert T + energy / 1000.0 == pytest.approx(float(steering_cost(state, target, T)), rel=1e-4)
    # any other jerk profile reaching the same final state differs by a perturbation orthogonal to
    # (T-t)²/2, T-t and 1 (the final state is linear in exactly these moments) and costs more
    basis = np.stack([(T - times) ** 2 / 2, T - times, np.ones_like(times)], axis=1)
    bump = np.sin(3 * np.pi * times / T) + 0.5 * np.cos(7 * times)
    bump -= basis @ np.linalg.lstsq(basis, bump, rcond=None)[0]
    assert np.abs(np.trapezoid(basis * bump[:, None], times, axis=0)).max() < 1e-3
    for scale in (0.05, 0.5, 2.0):
        assert np.trapezoid((path[:, 3] + scale * bump) ** 2, times) > energy


def test_at_target_means_no_motion():
    path = steer(np.array([LEFT, 0.0, 0.0]), np.array(LEFT), np.array([0.1, 0.2, 0.3]))
    np.testing.assert_allclose(path[:, 0], LEFT)
    np.testing.assert_allclose(path[:, 1:], 0.0)


def test_jerk_limited_steering_keeps_to_its_limits_reaches_the_target_and_is_faster_than_minimum_energy():
    """From every test state, and a lane change from rest: within 4.5 m/s² and 7 m/s³ (the jerk
    also as sampled every 0.1 s), at rest on the target after it, re-solving from a state on the way
    continues the same path, and the lane change ends sooner than the minimum-energy one whose
    sampled jerk peaks at the same 7 m/s³ (ρ = 60: 3.2 s); a small correction given a shortest
    time takes that long, gently."""
    times = np.arange(1, 81) * DT  # 0.1 .. 8 s
    path = jerk_limited_steer(STATES, TARGETS, times, 4.5, 7.0)  # [4, K, 3]
    acc = np.concatenate([STATES[:, None, 2], path[..., 2]], axis=1)
    assert np.abs(path[..., 2]).max() <= 4.5 + 1e-9 and np.abs(np.diff(acc, axis=1) / 0.1).max() <= 7.0 + 1e-9
    np.testing.assert_allclose(path[:, -1], np.stack([TARGETS, 0 * TARGETS, 0 * TARGETS], 1), atol=1e-9)
    again = jerk_limited_steer(path[:, 9], TARGETS, times[:20], 4.5, 7.0)  # from 1 s on
    np.testing.assert_allclose(again, path[:, 10:30], atol=1e-6)
    lane_change = jerk_limited_steer(np.array([RIGHT, 0.0, 0.0]), np.array(LEFT), times, 4.5, 7.0)
    done = times[np.argmax(np.abs(lane_change[:, 0] - LEFT) < 1e-6)]
    gentle = steer(np.array([RIGHT, 0.0, 0.0]), np.array(LEFT), times, 60.0)
    assert done < 2.8 and times[np.argmax(np.abs(gentle[:, 0] - LEFT) < 1e-3)] > 3.0
    assert np.abs(np.diff(np.r_[0.0, gentle[:, 2]]) / 0.1).max() > 7.0
    nudge = jerk_limited_steer(np.array([LEFT - 0.01, 0.02, 0.1]), np.array(LEFT), times, 4.5, 7.0, min_time=0.6)
    assert np.abs(nudge[:5, 0] - LEFT).min() > 1e-4 and np.abs(nudge[5:, 0] - LEFT).max() < 1e-9  # there at 0.6 s
    assert np.abs(nudge[..., 2]).max() < np.abs(jerk_limited_steer(np.array([LEFT - 0.01, 0.02, 0.1]), np.array(LEFT),
                                                                     times, 4.5, 7.0)[..., 2]).max() / 4
    with pytest.raises(ValueError, match="no jerk-limited steering"):
        jerk_limited_steer(np.array([RIGHT, np.nan, 0.0]), np.array(LEFT), times, 4.5, 7.0)
