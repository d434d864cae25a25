"""Driving styles (planning/styles.py): turn-back, set-out, progress and stand-off rules; fallbacks."""

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trafficweaving.dynamics import integrate_trapezoid
from trafficweaving.errors import InputError
from trafficweaving.model.constant_velocity import ConstantVelocityHuman
from trafficweaving.planning.candidates import (KINEMATICS, N_CANDIDATES, WINDOWS, Action,
                                                acceleration_indices, action_sequences, robot_candidates)
from trafficweaving.planning.costs import PaperCost
from trafficweaving.planning.planner import Budget, Planner
from trafficweaving.planning.styles import (HUMAN_ACCELERATION_HELD, PROGRESS_COST,
                                            SET_OUT_COST, SET_OUT_GAP, STANDOFF_EXIT_COST, STYLES, YIELD_MARGIN,
                                            YIELD_SPEED_FLOOR, DrivingStyle, brakes_along, set_outs, standoff_exit,
                                            turn_backs)
from trafficweaving.scenario import CAR_WIDTH, CUTOFF_X, DT, LANE_DIVIDER_Y

from helpers_planning import (HISTORY_TOY, LEFT, PRESENT_TOY, RIGHT, ToyHuman, _accelerates_throughout, _history,
                              toy_cost)


class GoalToyCost:
    """:func:`toy_cost` for a robot heading to the lane centre ``goal_y``, which it ignores."""

    def __init__(self, goal_y: float):
        self.goal_y = goal_y

    def __call__(self, robot, human):
        return toy_cost(robot, human)


@pytest.mark.slow
def test_turning_back_from_a_lane_change_under_way_costs_and_setting_out_does_not():
    """HISTORY_TOY's robot is in the right lane; window 0 sets out for the goal, the left lane."""
    fixed, cost = Action.of(0.0, "left").index, GoalToyCost(LEFT)
    history = HISTORY_TOY.copy()
    history[-1, 0, 1] = RIGHT + 1.5  # 1.5 m under way
    plain = Planner(ToyHuman(), seed=0).plan(history, fixed, cost)
    committed = Planner(ToyHuman(), seed=0, style=DrivingStyle(turn_back_cost=1000.0, commit_offset=1.0)).plan(history, fixed, cost)
    backs = turn_backs(plain.candidates.actions, "left")  # the toy cost ignores the lane
    assert backs.max() == 2 and (backs == 0).sum() == N_CANDIDATES // 2 ** (WINDOWS - 1)  # left, right, left, right, left
    np.testing.assert_allclose(committed.first_stage_cost - plain.first_stage_cost, 1000.0 * backs, atol=1e-3)
    assert backs[committed.index] == 0 and _accelerates_throughout(committed)
    probing = Planner(ToyHuman(), seed=0, style=DrivingStyle(turn_back_cost=1000.0, commit_offset=2.0)).plan(history, fixed, cost)
    np.testing.assert_array_equal(probing.first_stage_cost, plain.first_stage_cost)  # not yet committed: free
    free = Planner(ToyHuman(), seed=0, style=DrivingStyle(turn_back_cost=1000.0)).plan(history, fixed, toy_cost)
    np.testing.assert_array_equal(free.first_stage_cost, plain.first_stage_cost)  # a cost without a goal lane
    lanes = lambda *names: [Action.of(0.0, n).index for n in names]  # noqa: E731
    sequences = np.array([lanes("right", "left", "left", "left", "left"), lanes("left", "right", "left", "right", "left"),
                          lanes("right", "right", "right", "right", "right"), lanes("left", "left", "right", "right", "right")])
    assert turn_backs(sequences, "left").tolist() == [0, 2, 0, 1]


