"""MPC (planning/mpc.py): holding, replanning every window, and a style's fallbacks in the closed loop."""

from dataclasses import replace

import numpy as np
import torch
import pytest

from trafficweaving.model.constant_velocity import ConstantVelocityHuman
from trafficweaving.model.cvae import CVAE
from trafficweaving.model.predictor import HumanPredictor
from trafficweaving.planning.candidates import KINEMATICS, Action, rollout
from trafficweaving.planning.mpc import HOLD_STEPS, MPCPolicy
from trafficweaving.planning.planner import Budget, Planner
from trafficweaving.planning.styles import STYLES
from trafficweaving.scenario import CUTOFF_X, DT, LANE_DIVIDER_Y
from trafficweaving.sim.world import World

from helpers_planning import LEFT, RIGHT, _history


@pytest.mark.slow
def test_mpc_plans_in_the_fallback_from_the_first_plan_that_needs_it_to_the_end_of_the_episode():
    """A robot 3 s before the cutoff beside a slower human (4 m ahead, 5 m/s slower) it cannot set
    out beside yet, the fallback within 2.5 s: the first plans are comfortable, then every plan
    falls back, also once the lane change is under way; a new episode starts over."""
    torch.manual_seed(0)
    style = replace(STYLES["planner-comfort"], fallback=STYLES["planner-decisive"], fallback_within=2.5)
    policy = MPCPolicy(Planner(ConstantVelocityHuman(), Budget(1, 2, 2), style=style))
    start = np.array([[[CUTOFF_X - 29.0 * 3.0 - 29.0 * DT * (HOLD_STEPS - 1), RIGHT, 29.0, 0, 0, 0],
                       [CUTOFF_X - 29.0 * 3.0 - 29.0 * DT * (HOLD_STEPS - 1) + 4.0, LEFT, 24.0, 0, 0, 0]]])
    for _ in range(2):
        world = World(start)
        policy.reset(np.random.default_rng(0), world.states[:, :, 0], 0)
        for _ in range(HOLD_STEPS + 30):
            world.step(np.stack([policy.act(world.history), np.zeros((1, 2))], axis=1))
        seconds = [(CUTOFF_X - world.history[0, 0, t, 0]) / world.history[0, 0, t, 2] for t in policy.plan_steps]
        fell = next(k for k, s in enumerate(seconds) if s < 2.5)
        assert fell > 0 and all(p.style is style for p in policy.plans[:fell])
        assert all(p.style is STYLES["planner-decisive"] for p in policy.plans[fell:]) and policy.fallen_back
        assert any(Action(int(p.actions[0])).lane == "left" for p in policy.plans[fell:])  # under way, still
        assert world.history[0, 0, -1, 1] > LANE_DIVIDER_Y  # across


