"""The paper's receding-horizon robot policy (paper §II-B and §V-C).

The robot holds its lane at constant speed for the first 8 steps, then plans every 3 steps
(0.3 s). Each plan's window 0 is fixed: it is the window already being executed, chosen by the
previous plan (the hold action for the first plan); the chosen sequence's window 1 is executed
next and becomes the next plan's fixed window.
"""

from __future__ import annotations

import numpy as np

from .. import validate
from ..errors import InputError
from ..scenario import LANE_CENTRE_Y, LANES, lane_of
from .candidates import STEPS_PER_WINDOW, Action, rollout
from .costs import Cost, PaperCost
from .planner import Budget, Plan, Planner, check_cost, plan_options

HOLD_STEPS = 8
"""Steps the robot holds its lane at constant speed before its first plan."""
STATE_TOLERANCE = 1e-3
"""How far (m, m/s, m/s²) a history's last robot state may be from the state the policy set (a
history stored in float32 is within it)."""


class MPCPolicy:
    """Drives the robot one step at a time: :meth:`reset`, then :meth:`step` with the history.

    ``cost`` defaults to :class:`PaperCost` towards the lane the robot did not start in;
    ``deadline`` (s) switches the planner to its real-time mode; ``budget`` sets the sample counts
    otherwise; ``hold_steps``: steps held before the first plan. :attr:`plans` keeps every plan
    made since :meth:`reset`. Bad arguments raise :class:`~trafficweaving.errors.InputError`.
    """

    def __init__(self, planner: Planner, cost: Cost | None = None, budget: Budget | None = None,
                 deadline: float | None = None, hold_steps: int = HOLD_STEPS):
        self.planner = planner
        self.fixed_cost = None if cost is None else check_cost(cost)
        self.budget, self.deadline = plan_options(budget, deadline)
        self.hold_steps = validate.integer("hold_steps", hold_steps, 0)
        self.queue: list[np.ndarray] = []
        self.plans: list[Plan] = []
        self.robot_state: np.ndarray | None = None  # where the robot is now: the last state reset or step set

    def reset(self, robot_state: np.ndarray) -> None:
        """Start an episode with the robot at ``robot_state [6]`` (``[x, y, xd, yd, xdd, ydd]``, m,
        m/s, m/s², finite)."""
        robot_state = validate.car_state("robot_state", robot_state)
        lane = lane_of(np.array([robot_state[1]]))[0]
        goal = next(other for other in LANES if other != lane)
        self.cost = self.fixed_cost or PaperCost(goal_y=LANE_CENTRE_Y[goal])
        self.hold = Action.of(0.0, lane).index
        windows = -(-self.hold_steps // STEPS_PER_WINDOW)
        self.queue = list(rollout(robot_state, np.full((1, windows), self.hold))[0, : self.hold_steps])
        self.next_fixed = self.hold
        self.plans = []
        self.robot_state = robot_state.copy()

    def step(self, history: np.ndarray) -> np.ndarray:
        """The robot's state ``[6]`` at step t+1 given ``history [t+1, 2, 6]`` (robot, human; finite),
        whose last robot state must be where this policy put the robot (the state of :meth:`reset`,
        then the one the previous call returned)."""
        if self.robot_state is None:
            raise RuntimeError("MPCPolicy.step needs an episode: call reset(robot_state) first")
        history = validate.history(history, min_steps=1)
        if not np.allclose(history[-1, 0], self.robot_state, rtol=0.0, atol=STATE_TOLERANCE):
            raise InputError(f"history[-1, 0] is {np.round(history[-1, 0], 4).tolist()} (expected the robot state this policy "
                             f"set last, {np.round(self.robot_state, 4).tolist()}; reset(robot_state) starts another episode)")
        if not self.queue:
            executing = self.next_fixed
            plan = self.planner.plan(history, executing, self.cost, budget=self.budget, deadline=self.deadline)
            self.plans.append(plan)
            self.next_fixed = int(plan.actions[1])
            self.queue = list(rollout(history[-1, 0], np.array([[executing]]))[0])
        self.robot_state = self.queue.pop(0)
        return self.robot_state.copy()