@pytest.mark.slow
def test_setting_out_beside_the_human_costs_and_with_room_in_its_lane_or_under_way_does_not():
    """HISTORY_TOY's cars are side by side, the robot in the right lane; the goal is the left lane."""
    keep, cost, style = Action.of(0.0, "right").index, GoalToyCost(LEFT), DrivingStyle(set_out_gap=5.0)
    plain = Planner(ToyHuman(), seed=0).plan(HISTORY_TOY, keep, cost)
    beside = Planner(ToyHuman(), seed=0, style=style).plan(HISTORY_TOY, keep, cost)
    starts = set_outs(plain.candidates.actions, "left")
    assert starts.sum() == N_CANDIDATES // 2
    np.testing.assert_allclose(beside.first_stage_cost - plain.first_stage_cost, SET_OUT_COST * starts, atol=0.1)
    assert not starts[beside.index]

    def costs_of_the_rule(history):
        return (Planner(ToyHuman(), seed=0, style=style).plan(history, keep, cost).first_stage_cost
                - Planner(ToyHuman(), seed=0).plan(history, keep, cost).first_stage_cost)

    apart = HISTORY_TOY.copy()
    apart[:, 1, 0] -= 5.5  # the human 5.5 m behind at the same speed: room to set out, unless braking in front of it
    accelerations = np.array([[Action(int(a)).acceleration for a in row] for row in plain.candidates.actions])
    never_braking, braking_hard = (accelerations[:, 1:] >= 0).all(1), (accelerations[:, 1:3] == -6.0).all(1)
    apart_costs = costs_of_the_rule(apart)
    np.testing.assert_array_equal(apart_costs[never_braking], 0.0)
    np.testing.assert_allclose(apart_costs[braking_hard], SET_OUT_COST * starts[braking_hard], atol=0.1)
    pulling_away = HISTORY_TOY.copy()
    pulling_away[:, 1, 0] -= 2.0  # 2 m behind but 6 m/s slower: 5.6 m apart by the time the robot is across
    pulling_away[:, 1, 2] -= 6.0
    np.testing.assert_array_equal(costs_of_the_rule(pulling_away), 0.0)
    closing = apart.copy()
    closing[:, 1, 2] += 3.0  # 5 m behind but 3 m/s faster: 3.2 m behind 0.6 s from now
    np.testing.assert_allclose(costs_of_the_rule(closing), SET_OUT_COST * starts, atol=0.1)
    in_lane = HISTORY_TOY.copy()
    in_lane[:, 1] = HISTORY_TOY[:, 0] + [3.0, 0, 0, 0, 0, 0]  # 3 m ahead in the robot's lane: setting out moves away
    np.testing.assert_array_equal(costs_of_the_rule(in_lane), 0.0)
    going = Action.of(0.0, "left").index  # window 0 already sets out: nothing to start
    np.testing.assert_array_equal(Planner(ToyHuman(), seed=0, style=style).plan(HISTORY_TOY, going, cost).first_stage_cost,
                                  Planner(ToyHuman(), seed=0).plan(HISTORY_TOY, going, cost).first_stage_cost)
    lanes = lambda *names: [Action.of(0.0, n).index for n in names]  # noqa: E731
    sequences = np.array([lanes("right", "left", "left", "left", "left"), lanes("left", "left", "left", "left", "left"),
                          lanes("right", "right", "left", "left", "left"), lanes("left", "right", "left", "right", "left")])
    assert set_outs(sequences, "left").tolist() == [True, False, False, False]


def test_the_set_out_rule_moves_the_robot_as_each_candidate_does():
    """The human 1 m behind the robot and 6 m/s slower is 4.6 m behind 0.6 s from now if the robot
    keeps its speed: too close to set out; 5.3 m behind if the robot accelerates at 4 m/s² from now
    (the decisive kinematics reach it at once): room; 3.5 m if it brakes at 6 m/s². A candidate that
    holds its speed is judged as the robot keeping it (:meth:`DrivingStyle.blocks_set_out`)."""
    style = STYLES["planner-decisive"]
    robot = np.array([-120.0, RIGHT, 30.0, 0.0, 0.0, 0.0])
    human = robot + [-1.0, LEFT - RIGHT, -6.0, 0.0, 0.0, 0.0]
    assert style.blocks_set_out(robot, human)
    for acceleration, blocked in ((0.0, True), (4.0, False), (-6.0, True)):
        first, across = Action.of(acceleration, "right").index, Action.of(acceleration, "left").index
        states = robot_candidates(robot, first, style.kinematics).states
        sequence = (action_sequences(first)[:, 1:] == across).all(1)
        assert style.blocks_set_out_along(states[sequence], robot, human).tolist() == [blocked], acceleration
    holding = robot_candidates(robot, Action.of(0.0, "right").index, style.kinematics)
    held = (acceleration_indices(holding.actions) == 0).all(1)
    for gap in (-6.0, -4.0, 0.0, 4.9, 5.1, 8.0):
        for speed in (24.0, 30.0, 33.0):
            other = robot + [gap, LEFT - RIGHT, speed - 30.0, 0.0, 0.0, 0.0]
            along = style.blocks_set_out_along(holding.states[held], robot, other)
            assert (along == style.blocks_set_out(robot, other)).all()
    in_lane = robot + [-1.0, 0.0, -6.0, 0.0, 0.0, 0.0]  # the human in the robot's lane: nothing to wait for
    assert not style.blocks_set_out_along(holding.states, robot, in_lane).any()
    assert not STYLES["planner-paper"].blocks_set_out_along(holding.states, robot, human).any()


