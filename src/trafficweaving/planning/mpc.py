"""The paper's receding-horizon robot policy (paper §II-B and §V-C), as an agent of the world
(:class:`~trafficweaving.sim.world.Agent`).

The robot holds its lane at constant speed for the first 8 steps, then plans every 3 steps
(0.3 s). Each plan's window 0 is fixed: it is the window already being executed, chosen by the
previous plan (the hold action for the first plan); the chosen sequence's window 1 is executed
next and becomes the next plan's fixed window. The robot acts through accelerations, which the
world integrates (trapezoid rule), so every plan starts from the robot's true state.
"""

from __future__ import annotations

import time

import numpy as np

from .. import validate
from ..errors import InputError
from ..scenario import LANE_CENTRE_Y, LANES, STATE_NAMES, lane_of
from .candidates import STEPS_PER_WINDOW, Action, rollout
from .costs import Cost, PaperCost
from .planner import Budget, Plan, Planner, check_cost, plan_options

HOLD_STEPS = 8
"""Steps the robot holds its lane at constant speed before its first plan."""
ACCELERATION_COLUMNS = [STATE_NAMES.index("xdd"), STATE_NAMES.index("ydd")]
"""Where a state keeps the accelerations ``[xdd, ydd]`` an agent acts with."""


class MPCPolicy:
    """Drives the robot car of one episode (``m = 1``): :meth:`reset`, then :meth:`act` every step.

    ``cost`` defaults to :class:`PaperCost` towards the lane the robot did not start in;
    ``deadline`` (s) switches the planner to its real-time mode; ``budget`` sets the sample counts
    otherwise (None: the planner's); ``hold_steps``: steps held before the first plan.
    :attr:`plans` keeps every plan made since :meth:`reset` and :attr:`latencies` the seconds each
    took. Bad arguments raise :class:`~trafficweaving.errors.InputError`.
    """

    def __init__(self, planner: Planner, cost: Cost | None = None, budget: Budget | None = None,
                 deadline: float | None = None, hold_steps: int = HOLD_STEPS):
        self.planner = planner
        self.fixed_cost = None if cost is None else check_cost(cost)
        self.budget, self.deadline = plan_options(budget, deadline)
        self.hold_steps = validate.integer("hold_steps", hold_steps, 0)
        self.me: int | None = None  # the robot's car index; None before reset
        self.queue: list[np.ndarray] = []  # planned robot states [6] of the steps to come
        self.plans: list[Plan] = []
        self.plan_steps: list[int] = []  # the present step t of every plan
        self.latencies: list[float] = []

    def reset(self, rng: np.random.Generator, start: np.ndarray, me: int) -> None:
        """Start an episode from ``start [1, 2, 6]`` (both cars' states ``[x, y, xd, yd, xdd,
        ydd]``, m, m/s, m/s², finite) with the robot as car ``me`` (0 or 1). The planner's random
        generator is reseeded from ``rng`` (a NumPy Generator), so the same seed gives the same
        episode."""
        if not isinstance(rng, np.random.Generator):
            raise InputError(f"rng must be a numpy.random.Generator (np.random.default_rng(seed)), got {rng!r}")
        start = validate.finite_array("start", start, (1, 2, len(STATE_NAMES)), f"[1, 2, {len(STATE_NAMES)}]")
        self.me = validate.integer("me", me, 0, 1)
        robot = start[0, self.me]
        lane = lane_of(np.array([robot[1]]))[0]
        goal = next(other for other in LANES if other != lane)
        self.cost = self.fixed_cost or PaperCost(goal_y=LANE_CENTRE_Y[goal])
        self.hold = Action.of(0.0, lane).index
        windows = -(-self.hold_steps // STEPS_PER_WINDOW)
        self.queue = list(rollout(robot, np.full((1, windows), self.hold))[0, : self.hold_steps])
        self.next_fixed = self.hold
        self.plans, self.plan_steps, self.latencies = [], [], []
        self.planner.generator.manual_seed(int(rng.integers(2**63)))

    def act(self, history: np.ndarray) -> np.ndarray:
        """The robot's accelerations ``[1, 2]`` (``[xdd, ydd]``, m/s²) at step t+1 given both cars'
        states ``history [1, 2, t+1, 6]`` (finite; called once per step after :meth:`reset`, at
        least ``MIN_HISTORY`` steps at a plan).

        They are the planned robot state's at t+1: the hold's, then those of the window being
        executed, rolled out by the plan made at the window's start from the robot's true state
        (the plan's robot states; the last step of a window stores the next window's acceleration,
        applied from it on)."""
        if self.me is None:
            raise RuntimeError("MPCPolicy.act needs an episode: call reset(rng, start, me) first")
        history = validate.finite_array("history", history, (1, 2, None, len(STATE_NAMES)),
                                        f"[1, 2, t+1, {len(STATE_NAMES)}]")
        if not self.queue:
            robot_first = history[0, [self.me, 1 - self.me]].swapaxes(0, 1)  # [t+1, 2, 6]: robot, human
            clock = time.perf_counter()
            plan = self.planner.plan(robot_first, self.next_fixed, self.cost, budget=self.budget, deadline=self.deadline)
            self.latencies.append(time.perf_counter() - clock)
            self.plans.append(plan)
            self.plan_steps.append(history.shape[2] - 1)
            self.next_fixed = int(plan.actions[1])
            self.queue = list(plan.robot[:STEPS_PER_WINDOW])
        return self.queue.pop(0)[None, ACCELERATION_COLUMNS]
