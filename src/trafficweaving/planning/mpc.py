"""The paper's receding-horizon robot policy.

The robot holds its lane at constant speed for the first 8 steps, then plans every 3 steps
(0.3 s). Each plan's window 0 is fixed: it is the window already being executed, chosen by the
previous plan (the hold action for the first plan); the chosen sequence's window 1 is executed
next and becomes the next plan's fixed window.
"""

from __future__ import annotations

import numpy as np

from ..scenario import LANE_CENTRE_Y, lane_of
from .candidates import STEPS_PER_WINDOW, Action, rollout
from .costs import Cost, PaperCost
from .planner import Budget, Plan, Planner

HOLD_STEPS = 8


class MPCPolicy:
    """Drives the robot one step at a time: :meth:`reset`, then :meth:`step` with the history.

    ``cost`` defaults to :class:`PaperCost` towards the lane the robot did not start in;
    ``deadline`` (s) switches the planner to its real-time mode; ``budget`` sets the sample counts
    otherwise. :attr:`plans` keeps every plan made since :meth:`reset`.
    """

    def __init__(self, planner: Planner, cost: Cost | None = None, budget: Budget | None = None,
                 deadline: float | None = None, hold_steps: int = HOLD_STEPS):
        self.planner, self.fixed_cost, self.budget, self.deadline = planner, cost, budget, deadline
        self.hold_steps = hold_steps
        self.queue: list[np.ndarray] = []
        self.plans: list[Plan] = []

    def reset(self, robot_state: np.ndarray) -> None:
        """Start an episode with the robot at ``robot_state [6]``."""
        robot_state = np.asarray(robot_state, dtype=float)
        lane = lane_of(np.array([robot_state[1]]))[0]
        goal = "right" if lane == "left" else "left"
        self.cost = self.fixed_cost or PaperCost(goal_y=LANE_CENTRE_Y[goal])
        self.hold = Action.of(0.0, lane).index
        windows = -(-self.hold_steps // STEPS_PER_WINDOW)
        self.queue = list(rollout(robot_state, np.full((1, windows), self.hold))[0, : self.hold_steps])
        self.next_fixed = self.hold
        self.plans = []

    def step(self, history: np.ndarray) -> np.ndarray:
        """The robot's state ``[6]`` at step t+1 given ``history [t+1, 2, 6]`` (robot, human)."""
        if not self.queue:
            executing = self.next_fixed
            plan = self.planner.plan(history, executing, self.cost, budget=self.budget, deadline=self.deadline)
            self.plans.append(plan)
            self.next_fixed = int(plan.actions[1])
            self.queue = list(rollout(history[-1, 0], np.array([[executing]]))[0])
        return self.queue.pop(0)
