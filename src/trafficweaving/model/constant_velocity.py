"""The constant-velocity human: the classic non-interactive baseline model of the other driver.

:class:`ConstantVelocityHuman` is a :class:`~trafficweaving.planning.planner.HumanModel` that
predicts the human keeps its present velocity whatever the robot does: zero accelerations at
every future step, for every sample and every candidate (one deterministic future, so the
planner's samples all agree). Integrated by the trapezoid rule
(:func:`~trafficweaving.dynamics.future_states`), the first step still completes the present
acceleration's half step; from then on the speed is constant. Planning against it is the
non-interactive baseline the paper argues against (paper §I: a robot that treats the human as
unresponsive to its actions).
"""

from __future__ import annotations

import torch

from .. import validate
from ..errors import InputError
from ..scenario import HORIZON, STATE_NAMES


class ConstantVelocityHuman:
    """Zero human accelerations ``[n, k, 15, 2]`` (m/s²) for any ``n`` samples of ``k`` candidates,
    as tensors on ``device`` in ``dtype`` (a floating-point torch dtype; float32 by default, the
    planner computes its costs in it)."""

    def __init__(self, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32):
        try:
            self.device = torch.device(device)
        except (RuntimeError, TypeError):
            raise InputError(f"device must be a torch device such as 'cpu' or 'cuda:0', got {device!r}") from None
        if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
            raise InputError(f"dtype must be a floating-point torch dtype such as torch.float32, got {dtype!r}")
        self.dtype = dtype
        self.candidates = 0  # robot futures of the last prepare

    def prepare(self, history, robot_futures) -> None:
        """Take one situation: ``history [t+1, 2, 6]`` (robot, human states at steps 0..t, t >= 4)
        and ``robot_futures [B, 15, 6]`` (the candidates; only their count matters here)."""
        validate.history(history)
        futures = validate.finite_array("robot_futures", robot_futures, (None, HORIZON, len(STATE_NAMES)),
                                        f"[B >= 1, {HORIZON}, {len(STATE_NAMES)}]")
        if len(futures) == 0:
            raise InputError(f"robot_futures has shape {list(futures.shape)} (expected [B >= 1, {HORIZON}, {len(STATE_NAMES)}])")
        self.candidates = len(futures)

    def sample(self, candidates, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """Zero accelerations ``[n, len(candidates), 15, 2]`` (m/s²) for candidate indices
        ``candidates [k]`` of the last :meth:`prepare`; ``generator`` is not drawn from."""
        if not self.candidates:
            raise RuntimeError("ConstantVelocityHuman.sample needs a situation: call prepare(history, robot_futures) first")
        k = len(validate.indices("candidates", candidates, self.candidates))
        return torch.zeros((validate.integer("n", n, 1), k, HORIZON, 2), dtype=self.dtype, device=self.device)
