"""Helpers shared by the human-model test modules (test_model, test_train, test_evaluate_metrics, the
fine-tuning, cross-validation and calibration workflows of test_fine_tune_recipe and test_cli)."""

from pathlib import Path

import torch

from trafficweaving.data.trials import TrialSet
from trafficweaving.model.checkpoint import save_checkpoint
from trafficweaving.model.cvae import CVAE, CVAEConfig
from trafficweaving.model.exemplars import state_statistics
from trafficweaving.sim.generate import generate_trials

SMALL_UNITS = {"history_units": 8, "future_units": 8, "decoder_units": 16, "p_z_hidden": 8}
"""Layer widths of a small model: the workflows run at a fraction of the paper model's cost, while the
variant (latent variables, components, hold modes) and so every code path stay the paper's."""


def synthetic_trials(n: int, seed: int) -> TrialSet:
    """``n`` trials of the built-in synthetic drivers, seeded (no progress bar)."""
    trials, _ = generate_trials(n, seed=seed, progress=False)
    return trials


def small_model(trials: TrialSet, variant: str = "cvae-hold", seed: int = 0) -> CVAE:
    """An untrained ``variant`` model of :data:`SMALL_UNITS` (weights seeded), standardised for ``trials``."""
    torch.manual_seed(seed)
    return CVAE(CVAEConfig.variant(variant, **SMALL_UNITS)).set_standardisation(*state_statistics(trials))


def small_checkpoint(path: Path, trials: TrialSet, variant: str = "cvae-hold", seed: int = 0) -> Path:
    """:func:`small_model` saved at ``path`` (a model to fine-tune with ``--init`` or to calibrate)."""
    save_checkpoint(path, small_model(trials, variant, seed))
    return path
