"""Sampling of human futures in physical units for one history and many robot futures.

Given one interaction history and ``B`` candidate robot futures, :meth:`HumanPredictor.sample`
draws ``n`` human action sequences per candidate in one batched call: the history is encoded once,
each candidate's future once, then ``n·B`` latent values and decoder rollouts run together.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .cvae import CVAE, HORIZON, MIN_HISTORY, STATE_DIM
from .sampler import BatchedSampler


@dataclass
class Prediction:
    """``actions [n, B, 15, 2]`` sampled human accelerations ``[xdd, ydd]`` (m/s²) at steps
    t+1..t+15; ``latents [n, B]`` the joint latent value of each sample (0..Z-1, first latent
    variable slowest); ``log_p_z [B, Z]`` the prior over latent values for each candidate."""

    actions: torch.Tensor
    latents: torch.Tensor
    log_p_z: torch.Tensor


def _as_array(name: str, value, shape_text: str, ndim: int, last: tuple[int, ...]) -> np.ndarray:
    array = np.asarray(value.detach().cpu() if isinstance(value, torch.Tensor) else value, dtype=np.float64)
    if array.ndim != ndim or array.shape[ndim - len(last):] != last:
        raise ValueError(f"{name} has shape {list(array.shape)} (expected {shape_text})")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} has NaN or infinite values (expected finite numbers)")
    return array


class HumanPredictor:
    """Samples human futures from a :class:`CVAE` (evaluation mode, on the model's device),
    through the planner's fast batched sampler."""

    def __init__(self, model: CVAE):
        self.model = model.eval()
        self.sampler = BatchedSampler(model)
        self.device = next(model.parameters()).device

    @torch.no_grad()
    def sample(self, history, robot_futures, n: int, seed: int | None = 0) -> Prediction:
        """Sample ``n`` human action sequences for each candidate robot future.

        ``history [t+1, 2, 6]``: states ``[x, y, xd, yd, xdd, ydd]`` of the robot (index 0) and
        the human (index 1) at steps 0..t, ``t >= 4``; ``robot_futures [B, 15, 6]``: the robot's
        states at steps t+1..t+15 for each candidate. Deterministic for a given ``seed`` on a
        given device (``None``: nondeterministic).
        """
        history = _as_array("history", history, f"[t+1 >= {MIN_HISTORY}, 2, {STATE_DIM}]", 3, (2, STATE_DIM))
        robot_futures = _as_array("robot_futures", robot_futures, f"[B, {HORIZON}, {STATE_DIM}]", 3, (HORIZON, STATE_DIM))
        if history.shape[0] < MIN_HISTORY:
            raise ValueError(f"history has {history.shape[0]} steps (expected at least {MIN_HISTORY})")
        if not isinstance(n, int) or n < 1:
            raise ValueError(f"n must be a positive integer, got {n!r}")
        generator = torch.Generator(device=self.device)
        if seed is None:
            generator.seed()
        else:
            generator.manual_seed(seed)
        m = self.model
        context = self.sampler.encode_states(history, robot_futures)
        latents = self.sampler.sample_latents(context, n, generator)
        actions = self.sampler.sample(context, latents, generator=generator)
        return Prediction(actions * m.label_std + m.label_mean, latents, context["log_p_joint"])
