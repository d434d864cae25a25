"""Closed-loop episodes drawn as the paper's Fig. 6: the robot (blue) and the human (red), their
longitudinal and lateral accelerations over time and their ``(x, y)`` paths (paper §V-D)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from ..data.trials import TrialSet
from ..scenario import DT
from .figures import _save, draw_road
from .scene import CAR_COLOURS


def plot_episode(trials: TrialSet, index: int, path: str | os.PathLike, title: str | None = None) -> Path:
    """Fig. 6 for trial ``index`` of ``trials`` (an episode log: agents labelled ``robot`` and
    ``human``; any two agents are drawn by their roles): ``xdd`` and ``ydd`` (m/s²) against time
    (s), and the ``(x, y)`` paths (m) with the road. Writes the PNG to ``path``."""
    if not 0 <= index < len(trials):
        raise ValueError(f"index {index} is outside 0..{len(trials) - 1}")
    length = int(trials.lengths[index])
    states = trials.states[index, :, :length]  # [2, T, 6]
    roles = [str(r) for r in trials.roles[index]]
    time = DT * np.arange(length)
    fig = Figure(figsize=(10, 6.5), constrained_layout=True)
    grid = fig.add_gridspec(2, 2, height_ratios=(1, 1.1))
    panels = [(fig.add_subplot(grid[0, 0]), 4, "longitudinal acceleration ẍ (m/s²)"),
              (fig.add_subplot(grid[0, 1]), 5, "lateral acceleration ÿ (m/s²)")]
    for ax, column, label in panels:
        for car, role in enumerate(roles):
            ax.plot(time, states[car, :, column], color=CAR_COLOURS.get(role, "0.4"), lw=1.5, label=role)
        ax.axhline(0.0, color="0.7", lw=0.8)
        ax.set_xlabel("time (s)")
        ax.set_ylabel(label)
        ax.legend(fontsize=8)
    ax = fig.add_subplot(grid[1, :])
    draw_road(ax, (float(np.nanmin(states[:, :, 0])) - 5.0, max(float(np.nanmax(states[:, :, 0])), 5.0) + 5.0),
              float(np.nanmin(states[:, :, 1])))
    for car, role in enumerate(roles):
        ax.plot(states[car, :, 0], states[car, :, 1], color=CAR_COLOURS.get(role, "0.4"), lw=2.0, label=role)
        ax.plot(states[car, 0, 0], states[car, 0, 1], "o", color=CAR_COLOURS.get(role, "0.4"))
    ax.set_xlabel("x: longitudinal position (m), 0 at the cutoff")
    ax.set_ylabel("y (m)")
    ax.legend(fontsize=8, loc="lower left")
    fig.suptitle(title or f"{trials.sources[index]}: robot (blue) and human (red)", fontsize=10)
    return _save(fig, path)
