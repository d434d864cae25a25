"""``TrafficWeaving-v0``: the paper's traffic-weaving scenario as a Gymnasium environment.

Description
    A robot car (the learning agent) and a human-driven car start side by side in adjacent lanes
    of a highway about 145 m before a cutoff, in one of the study's 18 initial conditions (speed
    difference −2/0/+2 m/s, crossover time 1/2/3 s, which car starts in which lane; paper §V-A).
    Both must swap lanes before the cutoff; who passes whom is for them to settle. The human is
    any human agent of :func:`trafficweaving.sim.humans.human_agent` (default: the simulated
    drivers). A replayed human (``replay:FILE[#K]``) drives its recorded path instead: the episode
    starts from the recording's start, the robot in the recording's other car, the trial ``K`` or
    drawn uniformly at reset (:func:`trafficweaving.sim.humans.replay_start`). The world steps at
    0.1 s (trapezoid integration); one environment step is one decision window of 0.3 s (3 world
    steps), the planner's replanning period (paper §V-C).

Action space
    ``action_type="discrete"``: ``Discrete(8)``, the planner's window actions (longitudinal
    acceleration 0, +4, −3 or −6 m/s², target lane left or right; index ``2·acceleration index +
    lane index``, :class:`~trafficweaving.planning.candidates.Action`), steered as the planner's
    candidates are. ``action_type="continuous"``: ``Box([−6, −4], [4, 4])``, the robot's
    accelerations ``[xdd, ydd]`` (m/s²) held for the window.

Observation space
    ``Box(12,)`` float32: the robot's then the human's state ``[x, y, xd, yd, xdd, ydd]`` (m, m/s,
    m/s²; ``x`` = 0 at the cutoff, ``y`` = 0 at the left road edge), within the plausible ranges of
    :data:`~trafficweaving.data.trials.PLAUSIBLE_RANGES`.

Rewards
    Minus the planner's cost (:class:`~trafficweaving.planning.costs.PaperCost`, undiscounted:
    discounting is the learner's) summed over the window's 3 steps: collision proximity, effort,
    lane-change urgency towards the robot's goal lane and the separation reward.

Episode end
    Terminated on a collision (``|Δx| < 4.5 m`` and ``|Δy| < 1.8 m``), when a car leaves the road,
    when the robot reaches the cutoff line without having swapped lanes, or once both cars are
    past the end of the recorded road (success when the robot swapped lanes). Truncated at 11 s.
    ``info``: ``time_s``, ``collision``, ``off_road``, ``robot_swapped``.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from ..data.trials import PLAUSIBLE_RANGES, _short
from ..errors import InputError
from ..planning.candidates import ACCELERATIONS, N_ACTIONS, STEPS_PER_WINDOW, rollout
from ..planning.costs import PaperCost
from ..scenario import (
    CUTOFF_X,
    DT,
    LANE_CENTRE_Y,
    LANES,
    STATE_NAMES,
    across_divider,
    colliding,
    lane_of,
    on_road,
    study_initial_conditions,
)
from ..sim.drivers import MAX_LATERAL_ACCEL
from ..sim.humans import human_agent, replay_start
from ..sim.world import World

ROBOT, HUMAN = 0, 1
"""Car indices in the environment's world: the robot is car 0."""


