"""Figures of datasets and of their statistics, drawn with matplotlib's Agg renderer (no display).

Every function draws one figure, saves it as a PNG atomically (temporary file in the destination
folder, then rename) and returns the path written.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Rectangle

from ..atomic import atomic_write
from ..data.behaviour import behaviour_samples, compare_behaviour
from ..data.stats import TABLE1_PAPER, left_car_in_front, table1
from ..data.trials import TrialSet
from ..scenario import LANE_CENTRE_Y, LANE_DIVIDER_Y, ROAD_END_X, ROAD_Y_MIN, TCO_VALUES

ROAD_EDGES_Y = (0.0, ROAD_Y_MIN)
"""Lines drawn as the road's outer edges (left edge, right validity limit), m."""
COLOURS = {"left": "tab:blue", "right": "tab:orange", "front": "tab:green", "behind": "tab:red",
           "sim": "tab:blue", "real": "tab:orange"}


def _save(fig: Figure, path: str | os.PathLike, dpi: int = 120) -> Path:
    """Write ``fig`` to ``path`` as PNG via a temporary file in the same folder, then rename."""
    with atomic_write(path) as f:
        fig.savefig(f, format="png", dpi=dpi)
    return Path(path)


def draw_road(ax, x_range: tuple[float, float], y_min: float) -> None:
    """Road edges, lane centres, divider and cutoff on an (x, y) axis."""
    for y in ROAD_EDGES_Y:
        ax.axhline(y, color="0.3", lw=1.2)
    for y in LANE_CENTRE_Y.values():
        ax.axhline(y, color="0.7", lw=0.8, ls=":")
    ax.axhline(LANE_DIVIDER_Y, color="0.45", lw=1.0, ls=(0, (8, 6)))
    ax.axvline(ROAD_END_X, color="k", lw=1.5)
    ax.text(ROAD_END_X, ROAD_EDGES_Y[0] + 0.15, "cutoff x = 0 ", va="bottom", ha="right", fontsize=8, clip_on=True)
    ax.set_xlim(*x_range)
    ax.set_ylim(min(ROAD_EDGES_Y[1], y_min) - 0.5, ROAD_EDGES_Y[0] + 0.8)


def _pick(trials: TrialSet, max_trials: int) -> np.ndarray:
    """At most ``max_trials`` trial indices evenly spread over the set; ValueError if it is empty."""
    if len(trials) == 0:
        raise ValueError("no trials to plot")
    return np.unique(np.linspace(0, len(trials) - 1, min(len(trials), max_trials)).round().astype(int))


def plot_trajectories(trials: TrialSet, path: str | os.PathLike, max_trials: int = 300) -> Path:
    """(x, y) paths (m) of both cars of up to ``max_trials`` trials (evenly spread over the set),
    coloured by whether the car that started in the left lane passed in front; the left-lane car
    drawn solid, the right-lane car dashed. Lanes, divider and the cutoff drawn."""
    picked = _pick(trials, max_trials)
    front = left_car_in_front(trials)
    fig = Figure(figsize=(12, 4.2), layout="constrained")
    ax = fig.add_subplot()
    alpha = float(np.clip(30.0 / max(len(picked), 1), 0.15, 0.8))
    x_min, x_max = np.nanmin(trials.states[picked, ..., 0]), np.nanmax(trials.states[picked, ..., 0])
    for i in picked:
        colour = COLOURS["left"] if front[i] else COLOURS["right"]
        for agent in (0, 1):
            traj = trials.trajectory(i, agent)
            ls = "-" if trials.start_lanes[i, agent] == "left" else "--"
            ax.plot(traj[:, 0], traj[:, 1], color=colour, ls=ls, lw=0.8, alpha=alpha)
    draw_road(ax, (min(x_min, -10.0) - 2.0, max(x_max, 5.0) + 2.0), np.nanmin(trials.states[picked, ..., 1]))
    n_left = int(front[picked].sum())
    ax.legend(handles=[
        Line2D([], [], color=COLOURS["left"], label=f"left-lane car passed in front ({n_left})"),
        Line2D([], [], color=COLOURS["right"], label=f"right-lane car passed in front ({len(picked) - n_left})"),
        Line2D([], [], color="0.2", ls="-", label="car that started left"),
        Line2D([], [], color="0.2", ls="--", label="car that started right"),
        Line2D([], [], color="0.45", ls=(0, (8, 6)), label=f"lane divider (y = {LANE_DIVIDER_Y} m)"),
    ], loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=8)
    ax.set_xlabel("x: longitudinal position (m), 0 at the cutoff")
    ax.set_ylabel("y: lateral position (m)")
    ax.set_title(f"Trajectories of both cars ({len(picked)} of {len(trials)} trials)")
    return _save(fig, path)