def test_a_human_braking_hard_ahead_is_braked_for_in_the_safety_style_for_that_window_only():
    """Comfort first: a human braking hard ahead while the robot moves across is answered by the
    safety layer with the safety style's braking (the decisive braking, the comfort steering) for
    that window only; time running short switches to the decisive fallback, to the end of the episode."""
    first = STYLES["planner"]
    policy = MPCPolicy(Planner(ConstantVelocityHuman(), Budget(1, 2, 2), style=first))
    go = Action.of(0.0, "left").index

    def car(seconds_to_cutoff, y=RIGHT, yd=0.0, xdd=0.0):
        return np.array([CUTOFF_X - 30.0 * seconds_to_cutoff, y, 30.0, yd, xdd, 0.0])

    policy.reset(np.random.default_rng(0), np.stack([car(8.0), car(8.0, y=LEFT)])[None], 0)
    braking = np.stack([car(5.0), car(4.7, xdd=-8.0)])  # 9 m ahead in the robot's lane, braking hard
    keep = Action.of(0.0, "right").index
    window, style = policy.check_window(braking[None], keep, policy.plan_style(braking[None], keep), None)
    assert style is first.safety_fallback and style.kinematics == KINEMATICS["safety"]
    assert style.kinematics.accelerations[window // 2] < 0 and policy.fallen_back is None
    assert policy.safety_log[-1][1].chosen == window
    calm = np.stack([car(5.0, y=(LEFT + RIGHT) / 2, yd=1.5), car(4.0, y=LEFT)])
    assert policy.check_window(calm[None], go, policy.plan_style(calm[None], go), None) == (go, first)
    assert policy.plan_style(np.stack([car(1.9), car(5.0, y=LEFT)])[None], Action.of(0.0, "right").index) is first.fallback
    assert policy.plan_style(calm[None], go) is first.fallback  # to the end of the episode


def test_a_human_braking_harder_ahead_than_comfort_can_is_braked_for_in_lane_in_the_safety_style():
    """Comfort first: behind a human braking harder than the comfort kinematics can, the plan is made
    in the safety style (its hardest braking at once) and the layer does not swerve into the empty
    lane (the human may take it next): a proposed turn back becomes braking in lane. Not for a
    human braking within comfort, nor for one braking in the other lane."""
    first = STYLES["planner"]
    policy = MPCPolicy(Planner(ConstantVelocityHuman(), Budget(1, 2, 2), style=first))
    turn_back, keep = Action.of(0.0, "left").index, Action.of(0.0, "right").index
    robot = np.array([CUTOFF_X - 150.0, RIGHT, 26.0, 0.0, 0.0, 0.0])
    policy.reset(np.random.default_rng(0), np.stack([robot, robot + [14.0, 0, 0, 0, 0, 0]])[None], 0)

    def planned_in(human_xdd, human_lane=RIGHT, proposed=turn_back):
        history = np.stack([robot, robot + [14.0, human_lane - RIGHT, -1.0, 0.0, human_xdd, 0.0]])[None]
        return policy.check_window(history, proposed, policy.plan_style(history, proposed), None)

    assert KINEMATICS["comfort"].hardest_braking < 8.0
    window, style = planned_in(-8.0)
    assert style is first.safety_fallback and Action(window).lane == "right"
    assert style.kinematics.accelerations[window // 2] == min(style.kinematics.accelerations)  # the hardest
    assert policy.safety_log[-1][1].chosen == window
    policy.safety_log.clear()
    assert planned_in(-3.0) == (turn_back, first)
    assert planned_in(-8.0, human_lane=LEFT, proposed=keep) == (keep, first)
    assert not policy.safety_log  # the layer kept those windows


@pytest.mark.slow
def test_mpc_holds_then_replans_every_window_with_the_fixed_first_window():
    torch.manual_seed(0)
    policy = MPCPolicy(Planner(HumanPredictor(CVAE())), budget=Budget(1, 2, 2))
    world = World(_history(1))  # one episode; the robot is car 0, the human keeps its speed
    policy.reset(np.random.default_rng(0), world.states[:, :, 0], 0)
    for _ in range(HOLD_STEPS + 9):
        world.step(np.stack([policy.act(world.history), np.zeros((1, 2))], axis=1))
    robot = world.history[0, 0]
    np.testing.assert_allclose(robot[: HOLD_STEPS + 1, 1], RIGHT)
    np.testing.assert_allclose(robot[: HOLD_STEPS + 1, 2], 29.0)
    assert len(policy.plans) == len(policy.latencies) == 3  # at t = 8, 11, 14
    assert policy.plans[0].actions[0] == Action.of(0.0, "right").index
    for previous, current in zip(policy.plans, policy.plans[1:]):
        assert current.actions[0] == previous.actions[1]
    # what the robot executed in window t = 11..14 is the first plan's window 1, from its state at t = 11
    executed = rollout(robot[11], policy.plans[0].actions[1:2][None])[0]
    np.testing.assert_allclose(robot[12:15, 5], executed[:, 5])
    np.testing.assert_allclose(robot[12:14, 4], executed[:2, 4])


@pytest.mark.slow
def test_a_comfort_planner_drives_the_closed_loop_within_the_limits():
    from trafficweaving.sim.score import comfort_violations

    torch.manual_seed(0)
    policy = MPCPolicy(Planner(HumanPredictor(CVAE()), style=STYLES["planner-comfort"]), budget=Budget(1, 2, 2))
    world = World(_history(1))
    policy.reset(np.random.default_rng(0), world.states[:, :, 0], 0)
    for _ in range(40):
        world.step(np.stack([policy.act(world.history), np.zeros((1, 2))], axis=1))
    assert len(policy.plans) >= 10 and not comfort_violations(world.history[0, 0, :, 4:6]).any()


@pytest.mark.parametrize("policy_class", ["blocking", "non-blocking"])
def test_the_safety_layer_overrides_an_accelerating_window_when_a_car_cuts_in_ahead(policy_class):
    """The robot was going to accelerate in its lane (the window fixed by the last plan) when the
    human 6 m ahead moves into that lane: the window executed brakes, the override is logged, and
    the plan made from it has it as its fixed window 0. Without the safety layer it accelerates."""
    from trafficweaving.planning.mpc import NonBlockingMPCPolicy
    from trafficweaving.planning.safety import safe_action

    accelerate = Action.of(4.0, "right").index
    t = np.arange(HOLD_STEPS + 1)[:, None] * DT
    robot = np.array([-80.0, RIGHT, 29.0, 0.0, 0.0, 0.0]) + t * [29.0, 0, 0, 0, 0, 0]
    human = np.array([-74.0, -3.0, 29.0, -1.5, -1.0, 0.0]) + t * [29.0, 0, 0, 0, 0, 0]
    history = np.stack([robot, human])[None]  # [1, 2, t+1, 6]: the human cutting in now
    for style, overrides in ((STYLES["planner"], True), (replace(STYLES["planner"], safety_layer=False), False)):
        planner = Planner(ConstantVelocityHuman(), Budget(1, 2, 2), style=style)
        policy = MPCPolicy(planner) if policy_class == "blocking" else NonBlockingMPCPolicy(planner)
        policy.reset(np.random.default_rng(0), history[:, :, 0], 0)
        policy.queue, policy.next_fixed, policy.upcoming = [], accelerate, [accelerate]
        acceleration = policy.act(history)[0, 0]
        if policy_class == "non-blocking":
            policy.close()
        if not overrides:
            assert not policy.safety_log and acceleration >= 0
            continue
        (step, decision), = policy.safety_log
        assert step == HOLD_STEPS and decision.proposed == accelerate and not decision.proposed_safe
        assert decision.kinematics.accelerations[decision.chosen // 2] < 0 and acceleration < 0
        assert decision == safe_action(history[0, 0, -1], history[0, 1, -1], accelerate, KINEMATICS["comfort"], None,
                                       KINEMATICS["safety"])
        if policy_class == "blocking":
            assert int(policy.plans[-1].actions[0]) == decision.chosen


def test_the_planner_plans_within_what_the_safety_layer_will_let_it_drive():
    """With a car cutting in ahead, a planner with a safety layer chooses a window 1 the layer is
    expected to pass (:func:`~trafficweaving.planning.safety.unsafe_next`); the same planner
    without the layer is free to choose one the layer would reject."""
    from trafficweaving.planning.costs import PaperCost
    from trafficweaving.planning.safety import unsafe_next

    t = np.arange(HOLD_STEPS + 1)[:, None] * DT
    robot = np.array([-70.0, RIGHT, 29.0, 0.0, 0.0, 0.0]) + t * [29.0, 0, 0, 0, 0, 0]
    human = np.array([-56.0, -3.0, 29.0, -1.5, -1.0, 0.0]) + t * [29.0, 0, 0, 0, 0, 0]  # 14 m ahead, cutting in
    history = np.stack([robot, human], axis=1)  # [t+1, 2, 6]
    hold = Action.of(0.0, "right").index
    style = STYLES["planner"]
    candidates_next = rollout(history[-1, 0], np.array([[hold]]), style.kinematics)[0, -1]
    unsafe = unsafe_next(candidates_next, history[-1, 1], style.kinematics, style.safety_fallback.kinematics)
    assert unsafe.any() and not unsafe.all()
    cost = PaperCost(goal_y=LEFT)
    plan = Planner(ConstantVelocityHuman(), Budget(1, 2, 2), style=style).plan(history, hold, cost)
    assert not unsafe[int(plan.actions[1])]
    assert (plan.window_costs[unsafe] >= 100_000).all()
    free = Planner(ConstantVelocityHuman(), Budget(1, 2, 2), style=replace(style, safety_layer=False))
    assert (free.plan(history, hold, cost).window_costs[unsafe] < 100_000).all()


@pytest.mark.slow
def test_a_compiled_planner_warms_up_once_before_its_first_episode_without_changing_it(monkeypatch):
    """Planner.warm_up plans once (compiling the fused steps) at the first reset only, and leaves the
    random generator as it was: the episode is the one driven without the warm-up."""
    torch.manual_seed(0)
    predictor = HumanPredictor(CVAE(), precision="float32-compiled")
    made = []
    plan = Planner.plan
    monkeypatch.setattr(Planner, "plan", lambda self, *args, **kwargs: made.append(1) or plan(self, *args, **kwargs))

    def episode(warm: bool) -> tuple[np.ndarray, int]:
        policy = MPCPolicy(Planner(predictor), budget=Budget(1, 2, 2))
        if not warm:
            policy.warmed_up = True
        world = World(_history(1))
        made.clear()
        for _ in range(2):  # the second episode does not warm up again
            policy.reset(np.random.default_rng(0), world.states[:, :, 0], 0)
        warm_ups = len(made)
        for _ in range(HOLD_STEPS + 4):
            world.step(np.stack([policy.act(world.history), np.zeros((1, 2))], axis=1))
        assert policy.planner.rows_per_second is not None  # measured by the episode's plans, not the warm-up's
        return world.history[0, 0], warm_ups

    (warmed, warm_ups), (cold, none) = episode(True), episode(False)
    assert (warm_ups, none) == (1, 0)
    np.testing.assert_array_equal(warmed, cold)


def test_a_planner_sampling_in_float32_has_nothing_to_warm_up(monkeypatch):
    planner = Planner(HumanPredictor(CVAE()))
    monkeypatch.setattr(Planner, "plan", lambda *args, **kwargs: pytest.fail("warm_up planned"))
    planner.warm_up(_history(), Action.of(0.0, "right").index, lambda robot, human: robot[..., 0, 0] * 0)
