"""The paper's cost (planning/costs.py): its terms by hand, and broadcast over samples and candidates."""

import numpy as np
import pytest
import torch

from trafficweaving.planning.costs import PaperCost

from helpers_planning import LEFT, RIGHT


def _pair(robot_xy_v, human_xy_v, steps=15):
    r, h = torch.zeros(steps, 6, dtype=torch.float64), torch.zeros(steps, 6, dtype=torch.float64)
    r[:, [0, 1, 2, 4]] = torch.tensor(robot_xy_v, dtype=torch.float64)
    h[:, [0, 1, 2, 4]] = torch.tensor(human_xy_v, dtype=torch.float64)
    return r, h


def test_cost_terms_by_hand():
    cost = PaperCost(goal_y=LEFT)
    # 3 m behind and 1 m beside: collision zone; robot 2 m/s slower and behind: moving apart rewarded
    r, h = _pair([-60.0, LEFT - 1.0, 27.0, 2.0], [-57.0, LEFT, 29.0, 0.0])
    terms = cost.terms(r, h)
    assert terms["collision"][0].item() == pytest.approx(1000 * (9.25 - np.sqrt(10.0)))
    assert terms["effort"][0].item() == pytest.approx(4.0)
    assert terms["lane"][0].item() == pytest.approx(500 * min(1.5 - 60 / 150, 1.0) * 1.0)
    assert terms["separation"][0].item() == pytest.approx(-100 * min(max(-3.0 * -2.0, 0), 1))
    total = sum(v[0].item() for v in terms.values())
    assert cost(r, h).item() == pytest.approx(total * sum(0.9 ** i for i in range(1, 16)))
    # far apart, on goal, closing in: only effort
    r, h = _pair([-200.0, LEFT, 29.0, 0.0], [-100.0, RIGHT, 27.0, 0.0])
    terms = cost.terms(r, h)
    assert terms["collision"].abs().sum() == 0 and terms["lane"].abs().sum() == 0 and terms["separation"].abs().sum() == 0
    # lane urgency ramps: weight 1.5 + x/150, capped at 1
    r, _ = _pair([-150.0, RIGHT, 29.0, 0.0], [0.0, 0.0, 0.0, 0.0])
    assert cost.terms(r, h)["lane"][0].item() == pytest.approx(500 * 0.5 * (LEFT - RIGHT))


def test_cost_broadcasts_over_samples_and_candidates():
    cost = PaperCost(goal_y=LEFT)
    robot = torch.randn(1, 7, 15, 6, dtype=torch.float64)
    human = torch.randn(5, 7, 15, 6, dtype=torch.float64)
    out = cost(robot, human)
    assert out.shape == (5, 7)
    assert out[2, 3].item() == pytest.approx(cost(robot[0, 3], human[2, 3]).item())
