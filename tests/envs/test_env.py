"""The Gymnasium environment TrafficWeaving-v0: the checker, both action spaces, rewards and ends."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import trafficweaving  # noqa: F401  (registers the environment)
from trafficweaving.envs.traffic_weaving import ROBOT, TrafficWeavingEnv
from trafficweaving.planning.candidates import Action
from trafficweaving.scenario import LANE_DIVIDER_Y


@pytest.mark.parametrize("action_type", ["discrete", "continuous"])
def test_environment_passes_the_gymnasium_checker(action_type):
    env = gym.make("TrafficWeaving-v0", action_type=action_type, render_mode="rgb_array")
    check_env(env.unwrapped)
    env.reset(seed=0)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3


def _run(env, policy, seed):
    observation, info = env.reset(seed=seed)
    total, steps, done = 0.0, 0, False
    while not done:
        observation, reward, terminated, truncated, info = env.step(policy(observation))
        total, steps, done = total + reward, steps + 1, terminated or truncated
    return total, steps, info, observation


def _lanes(observation) -> tuple[str, str]:
    """The robot's present lane and the other one (its goal)."""
    start = "left" if observation[1] > LANE_DIVIDER_Y else "right"
    return start, "right" if start == "left" else "left"


@pytest.mark.slow
def test_same_seed_same_episode():
    env = TrafficWeavingEnv()
    hold = lambda obs: Action.of(0.0, _lanes(obs)[0]).index  # noqa: E731
    (total_a, steps_a, info_a, last_a), (total_b, steps_b, info_b, last_b) = (_run(env, hold, 5), _run(env, hold, 5))
    assert (total_a, steps_a, info_a) == (total_b, steps_b, info_b) and np.array_equal(last_a, last_b)


@pytest.mark.slow
def test_keeping_the_lane_or_cutting_in_fails_and_waiting_for_a_gap_succeeds():
    env = TrafficWeavingEnv()
    _, _, info, observation = _run(env, lambda obs: Action.of(0.0, _lanes(obs)[0]).index, seed=1)
    assert not info["robot_swapped"] and observation[0] > -10  # the robot's x: stopped at the cutoff line
    _, _, info, _ = _run(env, lambda obs: Action.of(0.0, _lanes(obs)[1]).index, seed=1)
    assert info["collision"]  # the cars start side by side: changing lanes at once hits the human

    def wait_for_a_gap(start: str, goal: str):
        def policy(obs):
            gap = obs[0] - obs[6]  # robot x minus human x, m
            if abs(gap) < 10.0:  # alongside: fall back (or pull ahead when already ahead), keep the lane
                return Action.of(-3.0 if gap < 3.0 else 4.0, start).index
            return Action.of(0.0, goal).index
        return policy

    outcomes = [_run(env, wait_for_a_gap(*_lanes(env.reset(seed=seed)[0])), seed)[2] for seed in range(10)]
    assert sum(o["robot_swapped"] and not o["collision"] for o in outcomes) >= 8


def test_rewards_are_minus_the_planners_cost_and_continuous_actions_are_accelerations():
    env = TrafficWeavingEnv(action_type="continuous")
    env.reset(seed=2)
    t0 = env.world.t
    _, reward, *_ = env.step(np.array([2.0, 0.0], np.float32))
    assert env.world.t == t0 + 3
    assert np.allclose(env.world.states[0, ROBOT, t0 + 1: t0 + 4, 4], 2.0)
    assert reward < 0  # the lane-change urgency of a robot still in its start lane


def test_bad_actions_are_refused():
    env = TrafficWeavingEnv()
    env.reset(seed=0)
    for action in (8, -1):
        with pytest.raises(ValueError, match="action must be"):
            env.step(action)
    with pytest.raises(ValueError, match="action_type"):
        TrafficWeavingEnv(action_type="both")
