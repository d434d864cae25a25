"""NonBlockingMPCPolicy: the planner agent of the browser drive, planning in a background thread.

The simulation never waits for a plan; a plan made at the start t of a window chooses the window
executed from t+3; a late plan leaves the robot on its current plan (the previous plan's next
windows) and is discarded.
"""

import os
import time

import numpy as np
import pytest
import torch

from trafficweaving.model.constant_velocity import ConstantVelocityHuman
from trafficweaving.planning.candidates import ACCELERATIONS, Action, rollout
from trafficweaving.planning.mpc import HOLD_STEPS, NonBlockingMPCPolicy
from trafficweaving.planning.planner import Budget, Planner
from trafficweaving.planning.styles import STANDOFF_WITHIN, STYLES
from trafficweaving.scenario import CUTOFF_X, DT, LANE_CENTRE_Y, LANE_DIVIDER_Y
from trafficweaving.sim.world import World

LEFT, RIGHT = LANE_CENTRE_Y["left"], LANE_CENTRE_Y["right"]
START = np.array([[[-120.0, RIGHT, 29.0, 0.0, 0.0, 0.0], [-118.0, LEFT, 29.0, 0.0, 0.0, 0.0]]])  # robot, human


class SlowPlanner(Planner):
    """A real planner (against a constant-velocity human) that sleeps ``delays[k]`` seconds before
    its k-th plan (0 once the list is spent)."""

    def __init__(self, delays):
        super().__init__(ConstantVelocityHuman(), Budget(1, 2, 2))
        self.delays = list(delays)

    def plan(self, *args, **kwargs):
        time.sleep(self.delays.pop(0) if self.delays else 0.0)
        return super().plan(*args, **kwargs)


def drive(policy, steps, wait_at=(), start=START):
    """Step a world from ``start`` with the robot as car 0 against a human at constant speed;
    before acting at the steps in ``wait_at`` wait for the running plan (the time a real-time loop
    gives it). Returns the world and the seconds each act took."""
    world = World(start)
    policy.reset(np.random.default_rng(0), world.states[:, :, 0], 0)
    seconds = []
    for t in range(steps):
        if t in wait_at:
            while policy.planning:
                time.sleep(0.005)
        clock = time.perf_counter()
        robot = policy.act(world.history)
        seconds.append(time.perf_counter() - clock)
        world.step(np.stack([robot, np.zeros((1, 2))], axis=1))
    return world, seconds


def executed_window(world, t, action):
    """The robot states at t+1..t+3 of ``action`` rolled out from its true state at t."""
    return rollout(world.history[0, 0, t], np.array([[action]]))[0]


@pytest.mark.slow
def test_in_time_plans_are_executed_window_by_window():
    policy = NonBlockingMPCPolicy(SlowPlanner([]))
    boundaries = range(HOLD_STEPS, 30, 3)
    world, _ = drive(policy, 30, wait_at=boundaries)
    robot = world.history[0, 0]
    np.testing.assert_allclose(robot[: HOLD_STEPS + 1, 2], 29.0)  # held its speed before planning
    assert policy.late_steps == []
    assert policy.plan_steps == list(boundaries)[:len(policy.plans)] and len(policy.plans) == 7
    hold = Action.of(0.0, "right").index
    assert policy.plans[0].actions[0] == hold
    for previous, current in zip(policy.plans, policy.plans[1:]):
        assert current.actions[0] == previous.actions[1]  # window 1 of one plan is window 0 of the next
    for made, plan in zip(policy.plan_steps[:-1], policy.plans[:-1]):
        t = made + 3  # the plan made at t - 3 chose the window executed from t
        expected = executed_window(world, t, int(plan.actions[1]))
        np.testing.assert_allclose(robot[t + 1: t + 4, 4:6], expected[:, 4:6], atol=1e-9)
    assert len(policy.latencies) == len(policy.plans)
    policy.close()


@pytest.mark.slow
def test_the_comfort_first_robot_executes_each_window_as_the_mode_that_planned_it():
    """9 m ahead of a human 4 m/s faster in the other lane, 4.1 s before the cutoff: the comfort
    mode's longer look holds the robot in its lane even accelerating as hard as that mode can, and
    as the stand-off would last until 2 s before the cutoff (:data:`STANDOFF_WITHIN`) the fallback
    (the decisive set-out check) takes over and sets out; every executed window is rolled out with the motion of the
    plan that chose it."""
    mode = STYLES["planner"]
    policy = NonBlockingMPCPolicy(Planner(ConstantVelocityHuman(), Budget(1, 2, 2), style=mode))
    start = START + [[[3.0, 0, 0, 0, 0, 0], [-8.0, 0, 4.0, 0, 0, 0]]]
    world, _ = drive(policy, 55, wait_at=range(HOLD_STEPS, 55, 3), start=start)
    robot = world.history[0, 0]
    modes = [plan.style for plan in policy.plans]
    fell = modes.index(mode.fallback)
    assert fell > 0 and set(modes[:fell]) == {mode} and set(modes[fell:]) == {mode.fallback} and policy.fallen_back
    made = policy.plan_steps[fell]
    assert (CUTOFF_X - robot[made, 0]) / robot[made, 2] < STANDOFF_WITHIN and robot[-1, 1] > LANE_DIVIDER_Y
    for made, plan in zip(policy.plan_steps[:-1], policy.plans[:-1]):
        t = made + 3
        expected = rollout(robot[t], np.array([[int(plan.actions[1])]]), plan.style.kinematics)[0]
        np.testing.assert_allclose(robot[t + 1: t + 4, 4:6], expected[:, 4:6], atol=1e-9)
    policy.close()


