"""Robot agents (sim/robots.py, planning/mpc.py, model/constant_velocity.py): the agent contract,
the MPC's hold and replanning cadence in the world, closed-loop lane swaps against a scripted
constant-speed human, and bad specs."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from trafficweaving.errors import InputError
from trafficweaving.model.constant_velocity import ConstantVelocityHuman
from trafficweaving.model.cvae import CVAE
from trafficweaving.model.predictor import HumanPredictor
from trafficweaving.planning.candidates import STEPS_PER_WINDOW, Action, rollout
from trafficweaving.planning.mpc import HOLD_STEPS, MPCPolicy
from trafficweaving.planning.planner import Budget, Planner, example_history
from trafficweaving.planning.styles import SET_OUT_GAP
from trafficweaving.scenario import (CAR_WIDTH, COLLISION_DY, DT, LANE_CENTRE_Y, LANE_DIVIDER_Y, SWAP_THRESHOLD_Y,
                                     VALIDITY_REASONS, check_validity, lane_of, study_initial_conditions)
from trafficweaving.sim.score import comfort_violations
from trafficweaving.sim.robots import ROBOT_SPECS, RuleBasedRobot, RuleParameters, robot_agent
from trafficweaving.sim.world import World, run_episodes

STARTS = np.stack([condition.start_states() for condition in study_initial_conditions()])  # [18, 2, 6]: car A, car B
TINY = Budget(1, 4, 8)


class ScriptedHuman:
    """Keeps its speed; once the robot has crossed into its lane, or at the latest 45 m before the
    cutoff, it changes to the other lane along a 2 s minimum-jerk profile (an agent, batched over
    episodes)."""

    def reset(self, rng, start, me):
        self.me, self.y0 = me, start[:, me, 1].copy()
        self.goal = np.where(lane_of(self.y0) == "left", LANE_CENTRE_Y["right"], LANE_CENTRE_Y["left"])
        self.began = np.full(len(start), -1)

    def act(self, history):
        t, robot_y = history.shape[2] - 1, history[:, 1 - self.me, :, 1]
        crossed = (SWAP_THRESHOLD_Y - robot_y[:, 0]) * (SWAP_THRESHOLD_Y - robot_y[:, -1]) < 0
        late = history[:, self.me, -1, 0] > -45.0
        self.began = np.where((self.began < 0) & (crossed | late), t, self.began)
        s = np.clip((t + 1 - self.began) * DT / 2.0, 0.0, 1.0)
        ydd = np.where(self.began >= 0, (self.goal - self.y0) * (60 * s - 180 * s**2 + 120 * s**3) / 4.0, 0.0)
        return np.stack([np.zeros(len(history)), ydd], axis=1)


def untrained_mpc() -> MPCPolicy:
    torch.manual_seed(0)
    return MPCPolicy(Planner(HumanPredictor(CVAE()), TINY))


def drive(robot, start, me, steps, seed=0) -> World:
    """``steps`` steps of the world from ``start [m, 2, 6]`` with ``robot`` as car ``me``."""
    agents = [robot, ScriptedHuman()][:: 1 if me == 0 else -1]
    world, rng = World(start), np.random.default_rng(seed)
    for car, agent in enumerate(agents):
        agent.reset(rng, world.states[:, :, 0], car)
    for _ in range(steps):
        actions = [agent.act(world.history) for agent in agents]
        assert all(a.shape == (len(start), 2) and np.isfinite(a).all() for a in actions)
        world.step(np.stack(actions, axis=1))
    return world


def swapped_and_clear(world, me):
    """``(reason, swap_step, min_dx)`` of each episode: its validity, the first step the robot is
    across the lane threshold, and the least |Δx| while the cars overlap laterally (m)."""
    states, lengths = world.recorded()
    reason, _ = check_validity(states, lengths)
    y = states[:, me, :, 1]
    swap = np.argmax((SWAP_THRESHOLD_Y - y[:, :1]) * (SWAP_THRESHOLD_Y - y) < 0, axis=1)
    overlap = np.abs(states[:, 0, :, 1] - states[:, 1, :, 1]) < COLLISION_DY
    dx = np.where(overlap, np.abs(states[:, 0, :, 0] - states[:, 1, :, 0]), np.inf)
    return [VALIDITY_REASONS[r] for r in reason], swap, np.nanmin(dx, axis=1)


# ---------------------------------------------------------------- the agent contract
@pytest.mark.slow
@pytest.mark.parametrize("make", [RuleBasedRobot, untrained_mpc, lambda: robot_agent("planner-cv", budget=TINY)],
                         ids=["rules", "planner", "planner-cv"])
def test_robots_keep_the_agent_contract_and_are_deterministic_given_the_seed(make):
    robot = make()
    runs = [drive(robot, start, me, HOLD_STEPS + 7, seed=3).states[0, me]
            for start, me in ((STARTS[[4]], 1), (STARTS[[4]], 1), (STARTS[[4], ::-1], 0))]
    np.testing.assert_array_equal(runs[0], runs[1])  # the same seed: the same episode
    np.testing.assert_allclose(runs[2], runs[0], atol=1e-9)  # the same car as car 0 or car 1
    if isinstance(robot, RuleBasedRobot):
        assert robot.latencies == []
    else:
        assert len(robot.latencies) == len(robot.plans) == 3 and min(robot.latencies) > 0  # at t = 8, 11, 14


@pytest.mark.slow
def test_the_mpc_holds_then_plans_every_window_from_the_true_state():
    robot, human = robot_agent("planner-cv", budget=TINY), ScriptedHuman()  # decisive: settled kinematics
    world, made = World(STARTS[[7]]), []  # the robot (car 1) starts in the left lane
    human.reset(np.random.default_rng(0), world.states[:, :, 0], 0)
    robot.reset(np.random.default_rng(0), world.states[:, :, 0], 1)
    for _ in range(HOLD_STEPS + 3 * STEPS_PER_WINDOW):
        world.step(np.stack([human.act(world.history), robot.act(world.history)], axis=1))
        made.append(len(robot.plans))
    car = world.history[0, 1]
    np.testing.assert_allclose(car[: HOLD_STEPS + 1, [1, 2]], car[:1, [1, 2]].repeat(HOLD_STEPS + 1, 0))  # lane and speed held
    np.testing.assert_array_equal(car[1: HOLD_STEPS + 1, 4:], 0.0)
    assert made == [0] * HOLD_STEPS + [1, 1, 1, 2, 2, 2, 3, 3, 3]  # plans at t = 8, 11, 14
    assert robot.plans[0].actions[0] == Action.of(0.0, "left").index
    for k, (plan, t) in enumerate(zip(robot.plans, (8, 11, 14))):
        if k:
            assert plan.actions[0] == robot.plans[k - 1].actions[1]  # window 0: the window being executed
        np.testing.assert_allclose(plan.robot, rollout(car[t], plan.actions[None], robot.planner.kinematics)[0], atol=1e-9)  # from the true state
        np.testing.assert_array_equal(car[t + 1: t + 4, 4:], plan.robot[:3, 4:])  # executed: the plan's accelerations


# ---------------------------------------------------------------- closed loop
@pytest.mark.parametrize("me", [0, 1])
def test_the_rule_based_robot_swaps_lanes_in_every_study_start(me):
    starts = STARTS if me == 0 else STARTS[:, ::-1]
    world = run_episodes(starts, [RuleBasedRobot(), ScriptedHuman()][:: 1 if me == 0 else -1], np.random.default_rng(0))
    reasons, swap, min_dx = swapped_and_clear(world, me)
    assert reasons == ["valid"] * len(STARTS), reasons
    assert world.states[np.arange(len(STARTS)), me, swap, 0].max() < -20.0 and min_dx.min() > 10.0


@pytest.mark.slow
@pytest.mark.parametrize("spec, start, me", [("planner-decisive", 6, 0), ("planner-decisive", 12, 1),
                                             ("planner-cv", 0, 1), ("planner", 0, 1), ("planner", 6, 0)])
def test_planner_robots_swap_lanes_without_collision_and_set_out_only_with_room(spec, start, me):
    """The scripted human keeps to its lane, so the robot must be SET_OUT_GAP ahead or behind it
    while it moves across (the human starts beside it in all five: 0 or 2 m apart). The default
    (comfort first) makes room beside it: side by side at the same speed (start 6) it drops behind
    within the comfort limits (before its stand-off exit it missed its lane swap there,
    docs/closed_loop.md)."""
    starts = STARTS[[start]] if me == 0 else STARTS[[start], ::-1]
    robot = robot_agent(spec, budget=Budget(1, 8, 32))
    world = run_episodes(starts, [robot, ScriptedHuman()][:: 1 if me == 0 else -1], np.random.default_rng(start))
    reasons, swap, min_dx = swapped_and_clear(world, me)
    assert reasons == ["valid"] and min_dx[0] > 6.0
    assert len(robot.latencies) == len(robot.plans) >= 15
    states = world.states[0]
    crossing = np.abs(states[me, :, 1] - LANE_DIVIDER_Y) < CAR_WIDTH / 2  # the robot's body over the divider
    assert 0 < np.argmax(crossing) < swap[0]
    assert np.abs(states[me, crossing, 0] - states[1 - me, crossing, 0]).min() >= SET_OUT_GAP
    if spec == "planner" and start == 6:
        assert not robot.fallen_back and not comfort_violations(states[me, :, 4:6]).any()


def test_the_planning_robots_drive_in_their_styles():
    from trafficweaving.planning.candidates import KINEMATICS
    from trafficweaving.planning.styles import STYLES
    from trafficweaving.sim.robots import robot_planner

    assert robot_planner("planner-decisive").style == robot_planner("planner-cv").style == STYLES["planner-decisive"]
    first = robot_planner("planner").style
    assert first == STYLES["planner"] and first.kinematics == KINEMATICS["comfort"]
    assert first.fallback == replace(STYLES["planner-decisive"], kinematics=KINEMATICS["safety"], turn_back_cost=0.0,
                                     standoff_exit_cost=first.standoff_exit_cost, progress_cost=first.progress_cost)
    assert first.turn_back_cost == first.fallback.turn_back_cost == first.safety_fallback.turn_back_cost == 0
    assert STYLES["planner-decisive"].turn_back_cost == STYLES["planner-comfort"].turn_back_cost > 0
    paper = STYLES["planner-paper"]
    assert robot_planner("planner-paper").style == paper and paper.kinematics == KINEMATICS["paper"]
    assert paper.turn_back_cost == 0 and paper.risk == 1  # the paper's objective, unchanged
    assert robot_planner("planner-comfort").kinematics == KINEMATICS["comfort"]
    assert robot_planner("planner-cautious").style.risk < 1


# ---------------------------------------------------------------- bad input
def test_bad_specs_and_arguments_raise_input_errors():
    with pytest.raises(InputError, match=r"robot 'mpc' is unknown \(expected one of: planner, planner-decisive, "
                                         r"planner-paper, planner-comfort, planner-cautious, planner-cv, rules\)"):
        robot_agent("mpc")
    assert ROBOT_SPECS == ("planner", "planner-decisive", "planner-paper", "planner-comfort", "planner-cautious",
                           "planner-cv", "rules")
    for bad in ({"time_headway": -1.0}, {"politeness": float("nan")}, {"hurried_lane_change_time": 4.0}):
        with pytest.raises(InputError, match=next(iter(bad))):
            RuleParameters(**bad)
    with pytest.raises(InputError, match="budget"):
        robot_agent("planner-cv", budget=(1, 2, 2))
    with pytest.raises(InputError, match="dtype"):
        ConstantVelocityHuman(dtype=torch.int64)
    policy = untrained_mpc()
    with pytest.raises(RuntimeError, match="reset"):
        policy.act(np.zeros((1, 2, 1, 6)))
    rng = np.random.default_rng(0)
    for args, name in (((0, STARTS[:1], 0), "rng"), ((rng, STARTS[:2], 0), "start"), ((rng, STARTS[:1], 2), "me")):
        with pytest.raises(InputError, match=f"^{name}"):
            policy.reset(*args)
    policy.reset(rng, STARTS[:1], 0)
    with pytest.raises(InputError, match="^history has shape \\[1, 2, 6\\]"):
        policy.act(STARTS[:1])


def test_the_constant_velocity_human_predicts_zero_accelerations():
    human = ConstantVelocityHuman(dtype=torch.float64)
    human.prepare(example_history(), np.zeros((7, 15, 6)))
    actions = human.sample(torch.tensor([6, 0, 2]), 4, torch.Generator())
    assert actions.shape == (4, 3, 15, 2) and actions.dtype == torch.float64 and not actions.any()
    with pytest.raises(InputError, match="candidates"):
        human.sample(torch.tensor([7]), 1, None)
