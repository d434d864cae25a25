"""Figures of the planner: the paper's Fig. 4 (every candidate robot future) and Fig. 5 (the chosen
sequence with its predicted human responses beside braking and accelerating alternatives)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from ..planning.candidates import ACCELERATIONS, STEPS_PER_WINDOW, Action, action_sequences, robot_candidates
from ..planning.costs import Cost
from ..planning.planner import Planner
from .figures import draw_road, _save


def plot_candidates(starts: list[tuple[np.ndarray, int, str]], path: str | os.PathLike) -> Path:
    """One panel per ``(robot present state [6], fixed first action, label)``: every candidate's
    ``(x, y)`` path over the 1.5 s horizon, the fixed first window drawn darker."""
    fig = Figure(figsize=(11, 2.4 * len(starts) + 0.4))
    axes = fig.subplots(len(starts), 1, squeeze=False)[:, 0]
    for ax, (present, first, label) in zip(axes, starts):
        c = robot_candidates(present, first)
        x = np.concatenate([np.full((len(c), 1), present[0]), c.states[..., 0]], axis=1)
        y = np.concatenate([np.full((len(c), 1), present[1]), c.states[..., 1]], axis=1)
        draw_road(ax, (present[0] - 5, x.max() + 5), float(y.min()))
        ax.plot(x.T, y.T, color="tab:blue", lw=0.3, alpha=0.15)
        ax.plot(x[0, :STEPS_PER_WINDOW + 1], y[0, :STEPS_PER_WINDOW + 1], color="k", lw=2.0, label=f"fixed first window: {Action(first).acceleration:+.0f} m/s², {Action(first).lane} lane")
        ax.plot(present[0], present[1], "ko")
        ax.set_title(f"{label}: {len(c)} candidate robot futures (1.5 s)", fontsize=9)
        ax.set_ylabel("y (m)")
        ax.legend(loc="lower left", fontsize=7)
    axes[-1].set_xlabel("x (m)")
    fig.tight_layout()
    return _save(fig, path)


def plot_plan(planner: Planner, history: np.ndarray, first_action: int, cost: Cost, path: str | os.PathLike,
              samples: int = 64, scoring_samples: int = 1024) -> Path:
    """Plan from ``history [t+1, 2, 6]``; draw the chosen robot future with ``samples`` predicted
    human responses, beside the same lane choices with the hardest braking and with accelerating
    (the lowest and highest :data:`~trafficweaving.planning.candidates.ACCELERATIONS`) in every free
    window, each with its expected cost from ``scoring_samples`` futures."""
    plan = planner.plan(history, first_action, cost)
    sequences = action_sequences(first_action)
    lanes = [Action(int(a)).lane for a in plan.actions[1:]]

    def variant(acceleration: float) -> int:
        wanted = [first_action] + [Action.of(acceleration, lane).index for lane in lanes]
        return int(np.flatnonzero((sequences == wanted).all(1))[0])

    picks = [("chosen", plan.index), ("braking", variant(min(ACCELERATIONS))), ("accelerating", variant(max(ACCELERATIONS)))]
    costs, human = planner.score(history, first_action, cost, [i for _, i in picks], scoring_samples)
    fig = Figure(figsize=(11, 7.4))
    axes = fig.subplots(3, 1)
    robot_hist, human_hist = history[:, 0], history[:, 1]
    for k, (ax, (name, index)) in enumerate(zip(axes, picks)):
        robot = np.concatenate([history[-1:, 0], plan.candidates.states[index]])
        futures = human[:samples, k]
        x_all = np.concatenate([robot[:, 0], futures[..., 0].ravel(), robot_hist[-15:, 0], human_hist[-15:, 0]])
        draw_road(ax, (x_all.min() - 3, x_all.max() + 3), float(min(futures[..., 1].min(), robot[:, 1].min())))
        for f in futures:
            ax.plot(np.r_[human_hist[-1, 0], f[:, 0]], np.r_[human_hist[-1, 1], f[:, 1]], color="tab:orange", lw=0.6, alpha=0.5)
        ax.plot(human_hist[-15:, 0], human_hist[-15:, 1], color="tab:orange", lw=2.2, label="human history")
        ax.plot(robot_hist[-15:, 0], robot_hist[-15:, 1], color="tab:blue", lw=2.2, label="robot history")
        ax.plot(robot[:, 0], robot[:, 1], color="tab:blue", lw=1.8, ls="--", marker=".", label="robot future")
        accels = ", ".join(f"{Action(int(a)).acceleration:+.0f}{Action(int(a)).lane[0].upper()}" for a in plan.candidates.actions[index])
        ax.set_title(f"{name}: windows [{accels}], expected cost {costs[k]:.0f} ({scoring_samples} samples)", fontsize=9)
        ax.set_ylabel("y (m)")
    axes[0].legend(loc="lower left", fontsize=7, ncol=3)
    axes[-1].set_xlabel("x (m)")
    fig.tight_layout()
    return _save(fig, path)