@pytest.mark.slow
def test_in_its_goal_lane_the_robot_gets_going_again_where_nothing_holds_it():
    """Stopped in its goal lane 8 m short of the cutoff, a slow human 7 m ahead beside it: the paper's
    cost pays the robot for staying behind (separation reward) and ``planner``'s styles still
    accelerate (PROGRESS_COST per m/s of the horizon's end speed short of the floor: the rule costs
    exactly that), without the progress cost they stay; in the start lane, or faster than the
    floor, the cost is silent."""
    robot = np.array([CUTOFF_X - 8.0, RIGHT, 0.0, 0.0, 0.0, 0.0])
    human = np.array([CUTOFF_X - 1.0, LEFT + 0.5, 1.5, 0.0, 0.0, 0.0])
    history = np.repeat(np.stack([robot, human])[None], 6, axis=0)
    history[:, 1, 0] += 1.5 * DT * np.arange(-5, 1)
    keep, cost = Action.of(0.0, "right").index, PaperCost(goal_y=RIGHT)
    first = STYLES["planner"]
    for style in (first, first.fallback, first.safety_fallback):
        assert style.progress_cost == PROGRESS_COST
        ruled = Planner(ConstantVelocityHuman(), Budget(1, 8, 1), style=style).plan(history, keep, cost)
        plain = Planner(ConstantVelocityHuman(), Budget(1, 8, 1), style=replace(style, progress_cost=0.0)).plan(
            history, keep, cost)
        short = np.maximum(YIELD_SPEED_FLOOR - ruled.candidates.states[:, -1, 2], 0.0)
        np.testing.assert_allclose(ruled.first_stage_cost - plain.first_stage_cost, PROGRESS_COST * short, rtol=1e-5)
        assert Action(int(ruled.actions[1])).acceleration > 0 and ruled.robot[-1, 2] > 1.5
        assert plain.robot[-1, 2] < 0.5  # the paper's cost alone keeps it behind the human
    fast = history.copy()
    fast[:, 0, 2] = YIELD_SPEED_FLOOR + 0.5  # its braking candidates end the horizon below the floor
    for situation, goal_y in ((history, LEFT), (fast, RIGHT)):  # in the start lane; not slower than the floor
        ruled = Planner(ConstantVelocityHuman(), Budget(1, 8, 1), style=first).plan(situation, keep, PaperCost(goal_y))
        plain = Planner(ConstantVelocityHuman(), Budget(1, 8, 1), style=replace(first, progress_cost=0.0)).plan(
            situation, keep, PaperCost(goal_y))
        np.testing.assert_allclose(ruled.first_stage_cost, plain.first_stage_cost)
    with pytest.raises(InputError, match="progress_cost"):
        DrivingStyle(progress_cost=-1.0)


def _seconds_to_clear(robot, human, acceleration, gap, ahead, floor=-np.inf):
    """How long the robot holding ``acceleration`` from its state ``robot [6]`` (its speed kept at
    ``floor`` or above once it is) takes to get ``gap`` ahead of (or behind) the human ``human
    [6]``, holding its acceleration for HUMAN_ACCELERATION_HELD s and then its speed, on a 1 ms
    grid (20 s)."""
    t = np.arange(0, 20_001) * 1e-3
    integral = lambda speed: np.concatenate([[0.0], np.cumsum(0.5 * 1e-3 * (speed[1:] + speed[:-1]))])  # noqa: E731
    human_x = human[0] + integral(human[2] + human[4] * np.minimum(t, HUMAN_ACCELERATION_HELD))
    robot_x = robot[0] + integral(np.maximum(robot[2] + acceleration * t, min(floor, robot[2])))
    dx = robot_x - human_x
    clear = dx >= gap if ahead else dx <= -gap
    return t[np.argmax(clear)] if clear.any() else np.inf


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(st.floats(-12.0, 12.0), st.floats(-4.0, 4.0), st.floats(-8.0, 4.0), st.floats(14.0, 32.0),
       st.sampled_from(["settled", "comfort"]), st.sampled_from(["holding", "accelerating", "braking"]))