@pytest.mark.slow
def test_a_slow_planner_never_stalls_the_simulation_and_the_robot_keeps_its_current_plan():
    # plans at t = 8 and 11 are in time; the plan at t = 14 takes 1 s: windows 17, 20, 23 follow
    # the plan made at 11 (its windows 2, 3, 4), window 26 holds its speed in that plan's last lane
    policy = NonBlockingMPCPolicy(SlowPlanner([0.0, 0.0, 1.0]))
    world, seconds = drive(policy, 28, wait_at=(11, 14))
    assert max(seconds) < 0.05  # act() never waited for the 1 s plan
    assert policy.planning  # ... which is still running
    assert policy.late_steps == [17, 20, 23, 26]
    assert policy.plan_steps == [8, 11]
    current = policy.plans[1]
    robot = world.history[0, 0]
    for k, t in enumerate((17, 20, 23)):
        expected = executed_window(world, t, int(current.actions[2 + k]))
        np.testing.assert_allclose(robot[t + 1: t + 4, 4:6], expected[:, 4:6], atol=1e-9)
    last_lane = Action(int(current.actions[4])).lane
    expected = executed_window(world, 26, Action.of(0.0, last_lane).index)
    np.testing.assert_allclose(robot[27:28, 4:6], expected[:1, 4:6], atol=1e-9)
    assert robot[27, 4] == ACCELERATIONS[0]

    # the late plan is discarded at the next window start after it arrives; planning resumes there
    while policy.planning:
        time.sleep(0.01)
    for t in (28, 29, 30, 31, 32):
        if t == 32:
            while policy.planning:
                time.sleep(0.005)
        world.step(np.stack([policy.act(world.history), np.zeros((1, 2))], axis=1))
    assert len(policy.latencies) == 4  # 8, 11, the late one, 29
    assert policy.plan_steps == [8, 11, 29]
    policy.close()


@pytest.mark.slow
def test_the_late_plan_is_discarded_and_the_next_one_made_at_the_following_window():
    policy = NonBlockingMPCPolicy(SlowPlanner([0.0, 0.3]))
    world = World(START)
    policy.reset(np.random.default_rng(0), world.states[:, :, 0], 0)
    for t in range(24):
        if t in (11, 17, 20, 23):
            while policy.planning:
                time.sleep(0.005)
        world.step(np.stack([policy.act(world.history), np.zeros((1, 2))], axis=1))
    # made at 11 (slow): late at 14, finished before 17, discarded there; a new plan made at 17 is
    # executed from 20
    assert policy.late_steps == [14]
    assert policy.plan_steps == [8, 17, 20]
    assert len(policy.latencies) == 4  # 8, 11 (discarded), 17, 20
    policy.close()


@pytest.mark.slow
def test_reset_waits_for_a_running_plan_and_starts_afresh():
    policy = NonBlockingMPCPolicy(SlowPlanner([0.2]))
    world, _ = drive(policy, HOLD_STEPS + 1)
    assert policy.planning
    policy.reset(np.random.default_rng(1), world.states[:, :, 0], 0)
    assert not policy.planning and policy.plans == [] and policy.latencies == [] and policy.late_steps == []
    policy.close()


def test_act_needs_an_episode():
    policy = NonBlockingMPCPolicy(SlowPlanner([]))
    with pytest.raises(RuntimeError, match="reset"):
        policy.act(START[:, :, None])
    policy.close()


@pytest.mark.slow
def test_a_real_time_loop_gets_every_plan_in_time():
    # 10 Hz pacing as the drive server runs it, with a planner that needs over 0.1 s a plan
    policy = NonBlockingMPCPolicy(SlowPlanner([0.1] * 20))
    world = World(START)
    policy.reset(np.random.default_rng(0), world.states[:, :, 0], 0)
    next_tick = time.perf_counter()
    for _ in range(HOLD_STEPS + 13):
        world.step(np.stack([policy.act(world.history), np.zeros((1, 2))], axis=1))
        next_tick += DT
        time.sleep(max(0.0, next_tick - time.perf_counter()))
    assert policy.late_steps == [] and policy.plan_steps == [8, 11, 14, 17]
    policy.close()


@pytest.mark.slow
def test_the_planner_thread_uses_the_torch_threads_it_is_given():
    seen = []

    class Recording(SlowPlanner):
        def plan(self, *args, **kwargs):
            seen.append(torch.get_num_threads())
            return super().plan(*args, **kwargs)

    counts = [1, 2] if (os.cpu_count() or 1) >= 2 else [1]
    for threads in counts:
        policy = NonBlockingMPCPolicy(Recording([]), threads=threads)
        policy.warm_up(np.repeat(START[0][None], 6, axis=0), plans=2)  # history [6, 2, 6], robot first
        policy.close()
    assert seen == [n for n in counts for _ in range(2)]
