"""The robot's objective: ``E[Σ_{i=1..15} γ^i J_i]`` with ``γ = 0.9`` and the paper's terms
(paper §II-B, §V-C). A cost is any callable ``(robot [..., 15, 6], human [..., 15, 6]) -> [...]``
(broadcasting over samples and candidates, torch tensors, states ``[x, y, xd, yd, xdd, ydd]``)
returning the discounted sum per trajectory pair; :class:`PaperCost` is the default.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch


class Cost(Protocol):
    def __call__(self, robot: torch.Tensor, human: torch.Tensor) -> torch.Tensor: ...


@dataclass(frozen=True)
class PaperCost:
    """The paper's cost for a robot heading to the lane centre ``goal_y`` (m).

    Per step, with ``Δs = x_r - x_h``, ``Δτ = y_r - y_h``, ``Δṡ = xd_r - xd_h``:
    collision ``J_c = 1000·1{|Δs| < 8, |Δτ| < 2}·(9.25 - sqrt(Δs² + Δτ²))``, effort ``J_a = xdd_r²``,
    lane-change urgency ``J_l = 500·min(1.5 + x_r/150, 1)·|y_r - goal_y|`` and separation reward
    ``J_d = -100·min(max(Δs·Δṡ, 0), 1)``; discounted by ``γ^i``, i = 1..15.
    """

    goal_y: float
    discount: float = 0.9
    collision_weight: float = 1000.0
    effort_weight: float = 1.0
    lane_weight: float = 500.0
    separation_weight: float = 100.0

    def _pair_terms(self, robot: torch.Tensor, human: torch.Tensor) -> dict[str, torch.Tensor]:
        """The terms that depend on both cars, ``[..., 15]`` (broadcast shape of the inputs)."""
        ds, dtau, dsd = robot[..., 0] - human[..., 0], robot[..., 1] - human[..., 1], robot[..., 2] - human[..., 2]
        close = (ds.abs() < 8.0) & (dtau.abs() < 2.0)
        collision = self.collision_weight * close * (9.25 - torch.sqrt(ds * ds + dtau * dtau))
        separation = -self.separation_weight * torch.clamp(ds * dsd, min=0.0, max=1.0)
        return {"collision": collision, "separation": separation}

    def _robot_terms(self, robot: torch.Tensor) -> dict[str, torch.Tensor]:
        """The terms of the robot's future alone, ``[..., 15]`` (shape of ``robot`` without its last axis)."""
        urgency = torch.clamp(1.5 + robot[..., 0] / 150.0, max=1.0)
        return {"effort": self.effort_weight * robot[..., 4] ** 2,
                "lane": self.lane_weight * urgency * (robot[..., 1] - self.goal_y).abs()}

    def terms(self, robot: torch.Tensor, human: torch.Tensor) -> dict[str, torch.Tensor]:
        """Undiscounted per-step terms ``[..., 15]`` (broadcast shape of the inputs)."""
        pair, own = self._pair_terms(robot, human), self._robot_terms(robot)
        shape = pair["collision"].shape
        return {"collision": pair["collision"], "effort": own["effort"].expand(shape), "lane": own["lane"].expand(shape),
                "separation": pair["separation"]}

    def __call__(self, robot: torch.Tensor, human: torch.Tensor) -> torch.Tensor:
        steps = robot.shape[-2]
        weights = self.discount ** torch.arange(1, steps + 1, dtype=robot.dtype, device=robot.device)
        # the robot's own terms are summed once per robot future, not once per human future
        return sum(self._pair_terms(robot, human).values()) @ weights + sum(self._robot_terms(robot).values()) @ weights