class TrafficWeavingEnv(gym.Env):
    """See the module docstring. ``human``: a human agent spec (``synthetic``, ``model:SPEC``,
    ``replay:FILE[#K]``, :data:`~trafficweaving.sim.humans.HUMAN_SPECS`); ``action_type``:
    ``discrete`` or ``continuous``; ``render_mode``: None or ``rgb_array`` (the road and both cars,
    robot blue, human red). :class:`~trafficweaving.errors.InputError` (a ValueError) with one line
    for any other value."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": round(1 / (STEPS_PER_WINDOW * DT))}

    def __init__(self, human: str = "synthetic", action_type: str = "discrete", render_mode: str | None = None):
        if not isinstance(action_type, str) or action_type not in ("discrete", "continuous"):
            raise InputError(f"action_type must be 'discrete' or 'continuous', got {_short(action_type)}")
        if render_mode is not None and not (isinstance(render_mode, str) and render_mode in self.metadata["render_modes"]):
            raise InputError(f"render_mode must be None or 'rgb_array', got {_short(render_mode)}")
        self.human = human_agent(human)
        self.driver = self.human  # the human agent of the present episode (a replay bound to its trial)
        self.action_type, self.render_mode = action_type, render_mode
        if action_type == "discrete":
            self.action_space = spaces.Discrete(N_ACTIONS)
        else:
            self.action_space = spaces.Box(np.array([min(ACCELERATIONS), -MAX_LATERAL_ACCEL], np.float32),
                                           np.array([max(ACCELERATIONS), MAX_LATERAL_ACCEL], np.float32))
        low = np.array([PLAUSIBLE_RANGES[name][0] for name in STATE_NAMES] * 2, np.float32)
        high = np.array([PLAUSIBLE_RANGES[name][1] for name in STATE_NAMES] * 2, np.float32)
        self.observation_space = spaces.Box(low, high, dtype=np.float32)
        self.world: World | None = None

    def _observation(self) -> np.ndarray:
        now = self.world.states[0, :, self.world.t].reshape(-1)
        return np.clip(now, self.observation_space.low, self.observation_space.high).astype(np.float32)

    def _info(self) -> dict:
        return {"time_s": self.world.t * DT, "collision": self.collided, "off_road": self.off_road,
                "robot_swapped": self.swapped}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        replay = replay_start((None, self.human), rng=self.np_random)  # cars ROBOT, HUMAN
        if replay is not None:
            start, self.driver = replay.start[0], replay.cars[HUMAN]
        else:
            conditions = study_initial_conditions()
            start = conditions[int(self.np_random.integers(len(conditions)))].start_states()
            if self.np_random.random() < 0.5:  # the robot drives car A or car B of the condition
                start = start[::-1].copy()
            self.driver = self.human
        self.world = World(start[None])
        self.driver.reset(self.np_random, self.world.states[:, :, 0], HUMAN)
        self.start_y = start[ROBOT, 1]
        goal = next(lane for lane in LANES if lane != lane_of(self.start_y))
        self.cost = PaperCost(goal_y=LANE_CENTRE_Y[goal])
        self.collided = self.off_road = self.swapped = False
        return self._observation(), self._info()

    def _robot_accelerations(self, action) -> np.ndarray:
        """The robot's accelerations ``[3, 2]`` for the window's steps."""
        if self.action_type == "discrete":
            if not self.action_space.contains(action):
                raise ValueError(f"action must be an integer in 0..{N_ACTIONS - 1}, got {action!r}")
            states = rollout(self.world.states[0, ROBOT, self.world.t], np.array([[int(action)]]))[0]
            return states[:, 4:6]
        action = np.asarray(action, dtype=np.float32)
        if action.shape != (2,) or not np.isfinite(action).all():
            raise ValueError(f"action must be a finite [xdd, ydd] in m/s², got {action!r}")
        return np.broadcast_to(np.clip(action, self.action_space.low, self.action_space.high), (STEPS_PER_WINDOW, 2))

    def step(self, action):
        if self.world is None:
            raise RuntimeError("TrafficWeavingEnv.step needs an episode: call reset() first")
        robot = self._robot_accelerations(action)
        first = self.world.t + 1
        for k in range(STEPS_PER_WINDOW):
            if self.world.done:
                break
            human = self.driver.act(self.world.history)[0]
            self.world.step(np.stack([robot[k], human])[None])
        now = self.world.states[0, :, first: self.world.t + 1]  # [2, steps, 6]: the window's steps
        window = torch.as_tensor(now)
        reward = -float(sum(term.sum() for term in self.cost.terms(window[ROBOT], window[HUMAN]).values()))
        self.collided |= bool(colliding(now[ROBOT], now[HUMAN]).any())
        self.off_road |= bool((~on_road(now[..., 1])).any())
        robot_now = self.world.states[0, ROBOT, self.world.t]
        self.swapped = bool(across_divider(self.start_y, robot_now[1]))
        missed = robot_now[0] >= CUTOFF_X and not self.swapped
        ended = not self.world.running[0]
        terminated = self.collided or self.off_road or missed or ended
        truncated = not terminated and self.world.done
        return self._observation(), reward, terminated, truncated, self._info()

    def render(self):
        if self.render_mode != "rgb_array" or self.world is None:
            return None
        from ..viz.scene import render_scene  # drawing is only needed when rendering

        roles = ("robot", "human")
        return render_scene(self.world.states[0, :, self.world.t], roles, title=f"t = {self.world.t * DT:.1f} s")
