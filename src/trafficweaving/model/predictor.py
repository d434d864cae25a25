"""Batched sampling of human futures in physical units: the model's interface to the planner.

Given one interaction history and ``B`` candidate robot futures, :meth:`HumanPredictor.sample`
draws ``n`` human action sequences per candidate in one batched call: the history is encoded once,
each candidate's future once, then ``n·B`` latent values and decoder rollouts run together.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..dynamics import integrate_trapezoid
from .cvae import CVAE, HORIZON, MIN_HISTORY, STATE_DIM


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
    """Samples human futures from a :class:`CVAE` (evaluation mode, on the model's device)."""

    def __init__(self, model: CVAE):
        self.model = model.eval()
        self.device = next(model.parameters()).device
        self.dtype = next(model.parameters()).dtype

    def _tensor(self, array: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(array, dtype=self.dtype, device=self.device)

    def _features(self, states: np.ndarray) -> torch.Tensor:
        m = self.model
        return (self._tensor(states) - m.feature_mean) / m.feature_std

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
        m, c = self.model, self.model.config
        generator = torch.Generator(device=self.device)
        if seed is None:
            generator.seed()
        else:
            generator.manual_seed(seed)

        past = self._features(history).reshape(1, history.shape[0], 2 * STATE_DIM)
        present = past[0, -1]
        robot_present, human_present = present[:STATE_DIM], present[STATE_DIM:]
        futures = self._features(robot_futures)  # [B, N, 6]
        b = futures.shape[0]
        history_h = m.encode_history(past, torch.tensor([history.shape[0] - 1], device=self.device))
        robot_summary = m.encode_robot_future(futures, robot_present.expand(b, -1))
        x = torch.cat([history_h.expand(b, -1), robot_summary], dim=-1)

        logits = m.p_z_logits(x)  # [B, N_z, K_z]
        log_p = torch.log_softmax(logits, dim=-1)
        u = torch.rand((n, *log_p.shape), generator=generator, device=self.device, dtype=self.dtype)
        classes = torch.argmax(log_p - torch.log(-torch.log(u.clamp_min(1e-20))), dim=-1)  # [n, B, N_z]
        place = c.latent_classes ** torch.arange(c.latent_vars - 1, -1, -1, device=self.device)
        latents = (classes * place).sum(-1)  # [n, B]
        z = torch.nn.functional.one_hot(classes, c.latent_classes).flatten(2).to(self.dtype)

        robot_inputs = torch.cat([robot_present.expand(b, 1, -1), futures[:, :-1]], dim=1)
        present_action = ((self._tensor(history[-1, 1, 4:6]) - m.label_mean) / m.label_std).expand(b, -1)
        actions = m.sample_actions(m.zx(z, x), robot_inputs, present_action, generator)
        return Prediction(actions * m.label_std + m.label_mean, latents, m.joint_log_prob(logits))


def human_states(present: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """Human states ``[..., 15, 6]`` at steps t+1..t+15 from its present state ``present [6]`` and
    sampled accelerations ``actions [..., 15, 2]`` (m/s²), by trapezoid integration (as recorded
    human cars move)."""
    actions = np.asarray(actions, dtype=np.float64)
    states = np.empty((*actions.shape[:-1], 6))
    for axis in (0, 1):  # x then y
        acc = np.concatenate([np.broadcast_to(present[4 + axis], actions.shape[:-2] + (1,)), actions[..., axis]], axis=-1)
        p, v = integrate_trapezoid(np.full(actions.shape[:-2], present[axis]), np.full(actions.shape[:-2], present[2 + axis]), acc)
        states[..., axis], states[..., 2 + axis], states[..., 4 + axis] = p[..., 1:], v[..., 1:], acc[..., 1:]
    return states
