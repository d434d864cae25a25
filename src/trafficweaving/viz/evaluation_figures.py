"""Figures comparing human models instance by instance (:class:`~trafficweaving.model.metrics.InstanceMetrics`):
coverage calibration, NLL by lane-change phase, and NLL per trial."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from ..model.metrics import DIRECTIONS, HORIZON_STEPS, PHASES, InstanceMetrics, horizon_key
from .figures import _save
from .model_figures import _finish_plot


def plot_coverage_calibration(results: dict[str, InstanceMetrics], path: str | os.PathLike,
                              step: int = HORIZON_STEPS[-1]) -> Path:
    """Empirical against nominal coverage of the central intervals of sampled positions,
    ``step`` steps ahead, one panel per direction, one line per named model."""
    h = HORIZON_STEPS.index(step)
    fig = Figure(figsize=(9, 4.2))
    for d, ax in enumerate(fig.subplots(1, len(DIRECTIONS))):
        ax.plot([0, 1], [0, 1], color="0.5", ls="--", lw=1, label="nominal")
        for name, metrics in results.items():
            levels = np.array(metrics.levels)
            ax.plot(levels, metrics.covered[metrics.sampled][:, d, h].mean(axis=0), marker="o", label=name)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.set_aspect("equal")
        ax.set_xlabel("nominal coverage of the central interval")
        ax.set_ylabel("empirical coverage")
        ax.set_title(f"{'longitudinal x' if d == 0 else 'lateral y'} position, {horizon_key(step)} s ahead", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def plot_nll_by_phase(results: dict[str, InstanceMetrics], path: str | os.PathLike) -> Path:
    """Mean exact NLL per lane-change phase (phases with instances), grouped bars per named model."""
    phases = [p for p in PHASES if any((m.phase == p).any() for m in results.values())]
    fig = Figure(figsize=(7, 4))
    ax = fig.subplots()
    width = 0.8 / len(results)
    for k, (name, metrics) in enumerate(results.items()):
        values = [metrics.evaluation.nll_exact[metrics.phase == p].mean() for p in phases]
        ax.bar(np.arange(len(phases)) + (k - (len(results) - 1) / 2) * width, values, width, label=name)
    counts = [int((next(iter(results.values())).phase == p).sum()) for p in phases]
    ax.set_xticks(np.arange(len(phases)), [f"{p}\n(n = {n})" for p, n in zip(phases, counts)])
    ax.axhline(0, color="0.3", lw=0.8)
    ax.set_ylabel("exact NLL (nats per instance)")
    ax.set_title("NLL by phase of the human's lane change", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    return _save(fig, path)


def plot_nll_per_trial(results: dict[str, InstanceMetrics], path: str | os.PathLike) -> Path:
    """Mean exact NLL of each trial's instances, one marker series per named model, trials in
    the order of the first model's NLL."""
    first = next(iter(results.values()))
    trials = np.unique(first.trial_id)
    per_trial = {name: np.array([m.evaluation.nll_exact[m.trial_id == i].mean() for i in trials])
                 for name, m in results.items()}
    order = np.argsort(per_trial[next(iter(results))])
    fig = Figure(figsize=(9, 4))
    ax = fig.subplots()
    for name, values in per_trial.items():
        ax.plot(np.arange(len(trials)), values[order], marker="o", ls="none", label=name)
    ax.set_xticks(np.arange(len(trials)), [str(i) for i in trials[order]], fontsize=7)
    return _finish_plot(fig, ax, "trial id (sorted by the first model's NLL)", "mean exact NLL (nats per instance)", path)
