"""Calibration of a trained human model's predictive spread, chosen on out-of-fold predictions.

Two scalars, buffers of :class:`~trafficweaving.model.cvae.CVAE` used by its density and by all
sampling alike: the **latent temperature** (divides the p(z|x) logits: more weight on the less
likely modes) and the **output scale** (multiplies every width of the per-step output, GMM
components and hold modes). A model fine-tuned on few trials is too sure of itself on new drivers;
these two knobs widen it without retraining.

They are chosen on the out-of-fold models of ``trafficweaving crossval --out DIR`` (each trial
predicted by the fold model that did not train on it): among the settings of a grid whose 90 %
position intervals 1.5 s ahead cover between 85 % and 95 % of the real positions in both
directions, the one with the best out-of-fold exact NLL (if none does, the one whose worse
direction is closest to 90 %). The chosen setting is then applied to the model trained on every
fold. The choice is made on the same out-of-fold predictions it is scored on: two scalars over
hundreds of instances, a small optimism.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..data.trials import TrialSet
from .crossval import out_of_fold_models
from .exemplars import build_exemplars
from .metrics import InstanceMetrics, evaluate_instances

TEMPERATURES = (1.0, 2.0, 5.0)
SCALES = (1.0, 1.4, 1.7, 2.0, 2.5)
COVERAGE_BAND = (0.85, 0.95)
"""Accepted coverage of the nominal 90 % position interval 1.5 s ahead, per direction."""


@dataclass
class Calibration:
    """``grid``: one dict per setting (``latent_temperature``, ``output_scale``, ``nll_exact``,
    ``coverage_90`` ``{"x", "y"}`` at 1.5 s, ``min_ade_m``), out-of-fold; ``chosen``: its index."""

    grid: list[dict]
    chosen: int

    def summary(self) -> dict:
        return {**self.grid[self.chosen], "grid": self.grid, "coverage_band": list(COVERAGE_BAND)}


def _choose(grid: list[dict]) -> int:
    low, high = COVERAGE_BAND
    inside = [k for k, g in enumerate(grid) if all(low <= c <= high for c in g["coverage_90"].values())]
    if inside:
        return min(inside, key=lambda k: grid[k]["nll_exact"])
    return min(range(len(grid)), key=lambda k: max(abs(c - 0.9) for c in grid[k]["coverage_90"].values()))


def calibrate(trials: TrialSet, folds: str, temperatures=TEMPERATURES, scales=SCALES, samples: int = 100,
              seed: int = 0, log: Callable[[str], None] = print) -> Calibration:
    """Score every (temperature, scale) of the grid on the out-of-fold models in folder ``folds``
    (written by ``crossval --out`` on ``trials``) and choose one (module docstring)."""
    models = out_of_fold_models(folds)
    subsets = [trials.subset(np.flatnonzero(np.isin(trials.trial_ids, held))) for _, held in models]
    grid = []
    for temperature in temperatures:
        for scale in scales:
            parts = [evaluate_instances(model.set_calibration(temperature, scale), fold, build_exemplars(fold),
                                        samples=samples, ade_samples=20, seed=seed)
                     for (model, _), fold in zip(models, subsets)]
            s = InstanceMetrics.concatenate(parts).summary()
            row = {"latent_temperature": temperature, "output_scale": scale, "nll_exact": s["nll_exact"],
                   "coverage_90": {d: s["coverage"][d]["1.5"]["90"] for d in ("x", "y")}, "min_ade_m": s["min_ade_m"]}
            grid.append(row)
            log(f"temperature {temperature:g}, scale {scale:g}: out-of-fold NLL {row['nll_exact']:.2f}, 90 % coverage "
                f"at 1.5 s x {100 * row['coverage_90']['x']:.0f} %, y {100 * row['coverage_90']['y']:.0f} %")
    return Calibration(grid, _choose(grid))
