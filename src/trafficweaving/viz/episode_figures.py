"""Closed-loop episodes drawn as the paper's Fig. 6: the robot (blue) and the human (red), their
longitudinal and lateral accelerations over time and their ``(x, y)`` paths (paper §V-D)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from ..data.trials import TrialSet, load_trials
from ..errors import InputError
from ..scenario import DT
from .figures import _save, draw_road
from .scene import CAR_COLOURS

MAX_ANIMATION_STEPS = 1000
"""Longest trial animated (100 s; episodes last at most 11 s): its frames are held in memory
(about 0.7 MB each at the default size) until the GIF is written."""


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


def animate_episode(states: np.ndarray, roles: tuple[str, str], path: str | os.PathLike,
                    plans: list[tuple[int, np.ndarray, np.ndarray]] = (), size: tuple[int, int] = (800, 300),
                    title: str = "") -> Path:
    """An animated GIF of an episode, one frame per step (10 frames/s): the road, both cars
    ``states [2, T, 6]`` (their past paths drawn thin) coloured by ``roles``, and at each
    replanning the robot's chosen future and the human futures it sampled: ``plans`` lists
    ``(t, robot_future [15, 6], human_futures [n, 15, 6])`` by the step ``t`` each plan was made
    at; a plan stays drawn until the next. Written atomically to ``path``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.patches import Rectangle
    from PIL import Image

    from ..atomic import atomic_write
    from ..scenario import CAR_LENGTH, CAR_WIDTH

    states = np.asarray(states, dtype=float)
    steps = states.shape[1]
    by_step = sorted(plans, key=lambda p: p[0])
    y_min = float(np.nanmin(states[:, :, 1]))
    frames = []
    fig = Figure(figsize=(size[0] / 100, size[1] / 100), dpi=100)  # one figure, cleared every frame
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.06, 0.15, 0.92, 0.72))
    for t in range(steps):
        ax.clear()
        centre = float(states[:, t, 0].mean())
        draw_road(ax, (centre - 45.0, centre + 35.0), y_min)
        current = [p for p in by_step if p[0] <= t]
        if current:
            made, robot_future, human_futures = current[-1]
            for future in human_futures:
                ax.plot(future[:, 0], future[:, 1], color=CAR_COLOURS["human"], lw=0.6, alpha=0.25)
            ax.plot(robot_future[:, 0], robot_future[:, 1], color=CAR_COLOURS["robot"], lw=2.0, ls="--")
        for car, role in enumerate(roles):
            colour = CAR_COLOURS.get(role, "0.4")
            ax.plot(states[car, : t + 1, 0], states[car, : t + 1, 1], color=colour, lw=1.0)
            ax.add_patch(Rectangle((states[car, t, 0] - CAR_LENGTH / 2, states[car, t, 1] - CAR_WIDTH / 2),
                                   CAR_LENGTH, CAR_WIDTH, color=colour, zorder=3))
        plan_text = f"; plan made at {made * DT:.1f} s" if current else ""
        ax.set_title(f"{title}  t = {t * DT:.1f} s{plan_text}".strip(), fontsize=9)
        ax.set_xlabel("x (m)", fontsize=8)
        ax.tick_params(labelsize=7)
        canvas.draw()
        frames.append(Image.fromarray(np.asarray(canvas.buffer_rgba())[..., :3].copy()))
    with atomic_write(path) as f:
        frames[0].save(f, format="GIF", save_all=True, append_images=frames[1:], duration=round(1000 * DT), loop=0)
    return Path(path)


def episode_figures(data: str, trial: int, out: Path, gif: Path | None = None) -> dict:
    """Fig. 6 of trial ``trial`` of the dataset or episode log ``data`` at ``out`` (PNG) and, with
    ``gif``, its animation; an episode log is run again to draw each plan's chosen future and
    sampled human futures. Returns the written paths (``figure``, ``animation``) and
    ``plans_drawn``."""
    trials = load_trials(data)
    if trial >= len(trials):
        raise InputError(f"--trial {trial}: {data} has {len(trials)} trials (expected 0..{len(trials) - 1})")
    length = int(trials.lengths[trial])
    plans = None
    if gif is not None:
        if length > MAX_ANIMATION_STEPS:
            raise InputError(f"--gif: trial {trial} of {data} has {length} steps (expected at most "
                             f"{MAX_ANIMATION_STEPS}, one frame each)")
        if "episode" in trials.metadata:
            from ..sim.episodes import rerun_with_plans

            plans = rerun_with_plans(trials)
    payload = {"figure": str(plot_episode(trials, trial, out))}
    if gif is not None:
        roles = tuple(str(r) for r in trials.roles[trial])
        payload["animation"] = str(animate_episode(trials.states[trial, :, :length], roles, gif, plans or [],
                                                   title=str(trials.sources[trial])))
        payload["plans_drawn"] = len(plans or [])
    return payload
