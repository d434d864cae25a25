"""Figures of human models: the paper's Fig. 3 (sampled human futures coloured by latent value,
beside the interaction history and the robot's future) and validation curves of training runs."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from matplotlib import colormaps
from matplotlib.figure import Figure

from ..data.trials import TrialSet
from ..dynamics import future_states
from ..model.cvae import CVAE
from ..model.predictor import HumanPredictor
from ..scenario import HORIZON, MIN_HISTORY
from .figures import draw_road, _save


def plot_predictions(model: CVAE, trials: TrialSet, picks: list[tuple[int, int, int]], path: str | os.PathLike,
                     samples: int = 50, seed: int = 0, title: str = "") -> Path:
    """One panel per ``(trial index, human agent, t)`` in ``picks``: history of both cars to step
    ``t``, the other car's recorded future (the condition), the human's recorded future, and
    ``samples`` sampled human futures coloured by their latent value."""
    predictor = HumanPredictor(model)
    fig = Figure(figsize=(11, 2.3 * len(picks) + 0.6))
    axes = fig.subplots(len(picks), 1, squeeze=False)[:, 0]
    for ax, (i, agent, t) in zip(axes, picks):
        human, robot = trials.trajectory(i, agent), trials.trajectory(i, 1 - agent)
        if not MIN_HISTORY - 1 <= t <= len(human) - 1 - HORIZON:
            raise ValueError(f"t = {t} is outside {MIN_HISTORY - 1}..{len(human) - 1 - HORIZON} for trial {i}")
        history = np.stack([robot[: t + 1], human[: t + 1]], axis=1)
        prediction = predictor.predict(history, robot[None, t + 1:t + 1 + HORIZON], samples, seed)
        futures = future_states(torch.as_tensor(human[t]), prediction.actions[:, 0].double().cpu()).numpy()  # [n, 15, 6]
        latents, values = prediction.latents[:, 0].cpu().numpy(), prediction.log_p_z.shape[-1]
        cmap = colormaps["tab20"] if values <= 20 else colormaps["turbo"]
        x_ahead = np.concatenate([robot[t:t + 1 + HORIZON, 0], human[t:t + 1 + HORIZON, 0], futures[..., 0].ravel()])
        # the last 2 s of history and everything predicted
        x_behind = min(robot[max(t - 20, 0), 0], human[max(t - 20, 0), 0])
        draw_road(ax, (x_behind - 3, x_ahead.max() + 5), float(futures[..., 1].min()))
        for k in range(samples):
            colour = cmap(latents[k] / max(values - 1, 1))
            ax.plot(np.r_[human[t, 0], futures[k, :, 0]], np.r_[human[t, 1], futures[k, :, 1]], color=colour, lw=0.8, alpha=0.8)
        ax.plot(robot[: t + 1, 0], robot[: t + 1, 1], color="0.25", lw=2.2, label="other car (robot) history")
        ax.plot(robot[t:t + 1 + HORIZON, 0], robot[t:t + 1 + HORIZON, 1], color="0.25", lw=1.6, ls="--", label="robot future (condition)")
        ax.plot(human[: t + 1, 0], human[: t + 1, 1], color="k", lw=2.2, label="human history")
        ax.plot(human[t:t + 1 + HORIZON, 0], human[t:t + 1 + HORIZON, 1], color="k", lw=1.2, ls=":", label="human recorded future")
        ax.set_ylabel("y (m)")
        ax.set_title(f"{trials.sources[i]} (trial {trials.trial_ids[i]}), human = agent {agent}, t = {t} "
                     f"({t * trials.dt:.1f} s): {samples} samples, colour = latent value", fontsize=9)
    axes[-1].set_xlabel("x (m)")
    axes[0].legend(loc="lower left", fontsize=7, ncol=4)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


def plot_validation_curves(histories: dict[str, list[tuple[int, float]]], path: str | os.PathLike,
                           reference: dict[str, float] | None = None) -> Path:
    """Validation NLL (nats, physical units) against training step for named runs; ``reference``
    draws horizontal lines (e.g. a model evaluated on the same exemplars)."""
    fig = Figure(figsize=(7, 4))
    ax = fig.subplots()
    for name, history in histories.items():
        steps, values = zip(*history)
        ax.plot(steps, values, marker=".", label=name)
    for name, value in (reference or {}).items():
        ax.axhline(value, color="0.4", ls="--", lw=1)
        ax.text(ax.get_xlim()[1], value, f" {name}", va="center", fontsize=8)
    return _finish_plot(fig, ax, "training step", "validation NLL (nats per exemplar)", path)


def _finish_plot(fig: Figure, ax, xlabel: str, ylabel: str, path: str | os.PathLike) -> Path:
    """Label the axes of the one-panel ``fig``, add its legend and a light grid, lay it out and
    save it to ``path``."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return _save(fig, path)
