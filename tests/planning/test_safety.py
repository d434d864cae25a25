"""The safety layer (planning/safety.py): what it keeps, what it overrides, and that what it calls
safe is: checked against an independent simulation of the human cutting in and braking."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trafficweaving.planning.candidates import KINEMATICS, N_ACTIONS, Action
from trafficweaving.planning.safety import (CLEAR_X, HUMAN_BRAKING, RESPONSE_TIME, action_times,
                                            plausible_human_paths, predicted_human, safe_action, unsafe_next)
from trafficweaving.scenario import COLLISION_DX, COLLISION_DY, DT, LANE_CENTRE_Y

LEFT, RIGHT = LANE_CENTRE_Y["left"], LANE_CENTRE_Y["right"]
COMFORT, SAFETY, SETTLED = KINEMATICS["comfort"], KINEMATICS["safety"], KINEMATICS["settled"]
ACCELERATE_LEFT, ACCELERATE_RIGHT = Action.of(4.0, "left").index, Action.of(4.0, "right").index
"""Acceleration index 1 (+4 m/s² for the paper's and the settled kinematics, +2 m/s² for comfort)."""


def state(x, y, v=29.0, vy=0.0, a=0.0, ay=0.0):
    return np.array([x, y, v, vy, a, ay], dtype=float)


def test_a_safe_window_is_kept():
    robot, human = state(-80, RIGHT), state(-60, LEFT)  # 20 m apart in the other lane, keeping it
    proposed = ACCELERATE_RIGHT
    decision = safe_action(robot, human, proposed, COMFORT, safety=SAFETY)
    assert decision.proposed_safe and decision.chosen == proposed and not decision.overridden


def test_no_acceleration_towards_a_car_moving_into_the_lane_ahead():
    robot = state(-60, RIGHT)
    human = state(-54, -3.0, vy=-1.5, a=-1.0)  # 6 m ahead, half way into the robot's lane
    proposed = ACCELERATE_RIGHT
    decision = safe_action(robot, human, proposed, COMFORT, safety=SAFETY)
    assert not decision.proposed_safe and decision.any_safe
    assert decision.kinematics.accelerations[decision.chosen // 2] < 0  # it brakes
    # the comfort kinematics cannot brake hard enough in time: the safety kinematics' braking is driven
    assert np.isfinite(action_times(robot, human, COMFORT, SAFETY)[0]).all()
    assert decision.kinematics == SAFETY


def test_the_best_safe_window_by_the_plans_costs():
    robot = state(-60, RIGHT)
    human = state(-54, -3.0, vy=-1.5, a=-1.0)
    safe = np.isinf(action_times(robot, human, SETTLED, SETTLED)[0])
    costs = np.arange(N_ACTIONS, dtype=float)[::-1].copy()  # the plan prefers high indices
    decision = safe_action(robot, human, ACCELERATE_RIGHT, SETTLED, costs)
    assert decision.chosen == np.flatnonzero(safe).max()


def test_where_nothing_is_safe_the_robot_avoids_the_collision_longest_then_brakes_in_its_lane():
    robot = state(-60, RIGHT)
    human = state(-60.5, -3.2, vy=-2.0)  # beside it, already moving into its lane
    conflicts, collisions = action_times(robot, human, SETTLED, SETTLED)
    assert np.isfinite(conflicts).all()
    decision = safe_action(robot, human, ACCELERATE_LEFT, SETTLED)
    assert not decision.any_safe and decision.conflict_s == conflicts[decision.chosen]
    assert collisions[decision.chosen] == collisions.max()
    best = [a for a in range(N_ACTIONS) if collisions[a] == collisions.max() and conflicts[a] == conflicts[
        collisions == collisions.max()].max()]
    in_lane = [a for a in best if Action(a).lane == "right"]
    assert decision.chosen == min(in_lane or best, key=lambda a: SETTLED.accelerations[a // 2])


def test_a_car_merging_in_from_just_behind_is_not_braked_into():
    """The human 3 m behind in the other lane, moving into the robot's lane: braking hard in lane
    would put the robot in its way; what the robot drives keeps it clear of a collision."""
    robot, human = state(-45, RIGHT, v=29.7), state(-48, -3.0, v=27.0, vy=-1.8, ay=-1.0)
    brake = Action.of(-6.0, "right").index
    collisions = action_times(robot, human, SETTLED, SETTLED)[1]
    decision = safe_action(robot, human, brake, SETTLED)
    assert np.isfinite(collisions[brake]) and np.isinf(collisions[decision.chosen])


def test_a_faster_car_closing_from_behind_in_the_goal_lane_leaves_room_to_set_out_ahead_of_it():
    """20 m ahead of a human 4 m/s faster in the lane it wants, the robot may set out: accelerating
    afterwards keeps it clear whatever the human does."""
    robot, human = state(-90, LEFT, v=25.0), state(-110, RIGHT, v=29.0)
    set_out = Action.of(0.0, "right").index
    assert safe_action(robot, human, set_out, SETTLED).proposed_safe


def test_plausible_human_paths_brake_to_a_stop_and_stay_between_the_lanes():
    human = state(-50, LEFT, v=10.0, vy=-2.5, ay=-1.0)
    paths = plausible_human_paths(human, 42)
    holding, braking = paths[0], paths[4]
    assert np.all(np.diff(braking[:, 0]) >= -1e-12)  # never backwards
    assert braking[-1, 0] == pytest.approx(-50 + 10.0 ** 2 / (2 * HUMAN_BRAKING))
    assert holding[-1, 0] > braking[-1, 0]
    assert paths[..., 1].min() >= RIGHT - 1e-12 and paths[..., 1].max() <= LEFT + 1e-12
    assert paths[0, -1, 1] == pytest.approx(RIGHT)  # it completes the lane change it started
    assert np.all(paths[1, :, 1] == LEFT)  # or holds its lateral position
    fast = plausible_human_paths(state(-50, LEFT, v=36.0, a=2.0), 42)[2]  # keeps accelerating, up to the alert
    np.testing.assert_allclose(np.diff(fast[10:, 0]), 38.0 * DT)
    assert np.diff(fast[:9, 0]).max() < 38.0 * DT


def _clear_of_every_plausible_human(robot, human, acceleration, steps=42):
    """Whether the robot, holding ``acceleration`` for the response time and then either its speed
    or braking at 6 m/s² to a stop in its lane, stays clear (the collision rule) of the human
    crossing at its lateral speed and either keeping its speed or braking at HUMAN_BRAKING, for
    one response whatever the human does: an independent simulation of the layer's claim."""
    def clear(response, human_braking):
        x, v, hx, hv, hy = robot[0], robot[2], human[0], human[2], human[1]
        for k in range(1, steps + 1):
            a = acceleration if k * DT <= RESPONSE_TIME + 1e-9 else response
            v_next = max(v + a * DT, 0.0)
            x, v = x + 0.5 * (v + v_next) * DT, v_next
            hv_next = max(hv - human_braking * DT, 0.0)
            hx, hv = hx + 0.5 * (hv + hv_next) * DT, hv_next
            hy = max(hy + human[3] * DT, RIGHT)
            if abs(hx - x) < COLLISION_DX and abs(hy - robot[1]) < COLLISION_DY:
                return False
        return True
    return any(all(clear(response, b) for b in (0.0, HUMAN_BRAKING)) for response in (0.0, -6.0))


@settings(max_examples=60, deadline=None)
@given(gap=st.floats(5.0, 40.0), speed=st.floats(20.0, 35.0), lateral=st.floats(0.5, 2.5),
       proposed=st.integers(0, N_ACTIONS - 1))
def test_what_it_drives_in_lane_behind_a_car_cutting_in_ahead_stays_clear(gap, speed, lateral, proposed):
    robot = state(-80, RIGHT, v=speed)
    human = state(-80 + gap, -3.0, v=speed, vy=-lateral)
    decision = safe_action(robot, human, proposed, SETTLED)
    acceleration = SETTLED.accelerations[decision.chosen // 2]
    if decision.any_safe and Action(decision.chosen).lane == "right":
        assert _clear_of_every_plausible_human(robot, human, acceleration)
    if acceleration > 0:  # accelerating towards it only with room to spare
        assert decision.any_safe and gap > CLEAR_X


def test_the_next_window_is_judged_from_where_both_cars_will_be_when_it_starts():
    """unsafe_next: the window after the one being executed is checked from the robot's state at
    its start and the human's predicted there (holding its accelerations for the response time)."""
    human = state(-54, -3.0, vy=-1.5, a=-1.0, ay=-0.5)
    later = predicted_human(human, RESPONSE_TIME)
    x, y, v, vy = -54 + 29 * 0.3 - 0.5 * 0.09, -3.0 - 1.5 * 0.3 - 0.25 * 0.09, 29 - 0.3, -1.5 - 0.15
    np.testing.assert_allclose(later, [x, y, v, vy, -1.0, -0.5])
    robot_next = state(-51.3, RIGHT)  # where a robot at -60 m, 29 m/s, will be
    unsafe = unsafe_next(robot_next, human, COMFORT, SAFETY)
    expected = np.isfinite(action_times(robot_next, later, COMFORT, SAFETY)[0])
    if expected.all():
        assert not unsafe.any()  # nothing would pass: the layer's least-bad choice decides, not the plan
    else:
        np.testing.assert_array_equal(unsafe, expected)
    far = unsafe_next(state(-90, RIGHT), state(-40, LEFT), COMFORT, SAFETY)
    assert not far.any()  # 50 m apart in their own lanes: every window passes
    cutting_in = unsafe_next(state(-62, RIGHT), human, SETTLED, SETTLED)
    assert cutting_in[ACCELERATE_RIGHT] and not cutting_in.all()  # not accelerating into it; braking passes


def test_behind_a_human_braking_hard_the_layer_brakes_in_lane_and_the_planner_is_told_so():
    """A human 14 m ahead in the robot's lane brakes at 8 m/s², harder than the comfort kinematics
    can: the empty other lane is no escape (the human may change into it next), so a proposed
    turn back is replaced by braking in lane; farther back, where braking in lane is safe, the
    planner is told that every turn back would be rejected (unsafe_next)."""
    robot, human = state(-90, RIGHT, v=26.0), state(-76, RIGHT, v=25.0, a=-8.0)
    turn_back = Action.of(0.0, "left").index
    decision = safe_action(robot, human, turn_back, COMFORT, safety=SAFETY)
    assert decision.overridden and Action(decision.chosen).lane == "right"
    assert decision.kinematics.accelerations[decision.chosen // 2] < 0
    farther = state(-50, RIGHT, v=25.0, a=-8.0)  # 40 m ahead: braking in lane is safe, a turn back is not
    leaves = np.array([Action(a).lane == "left" for a in range(N_ACTIONS)])
    np.testing.assert_array_equal(unsafe_next(robot, farther, COMFORT, SAFETY), leaves)
    calm = state(-76, RIGHT, v=25.0, a=-3.0)  # within what comfort can brake for: turning back stays an option
    assert not safe_action(robot, calm, turn_back, COMFORT, safety=SAFETY).overridden