def plot_profiles(trials: TrialSet, path: str | os.PathLike, max_trials: int = 300) -> Path:
    """Speed (m/s), longitudinal and lateral acceleration (m/s²) against x (m) of every car, coloured
    by whether it ended in front of the other car (at the step both have swapped lanes) or behind:
    thin translucent lines for up to ``max_trials`` trials, bold medians over all trials on a 1 m
    grid of x (where at least a quarter of the group's cars, and 3, were recorded)."""
    picked = set(_pick(trials, max_trials).tolist())
    n = len(trials)
    front_left = left_car_in_front(trials)
    left_agent = (trials.start_lanes[:, 1] == "left").astype(int)
    front_agent = np.where(front_left, left_agent, 1 - left_agent)  # [n]
    fig = Figure(figsize=(11, 8.5), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    quantities = [(2, "speed xd (m/s)"), (4, "longitudinal accel. xdd (m/s²)"), (5, "lateral accel. ydd (m/s²)")]
    alpha = float(np.clip(20.0 / max(len(picked), 1), 0.08, 0.6))
    grid = np.arange(np.floor(np.nanmin(trials.states[..., 0])), np.nanmax(trials.states[..., 0]) + 1.0)
    on_grid = {"front": [], "behind": []}
    for i in range(n):
        for agent in (0, 1):
            group = "front" if agent == front_agent[i] else "behind"
            traj = trials.trajectory(i, agent)
            inside = (grid >= traj[0, 0]) & (grid <= traj[-1, 0])
            on_grid[group].append(np.stack([np.where(inside, np.interp(grid, traj[:, 0], traj[:, k]), np.nan)
                                            for k, _ in quantities]))
            if i in picked:
                for ax, (k, _) in zip(axes, quantities):
                    ax.plot(traj[:, 0], traj[:, k], color=COLOURS[group], lw=0.6, alpha=alpha)
    for group, curves in on_grid.items():
        stacked = np.stack(curves)  # [cars, 3, grid], NaN outside each car's recorded x range
        enough = np.isfinite(stacked[:, 0]).sum(axis=0) >= max(3, len(curves) // 4)
        median = np.nanmedian(stacked[:, :, enough], axis=0)  # [3, grid points kept]
        for ax, row in zip(axes, median):
            ax.plot(grid[enough], row, color=COLOURS[group], lw=2.5)
    for ax, (_, label) in zip(axes, quantities):
        ax.axvline(ROAD_END_X, color="k", lw=1.2)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(handles=[
        Line2D([], [], color=COLOURS["front"], label="car that ended in front"),
        Line2D([], [], color=COLOURS["behind"], label="car that ended behind"),
        Line2D([], [], color="0.3", lw=2.5, label="median (bold)"),
        Line2D([], [], color="k", lw=1.2, label="cutoff x = 0"),
    ], fontsize=8, loc="best")
    axes[-1].set_xlabel("x: longitudinal position (m)")
    axes[0].set_title(f"Speed and acceleration profiles ({len(picked)} of {n} trials drawn, medians over all)")
    return _save(fig, path)


def plot_table1(table: dict, path: str | os.PathLike, reference: dict = TABLE1_PAPER,
                counts: dict | None = None) -> Path:
    """Heat map of Table I: rows tco 1, 2, 3 s; columns Δv = -2, 0, +2 m/s (Δv = 0 one merged cell
    over all tco). Each cell shows the fraction of trials where the left-lane car passed in front
    and the reference (paper) value; ``table`` and ``reference`` (and the optional trial ``counts``)
    have the shape of ``stats.table1(...)["table1"]``."""
    fig = Figure(figsize=(7.5, 5.2), layout="constrained")
    ax = fig.add_subplot()
    cmap = colormaps["RdBu_r"]
    norm = Normalize(0.0, 1.0)
    rows = [str(int(c)) for c in TCO_VALUES]
    for col, dv in enumerate(("-2", "0", "2")):
        cells = [("all", 0, len(rows))] if dv == "0" else [(r, k, 1) for k, r in enumerate(rows)]
        for key, row, height in cells:
            value = table.get(dv, {}).get(key)
            ref = reference.get(dv, {}).get(key)
            face = cmap(norm(value)) if value is not None else (0.9, 0.9, 0.9, 1.0)
            ax.add_patch(Rectangle((col, row), 1, height, facecolor=face, edgecolor="white", lw=3))
            text = "no trials" if value is None else f"{100 * value:.1f} %"
            if ref is not None:
                text += f"\n(paper {100 * ref:.1f} %)"
            if counts is not None and counts.get(dv, {}).get(key) is not None:
                text += f"\nn = {counts[dv][key]}"
            dark = value is not None and abs(value - 0.5) > 0.3
            ax.text(col + 0.5, row + height / 2, text, ha="center", va="center", fontsize=11,
                    color="white" if dark else "black")
    ax.set_xlim(0, 3)
    ax.set_ylim(len(rows), 0)
    ax.set_xticks([0.5, 1.5, 2.5], ["Δv = -2 m/s", "Δv = 0 (all tco)", "Δv = +2 m/s"])
    ax.set_yticks([0.5, 1.5, 2.5], [f"tco = {r} s" for r in rows])
    ax.tick_params(length=0)
    for side in ax.spines.values():
        side.set_visible(False)
    fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=ax, label="left-lane car passes in front (fraction)")
    ax.set_title("Table I: left-lane car passes in front (Δv = v_left − v_right)")
    return _save(fig, path)


def plot_behaviour(sim: dict, real: dict, path: str | os.PathLike,
                   labels: tuple[str, str] = ("simulated", "real HITL")) -> Path:
    """Density histograms of two dicts of ``behaviour_samples`` (1-D arrays per statistic), one panel
    per statistic present in both, overlaid, with the Wasserstein distance (of the full samples) in
    each title. Bins span the pooled 0.5–99.5 percentiles so that a few extreme values do not
    flatten the panel; values outside are not drawn."""
    comparison = compare_behaviour(sim, real)
    names = list(comparison)
    cols = 3 if len(names) > 4 else max(len(names), 1)
    rows = -(-len(names) // cols) if names else 1
    fig = Figure(figsize=(4.2 * cols, 3.2 * rows), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax, name in zip(axes, names):
        a, b = np.asarray(sim[name], float), np.asarray(real[name], float)
        row = comparison[name]
        unit = row["unit"]
        pooled = np.concatenate([a, b])
        if pooled.size == 0:
            ax.text(0.5, 0.5, "no samples", ha="center", va="center", transform=ax.transAxes)
        else:
            lo, hi = np.percentile(pooled, [0.5, 99.5])
            if hi - lo < 1e-6:  # a (nearly) constant sample still gets a readable bin
                lo, hi = lo - 0.5, hi + 0.5
            bins = np.linspace(lo, hi, int(np.clip(np.sqrt(pooled.size), 10, 60)) + 1)
            for sample, key, label in ((a, "sim", labels[0]), (b, "real", labels[1])):
                if ((sample >= lo) & (sample <= hi)).any():  # density of an empty range is undefined
                    ax.hist(sample, bins=bins, density=True, histtype="stepfilled",
                            alpha=0.35, color=COLOURS[key], edgecolor=COLOURS[key], lw=1.2,
                            label=f"{label} (n = {sample.size})")
            ax.legend(fontsize=7)
        w, ws = row["wasserstein"], row["wasserstein_over_std"]
        w_text = "W = –" if w is None else f"W = {w:.3g} {unit}" + ("" if ws is None else f" ({ws:.2f} σ)")
        ax.set_title(f"{name}\n{w_text}", fontsize=10)
        ax.set_xlabel(f"{name.replace('_', ' ')} ({unit})" if unit else name.replace("_", " "))
        ax.set_ylabel(f"density (1/{unit})" if unit else "density")
    for ax in axes[len(names):]:
        ax.set_visible(False)
    fig.suptitle(f"Driving behaviour: {labels[0]} vs {labels[1]} (σ: std of {labels[1]})")
    return _save(fig, path)


def write_dataset_figures(trials: TrialSet, out: str | os.PathLike, reference: TrialSet | None = None) -> list[Path]:
    """Write the dataset figures into folder ``out`` (created if needed): trajectories, speed and
    acceleration profiles, Table I, and the humans' behaviour against ``reference`` when given.
    Returns the paths written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = [plot_trajectories(trials, out / "trajectories.png"), plot_profiles(trials, out / "profiles.png"),
             plot_table1(table1(trials)["table1"], out / "table1.png")]
    if reference is not None:
        paths.append(plot_behaviour(behaviour_samples(trials, "human"), behaviour_samples(reference, "human"),
                                    out / "behaviour_vs_reference.png"))
    return paths
