"""Figures of ``trafficweaving report`` (:mod:`trafficweaving.report`): closed-loop scores, the
models' NLL by direction and the agents' realism, drawn from plain numbers so that the same
numbers give the same PNG bytes."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from .figures import _save
from .model_figures import _finish_plot

MARKERS = "osD^vPX*<>"
"""Marker per series, in turn."""

DIRECTION_NAMES = {"x": "x (longitudinal)", "y": "y (lateral)"}


def short_spec(spec: str) -> str:
    """An agent spec for a tick label: every path in it cut to its file name
    (``model:authors:/a/b/weights.npz`` -> ``model:authors:weights.npz``)."""
    return ":".join(Path(part).name if "/" in part else part for part in spec.split(":"))


def plot_scores_by_human(points: list[dict], path: str | os.PathLike) -> Path:
    """The closed-loop score's mean and 95 % interval per human (x, sorted), one marker series
    per robot. ``points``: dicts with ``series`` (the robot's name), ``human``, ``mean`` and
    ``ci95`` (``[low, high]`` or None: no bar); a point with mean None is left out."""
    humans = sorted({p["human"] for p in points})
    series = sorted({p["series"] for p in points})
    width = 0.6 / max(len(series), 1)
    fig = Figure(figsize=(max(5.0, 1.6 * len(humans) + 2), 4))
    ax = fig.subplots()
    for k, name in enumerate(series):
        mine = [p for p in points if p["series"] == name and p["mean"] is not None]
        x = np.array([humans.index(p["human"]) for p in mine], dtype=float) + (k - (len(series) - 1) / 2) * width
        mean = np.array([p["mean"] for p in mine], dtype=float)
        low = np.array([p["mean"] - p["ci95"][0] if p["ci95"] else 0.0 for p in mine])
        high = np.array([p["ci95"][1] - p["mean"] if p["ci95"] else 0.0 for p in mine])
        ax.errorbar(x, mean, yerr=[low, high], fmt=MARKERS[k % len(MARKERS)], capsize=3, label=name)
    ax.set_xticks(np.arange(len(humans)), [short_spec(h) for h in humans])
    ax.set_xlim(-0.5, len(humans) - 0.5)
    ax.set_title("closed-loop score per human, 95 % interval", fontsize=10)
    return _finish_plot(fig, ax, "human", "score (0 to 1)", path)


def plot_nll_by_direction(models: list[tuple[str, dict]], path: str | os.PathLike) -> Path:
    """Exact NLL per direction (nats per instance, 15 accelerations each), grouped bars per
    model. ``models``: ``(name, {"x": nll, "y": nll})`` in the order drawn (None: no bar)."""
    fig = Figure(figsize=(max(5.0, 1.2 * len(models) + 2), 4))
    ax = fig.subplots()
    for d, (direction, name) in enumerate(DIRECTION_NAMES.items()):
        values = [np.nan if v.get(direction) is None else v[direction] for _, v in models]
        ax.bar(np.arange(len(models)) + (d - 0.5) * 0.4, values, 0.4, label=name)
    ax.set_xticks(np.arange(len(models)), [name for name, _ in models], fontsize=8)
    ax.set_xlim(-0.7, len(models) - 0.3)
    ax.axhline(0, color="0.3", lw=0.8)
    ax.set_title("exact NLL by direction", fontsize=10)
    return _finish_plot(fig, ax, "model", "exact NLL (nats per instance)", path)


def plot_realism(agents: list[tuple[str, dict]], path: str | os.PathLike) -> Path:
    """The realism score and its parts (0 to 1), grouped bars per agent. ``agents``: ``(name,
    {part: value})`` in the order drawn; every agent's parts drawn in the first agent's order."""
    parts = list(agents[0][1]) if agents else []
    width = 0.8 / max(len(parts), 1)
    fig = Figure(figsize=(max(5.0, 1.5 * len(agents) + 2), 4))
    ax = fig.subplots()
    for k, part in enumerate(parts):
        values = [np.nan if v.get(part) is None else v[part] for _, v in agents]
        ax.bar(np.arange(len(agents)) + (k - (len(parts) - 1) / 2) * width, values, width, label=part)
    ax.set_xticks(np.arange(len(agents)), [name for name, _ in agents], fontsize=8)
    ax.set_xlim(-0.7, len(agents) - 0.3)
    ax.set_ylim(0, 1)
    ax.set_title("realism and its parts", fontsize=10)
    return _finish_plot(fig, ax, "human agent", "likelihood of the real driving (0 to 1)", path)
