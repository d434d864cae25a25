"""Scenario facts and the authors' validity rules."""

import numpy as np
import pytest

from trafficweaving.scenario import (
    BASE_SPEED, COLLISION_DX, CUTOFF_X, DT, LANE_CENTRE_Y, START_X, VALIDITY_REASONS,
    at_fault_collision, check_validity, colliding, lane_centre_y, lane_of, study_initial_conditions,
)


def test_eighteen_initial_conditions_cover_the_grid():
    ics = study_initial_conditions()
    assert len(ics) == 18 and len(set(ics)) == 18
    assert {ic.dv_left_minus_right for ic in ics} == {-2.0, 0.0, 2.0}


@pytest.mark.parametrize("ic", study_initial_conditions(), ids=str)
def test_faster_car_starts_behind_by_dv_times_tco(ic):
    a, b = ic.start_states()
    assert a[2] == BASE_SPEED and b[2] == BASE_SPEED + ic.dv_ab
    assert max(a[0], b[0]) == START_X
    faster, slower = (a, b) if a[2] > b[2] else (b, a)
    assert slower[0] - faster[0] == pytest.approx(abs(ic.dv_ab) * ic.tco)
    if ic.dv_ab != 0:  # with no control they are side by side after tco seconds
        t = (slower[0] - faster[0]) / (faster[2] - slower[2])
        assert t == pytest.approx(ic.tco)
    lanes = {a[1]: ic.lane_a, b[1]: ic.lane_b}
    assert sorted(lanes.values()) == ["left", "right"]
    assert all(LANE_CENTRE_Y[lane] == y for y, lane in lanes.items())
    v_left = a[2] if ic.lane_a == "left" else b[2]
    v_right = b[2] if ic.lane_a == "left" else a[2]
    assert ic.dv_left_minus_right == v_left - v_right


def weave(T=70, collide=False, swap_b=True, off_road=False, slow=False):
    """Two cars at 30 m/s from x = -150 (B 10 m behind) swapping lanes mid-way: ``[1, 2, T, 6]``."""
    t = np.arange(T) * 0.1
    s = np.zeros((1, 2, T, 6))
    s[0, 0, :, 0] = -150 + 30 * t
    s[0, 1, :, 0] = -160 + (20 if slow else 30) * t + (10 if collide else 0)
    s[0, :, :, 2] = 30
    ramp = np.clip((t - 2) / 2, 0, 1)
    s[0, 0, :, 1] = LANE_CENTRE_Y["left"] + (LANE_CENTRE_Y["right"] - LANE_CENTRE_Y["left"]) * ramp
    s[0, 1, :, 1] = LANE_CENTRE_Y["right"] + (LANE_CENTRE_Y["left"] - LANE_CENTRE_Y["right"]) * (ramp if swap_b else 0)
    if off_road:
        s[0, 0, 10, 1] = -8.5
    return s, np.array([T])


def test_valid_trial_is_cut_before_the_first_car_reaches_the_cutoff():
    states, lengths = weave()
    reason, cut = check_validity(states, lengths)
    assert VALIDITY_REASONS[reason[0]] == "valid"
    first = np.flatnonzero(states[0, 0, :, 0] >= CUTOFF_X)[0]
    assert cut[0] == first and states[0, :, cut[0] - 1, 0].max() < CUTOFF_X


@pytest.mark.parametrize("kwargs, expected", [
    ({"collide": True}, "collision"),
    ({"swap_b": False}, "no_lane_swap"),
    ({"off_road": True}, "off_road"),
    ({"slow": True, "T": 60}, "cutoff_not_reached"),
])
def test_invalid_trials_are_rejected_with_their_reason(kwargs, expected):
    states, lengths = weave(**kwargs)
    reason, cut = check_validity(states, lengths)
    assert VALIDITY_REASONS[reason[0]] == expected and cut[0] == 0


def test_collision_needs_both_longitudinal_and_lateral_overlap():
    states, lengths = weave()
    states[0, 1, :, 0] = states[0, 0, :, 0] - (COLLISION_DX + 0.01)  # close behind, never overlapping
    reason, _ = check_validity(states, lengths)
    assert VALIDITY_REASONS[reason[0]] != "collision"


def test_steps_past_the_length_are_ignored():
    states, _ = weave()
    padded = np.concatenate([states, np.full((1, 2, 10, 6), np.nan)], axis=2)
    assert check_validity(padded, np.array([70]))[0][0] == 0


def test_lane_of():
    assert lane_of(np.array([-1.83, -3.9, -4.0, -6.09])).tolist() == ["left", "left", "right", "right"]
    assert lane_centre_y(np.array([[-1.0, -3.9], [-4.0, -7.5]])).tolist() == [[-1.83, -1.83], [-6.09, -6.09]]


def drive(x0: float, speed: float, y0: float, lateral_speed: float = 0.0, steps: int = 40) -> np.ndarray:
    """One car at constant velocity, states ``[1, steps, 6]``."""
    t = DT * np.arange(steps)
    states = np.zeros((1, steps, 6))
    states[0, :, 0], states[0, :, 1] = x0 + speed * t, y0 + lateral_speed * t
    states[0, :, 2], states[0, :, 3] = speed, lateral_speed
    return states


def test_at_fault_collision_blames_the_car_behind_or_the_one_moving_sideways_into_the_other():
    left, right = LANE_CENTRE_Y["left"], LANE_CENTRE_Y["right"]
    behind, ahead = drive(START_X, 30.0, left), drive(START_X + 10, 25.0, left)  # same lane, closing at 5 m/s
    assert colliding(behind, ahead).any()
    assert at_fault_collision(behind, ahead).tolist() == [True] and at_fault_collision(ahead, behind).tolist() == [False]
    # side by side, the right-lane car moves left into the other, which keeps its lane
    mover, keeper = drive(START_X, 28.0, right, lateral_speed=1.5), drive(START_X + 1, 28.0, left)
    assert colliding(mover, keeper).any()
    assert at_fault_collision(mover, keeper).tolist() == [True] and at_fault_collision(keeper, mover).tolist() == [False]
    # both move towards each other: the faster mover is at fault
    slow_mover = drive(START_X + 1, 28.0, left, lateral_speed=-0.5)
    assert at_fault_collision(mover, slow_mover).tolist() == [True]
    assert at_fault_collision(slow_mover, mover).tolist() == [False]
    # no collision, or one only at steps that are not counted: nobody is at fault
    apart = drive(START_X + 30, 28.0, left)
    assert not at_fault_collision(behind, apart).any()
    assert not at_fault_collision(behind, ahead, steps=np.zeros((1, 40), dtype=bool)).any()
