"""One moment of an episode drawn as an image: the road and both cars (robot blue, human red, as
the paper's Fig. 6), for environment rendering and episode animations."""

from __future__ import annotations

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from ..scenario import CAR_LENGTH, CAR_WIDTH
from .figures import draw_road

CAR_COLOURS = {"robot": "tab:blue", "human": "tab:red"}
"""Colour of each role (the paper's Fig. 6)."""


def render_scene(states: np.ndarray, roles: tuple[str, str], window: tuple[float, float] = (-40.0, 25.0),
                 size: tuple[int, int] = (640, 200), title: str | None = None) -> np.ndarray:
    """The cars ``states [2, 6]`` (``[x, y, xd, yd, xdd, ydd]``, m, m/s, m/s²) labelled ``roles``
    (``"robot"``/``"human"``), seen from ``window`` metres behind/ahead of the cars' mean ``x``,
    as an RGB image ``[height, width, 3]`` (uint8) of ``size`` (width, height) pixels."""
    states = np.asarray(states, dtype=float)
    centre = float(states[:, 0].mean())
    fig = Figure(figsize=(size[0] / 100, size[1] / 100), dpi=100)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.02, 0.08, 0.96, 0.8 if title else 0.88))
    draw_road(ax, (centre + window[0], centre + window[1]), float(states[:, 1].min()))
    for state, role in zip(states, roles):
        ax.add_patch(Rectangle((state[0] - CAR_LENGTH / 2, state[1] - CAR_WIDTH / 2), CAR_LENGTH, CAR_WIDTH,
                               color=CAR_COLOURS[role], zorder=3))
    ax.set_yticks([])
    ax.tick_params(labelsize=7)
    if title:
        ax.set_title(title, fontsize=8)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()
