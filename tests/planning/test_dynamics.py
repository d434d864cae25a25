"""The human's future states (dynamics.py): sampled accelerations integrated by the trapezoid rule."""

import numpy as np
import torch

from trafficweaving.dynamics import future_states, integrate_trapezoid

from helpers_planning import RIGHT


def test_human_integration_is_the_trapezoid_rule():
    present = torch.tensor([-80.0, RIGHT, 28.0, 0.3, 1.0, -0.2], dtype=torch.float64)
    actions = torch.randn(4, 15, 2, dtype=torch.float64)
    states = future_states(present, actions)
    for axis in (0, 1):
        p, v = integrate_trapezoid(np.full(4, present[axis].item()), np.full(4, present[2 + axis].item()),
                                   np.concatenate([np.full((4, 1), present[4 + axis].item()), actions[..., axis].numpy()], 1))
        np.testing.assert_allclose(states[..., axis].numpy(), p[:, 1:], atol=1e-10)
        np.testing.assert_allclose(states[..., 2 + axis].numpy(), v[:, 1:], atol=1e-10)
