"""Helpers shared by the planning test modules: lane centres, a toy human model and cost, a history."""

import numpy as np
import torch

from trafficweaving.planning.candidates import Action
from trafficweaving.scenario import DT, LANE_CENTRE_Y


LEFT, RIGHT = LANE_CENTRE_Y["left"], LANE_CENTRE_Y["right"]


class ToyHuman:
    """Human accelerations ``N(0, 1)`` per step, independent of the robot: with :func:`toy_cost`
    each candidate's expected cost is known exactly."""

    device, dtype = torch.device("cpu"), torch.float32

    def prepare(self, history, robot_futures):
        pass

    def sample(self, candidates, n, generator):
        return torch.randn((n, len(candidates), 15, 2), generator=generator, dtype=torch.float64)


def toy_cost(robot, human):
    """Expected value: 200 per free window whose acceleration is not 4 m/s² (the 16 candidates that
    accelerate throughout are optimal); noise: sd 800 per sampled future, so 16 samples (sd 200)
    often rank one of the 192 candidates 200 worse first, 1024 samples (sd 25) do not."""
    windows = robot[..., [3, 6, 9, 12], 4]  # acceleration of windows 1..4
    return 200.0 * (windows != 4.0).sum(-1) + 3100.0 * human[..., 4].mean(-1)


PRESENT_TOY = np.array([0.0, RIGHT, 30.0, 0.0, 0.0, 0.0])
HISTORY_TOY = np.repeat(np.stack([PRESENT_TOY, PRESENT_TOY + [0, 4.26, 0, 0, 0, 0]])[None], 6, axis=0)


def _accelerates_throughout(plan):
    return all(Action(int(a)).acceleration == 4.0 for a in plan.actions[1:])


def _history(steps=10):
    robot = np.array([-120.0, RIGHT, 29.0, 0.0, 0.0, 0.0])
    human = np.array([-118.0, LEFT, 29.0, 0.0, 0.0, 0.0])
    t = DT * np.arange(steps)[:, None]
    return np.stack([robot + t * [29.0, 0, 0, 0, 0, 0], human + t * [29.0, 0, 0, 0, 0, 0]], axis=1)
