"""Helpers shared by the human-model test modules (test_model, test_train, test_evaluate_metrics)."""

from trafficweaving.sim.generate import generate_trials
from trafficweaving.data.trials import TrialSet


def synthetic_trials(n: int, seed: int) -> TrialSet:
    """``n`` trials of the built-in synthetic drivers, seeded (no progress bar)."""
    trials, _ = generate_trials(n, seed=seed, progress=False)
    return trials