def test_the_standoff_exit_takes_the_sooner_way_out_and_keeps_to_the_present_one_in_doubt(
        dx, dv, human_acceleration, speed, kinematics_name, present):
    """Against brute force, the robot braking to YIELD_SPEED_FLOOR and no slower: in doubt (neither
    way out YIELD_MARGIN s sooner) it yields, unless it is accelerating already."""
    kinematics = KINEMATICS[kinematics_name]
    robot_acceleration = {"holding": 0.0, "accelerating": max(kinematics.accelerations),
                          "braking": -kinematics.hardest_braking}[present]
    human = np.array([-100.0, LEFT, speed, 0.0, human_acceleration, 0.0])
    robot = np.array([-100.0 + dx, RIGHT, speed + dv, 0.0, robot_acceleration, 0.0])
    ahead = _seconds_to_clear(robot, human, max(kinematics.accelerations), SET_OUT_GAP, True)
    behind = _seconds_to_clear(robot, human, -kinematics.hardest_braking, SET_OUT_GAP, False, YIELD_SPEED_FLOOR)
    way_out = kinematics.accelerations[standoff_exit(robot, human, kinematics, SET_OUT_GAP)]
    doubt = ahead + YIELD_MARGIN > behind + 2e-3 and behind + YIELD_MARGIN > ahead + 2e-3  # neither clearly sooner
    if ahead + YIELD_MARGIN < behind - 2e-3 or doubt and present == "accelerating":
        assert way_out == max(kinematics.accelerations)
    elif behind + YIELD_MARGIN < ahead - 2e-3 or (doubt or ahead == behind == np.inf) and present != "accelerating":
        assert way_out == -kinematics.hardest_braking


def test_the_standoff_exit_yields_down_to_the_speed_floor_and_no_further():
    """2 m behind a human at the same speed, the robot drops behind (hardest braking) at 29 m/s;
    at YIELD_SPEED_FLOOR it cannot brake any more, so it goes ahead instead."""
    kinematics = KINEMATICS["settled"]
    for speed, way_out in ((29.0, -6.0), (YIELD_SPEED_FLOOR, 4.0)):
        human = np.array([-60.0, LEFT, speed, 0.0, 0.0, 0.0])
        robot = human + [-2.0, RIGHT - LEFT, 0.0, 0.0, 0.0, 0.0]
        assert kinematics.accelerations[standoff_exit(robot, human, kinematics, SET_OUT_GAP)] == way_out


def _side_by_side(robot_accelerations, human_accelerations, dx=0.0):
    """Both cars' states ``[t+1, 2, 6]`` from 29 m/s side by side (the robot ``dx`` m ahead),
    moving with the accelerations ``[t+1]`` (m/s²) of each (trapezoid rule, as the world)."""
    cars = []
    for x, y, acceleration in ((-160.0 + dx, RIGHT, robot_accelerations), (-160.0, LEFT, human_accelerations)):
        acceleration = np.asarray(acceleration, dtype=float)
        position, speed = integrate_trapezoid(x, 29.0, acceleration)
        zeros = np.zeros_like(position)
        cars.append(np.stack([position, zeros + y, speed, zeros, acceleration, zeros], axis=-1))
    return np.stack(cars, axis=1)


def test_the_way_out_goes_ahead_once_the_human_has_braked_along():
    """Side by side, the robot has braked at 4 m/s² for a second, then held its speed: the present
    states alone say drop behind. A human that braked as hard (brakes_along) makes the robot go
    ahead, also 2 s later, and makes comfort first fall back on the decisive style; one that kept
    its speed, braked at half the robot's rate or at twice it (the speeds part: the way ahead opens
    by itself), or braked along while far ahead (no stand-off), does not."""
    first = replace(STYLES["planner"], standoff_within=0.0)  # beside the human yielding, not time, makes it fall back
    style = first.fallback
    keep = Action.of(0.0, "right").index
    braking = [0.0] * 5 + [-4.0] * 10 + [0.0]
    hardest, ahead = style.kinematics.hardest_braking, max(style.kinematics.accelerations)
    for human, along in ((braking, True), ([0.0] * 16, False), ([0.0] * 5 + [-2.0] * 10 + [0.0], False)):
        history = _side_by_side(braking, human, dx=2.0 * along - 1.0)  # 1 m behind or ahead: no way ahead before
        assert brakes_along(history) == along
        assert style.kinematics.accelerations[standoff_exit(*history[-1], style.kinematics, SET_OUT_GAP)] == -hardest
        assert style.human_yields(history) == along
        assert style.kinematics.accelerations[style.way_out(history)] == (ahead if along else -hardest)
        assert first.fallback_for(history, keep, LEFT) is (style if along else None)
    harder = _side_by_side(braking, [0.0] * 5 + [-8.0] * 10 + [0.0], dx=1.0)  # the human braking twice as hard
    assert not brakes_along(harder) and not style.human_yields(harder) and first.fallback_for(harder, keep, LEFT) is None
    assert style.way_out(harder) == standoff_exit(*harder[-1], style.kinematics, SET_OUT_GAP)  # ahead opens by itself
    later = _side_by_side(braking + [0.0] * 20, braking + [0.0] * 20, dx=1.0)
    assert not brakes_along(later) and style.human_yields(later) and first.fallback_for(later, keep, LEFT) is style
    assert style.kinematics.accelerations[style.way_out(later)] == ahead
    far = _side_by_side(braking, braking, dx=-30.0)
    assert brakes_along(far) and not style.human_yields(far) and first.fallback_for(far, keep, LEFT) is None
    assert not brakes_along(_side_by_side([0.0] * 3 + [-4.0] * 3, [0.0] * 3 + [-4.0] * 3))  # too short a history


@pytest.mark.slow
def test_the_standoff_exit_makes_room_beside_the_human():
    """2 m behind the human at the same speed, the robot yields (hardest braking); 4 m ahead, or
    beside a human braking at 8 m/s², it goes ahead. The planner costs every other window-1
    acceleration ``standoff_exit_cost`` while the set-out rule holds the robot in its lane, and
    only then. (On the decisive kinematics, whose window-1 accelerations the toy human separates.)"""
    style = replace(STYLES["planner"].fallback, kinematics=KINEMATICS["settled"])
    assert style.standoff_exit_cost == STYLES["planner"].standoff_exit_cost == STANDOFF_EXIT_COST
    history = _history()
    robot, human = history[-1]
    assert style.blocks_set_out(robot, human)  # the human 2 m ahead at the same speed
    hardest, ahead_acceleration = style.kinematics.hardest_braking, max(style.kinematics.accelerations)
    assert style.kinematics.accelerations[standoff_exit(robot, human, style.kinematics, SET_OUT_GAP)] == -hardest
    ahead = robot + [6.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    assert style.kinematics.accelerations[standoff_exit(ahead, human, style.kinematics, SET_OUT_GAP)] == ahead_acceleration
    braking = human + [0.0, 0.0, 0.0, 0.0, -8.0, 0.0]  # a human that yields too: the robot goes ahead
    assert style.kinematics.accelerations[standoff_exit(robot, braking, style.kinematics, SET_OUT_GAP)] == ahead_acceleration
    keep, cost = Action.of(0.0, "right").index, GoalToyCost(LEFT)
    ruled = Planner(ToyHuman(), seed=0, style=style).plan(history, keep, cost)
    plain = Planner(ToyHuman(), seed=0, style=replace(style, standoff_exit_cost=0.0)).plan(history, keep, cost)
    exits = np.array([Action(int(a)).acceleration for a in ruled.candidates.actions[:, 1]]) == -6.0
    np.testing.assert_allclose(ruled.first_stage_cost - plain.first_stage_cost, STANDOFF_EXIT_COST * ~exits, atol=0.1)
    assert Action(int(ruled.actions[1])).acceleration == -6.0 and Action(int(plain.actions[1])).acceleration == 4.0
    clear = history.copy()
    clear[:, 1, 0] += 30.0  # the human 32 m ahead: no stand-off, no exit cost
    ruled = Planner(ToyHuman(), seed=0, style=style).plan(clear, keep, cost)
    plain = Planner(ToyHuman(), seed=0, style=replace(style, standoff_exit_cost=0.0)).plan(clear, keep, cost)
    np.testing.assert_allclose(ruled.first_stage_cost, plain.first_stage_cost)
    with pytest.raises(InputError, match="standoff_exit_cost"):
        DrivingStyle(standoff_exit_cost=-1.0)


def test_the_set_out_rule_watches_the_gap_while_each_styles_lane_change_crosses_the_divider():
    """With half a second or more to spare either side, for the lane change from rest set out in
    window 1 (0.3 s from now); the styles' fallbacks too, but for comfort first's, which under time
    pressure watches only until the robot's body has cleared the divider (the safety layer guards
    the rest)."""
    times = np.arange(1, 61) * DT
    for name, style in [(name, style) for name, top in STYLES.items()
                       for style in (top, top.fallback, top.safety_fallback) if style is not None]:
        if style.set_out_gap:
            y = style.kinematics.steer(np.array([RIGHT, 0.0, 0.0]), np.array(LEFT), times)[:, 0]
            over = np.abs(y - LANE_DIVIDER_Y) < CAR_WIDTH / 2  # the robot's body over the divider
            first, last = 0.3 + times[over][[0, -1]]
            spare_after = 0.05 if style is STYLES["planner"].fallback else 0.45
            assert style.set_out_times[0] <= first - 0.45 and style.set_out_times[-1] >= last + spare_after, name


@pytest.mark.slow
def test_a_style_falls_back_when_time_runs_short_or_the_human_ahead_brakes_harder_than_it_can():
    """The fallback plans from the first window the robot, settled in its start lane, would reach the
    cutoff within ``fallback_within`` s, or ``standoff_within`` s while the set-out rule holds it
    and would still hold it ``fallback_within`` s before the cutoff (not while a lane change is
    under way)."""
    comfort, quick = STYLES["planner-comfort"], STYLES["planner-decisive"]
    style = replace(comfort, fallback=quick, fallback_within=2.0, standoff_within=3.0)
    keep, go = Action.of(0.0, "right").index, Action.of(0.0, "left").index

    def car(seconds_to_cutoff, speed=30.0, y=RIGHT, yd=0.0):
        return np.array([CUTOFF_X - 30.0 * seconds_to_cutoff, y, speed, yd, 0.0, 0.0])

    def fallback(style, robot, human, first_action, goal_y):  # from the present states alone
        return style.fallback_for(np.stack([robot, human])[None], first_action, goal_y)

    far = car(5.0, y=LEFT)
    assert fallback(style, car(1.95), far, keep, LEFT) is quick and fallback(style, car(2.05), far, keep, LEFT) is None
    assert fallback(style, car(1.0), far, go, LEFT) is None  # set out: window 0 heads for the goal lane
    assert fallback(style, car(1.0, y=RIGHT + 0.5), far, keep, LEFT) is None  # turning back, not yet settled
    assert fallback(style, car(1.0, yd=0.5), far, keep, LEFT) is None
    assert fallback(style, car(1.0), far, keep, None) is None  # a cost without a goal lane
    assert fallback(style, car(1.0, speed=0.0), far, keep, LEFT) is None  # standing still
    assert fallback(comfort, car(0.5), far, keep, LEFT) is None  # no fallback
    # a stand-off: beside the human at its speed 2.9 s before the cutoff; not when drifting apart, or earlier
    assert style.blocks_set_out(car(2.9), car(2.9, y=LEFT)) and not style.blocks_set_out(car(2.9), far)
    assert not style.blocks_set_out(car(2.9), car(2.9))  # the human in the robot's lane
    assert fallback(style, car(2.9), car(2.9, y=LEFT), keep, LEFT) is quick
    assert fallback(style, car(2.9), car(2.9, speed=25.0, y=LEFT), keep, LEFT) is None  # clear in time
    assert style.blocks_set_out(car(2.9), car(2.9, speed=25.0, y=LEFT))
    assert fallback(style, car(3.1), car(3.1, y=LEFT), keep, LEFT) is None
    # braking for a human ahead is the safety layer's (planning/safety.py), not a fallback's
    ahead = car(4.0, y=LEFT) + [20.0, 0.0, 0.0, 0.0, -(comfort.kinematics.hardest_braking + 0.5), 0.0]
    assert fallback(style, car(5.0, y=LEFT), ahead, go, LEFT) is None
    for fallbacks in ({"fallback": style}, {"safety_fallback": style}, {"safety_fallback": replace(comfort, safety_fallback=quick)}):
        with pytest.raises(InputError):
            DrivingStyle(**fallbacks)  # a fallback has none of its own
    with pytest.raises(InputError):
        DrivingStyle(standoff_within=-1.0)

    # the planner plans in the style it is given, moving as that style
    planner, cost = Planner(ToyHuman(), seed=0, style=style), GoalToyCost(LEFT)
    for given, kinematics in ((None, comfort.kinematics), (quick, quick.kinematics)):
        plan = planner.plan(HISTORY_TOY, keep, cost, style=given)
        assert plan.style is (given or style)
        np.testing.assert_array_equal(plan.robot, robot_candidates(PRESENT_TOY, keep, kinematics).states[plan.index])
    with pytest.raises(InputError):
        planner.plan(HISTORY_TOY, keep, cost, style="decisive")
