"""Calibration of a trained human model's predictive spread, chosen on out-of-fold predictions.

Buffers of :class:`~trafficweaving.model.cvae.CVAE` used by its density and by all sampling
alike: the **latent temperature** (divides the p(z|x) logits: more weight on the less likely
modes) and the **output scale**, one per direction (multiplies the widths of the per-step GMM's
components in x and in y; not the hold modes', which measure how exactly a held control is held).
A model fine-tuned on few trials is too sure of itself on new drivers; these knobs widen it
without retraining.

They are chosen on the out-of-fold models of ``trafficweaving crossval --out DIR`` (each trial
predicted by the fold model that did not train on it). A grid of temperatures and scales (the
same in both directions) is scored; a direction's coverage and NLL depend on the temperature and
that direction's scale alone, so for each temperature each direction's scale is chosen on its
own (the best NLL of that direction among the scales whose 90 % position intervals 1.5 s ahead
cover 85–95 % of the real positions in it; if none does, the closest to 90 %), and that
per-direction setting is scored too. Among all scored settings, the one with the best out-of-fold
exact NLL whose coverage is in the band in both directions is chosen (if none is, the one whose
worse direction is closest to 90 %). The chosen setting is then applied to the model trained on every
fold. Several cross-validation folders are candidate recipes: the recipe is chosen first, by
likelihood (the best uncalibrated out-of-fold exact NLL), then its calibration by the rule above
(coverage is a property the calibration fixes, not a reason to prefer a worse recipe).

With a **companion** model (``calibrate --companion authors:PATH``: the authors' published model,
trained on 1105 real trials and none of these), the calibrated model is last mixed with it,
``w · calibrated + (1 - w) · companion`` (:class:`~trafficweaving.model.mixture.Mixture`), ``w`` from
:data:`MIX_WEIGHTS` by the same rule (1: no mixture), out-of-fold like the rest.

That choice is made on the same out-of-fold predictions it is scored on, a small optimism. The
nested estimate (:func:`calibrate_nested`, ``calibrate --nested``) removes it: each outer fold's
recipe, steps and calibration are chosen on its inner folds alone, as a new trial would meet them.
"""

from __future__ import annotations

import copy
import multiprocessing
from concurrent.futures import Executor, ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..data.trials import TrialSet
from .crossval import out_of_fold_models
from .cvae import CVAE
from .exemplars import build_exemplars
from .evaluate import evaluate
from .metrics import InstanceMetrics, evaluate_instances
from .mixture import Mixture, companion_for

TEMPERATURES = (1.0, 2.0, 5.0)
SCALES = (1.0, 1.2, 1.4, 1.7, 2.0, 2.5, 3.0)
MIX_WEIGHTS = (0.95, 0.9, 0.8, 0.7, 0.5)
"""Weights of the calibrated model in its mixture with a companion, tried after the calibration
(1, no mixture, is the calibration's own row)."""
COVERAGE_BAND = (0.85, 0.95)
"""Accepted coverage of the nominal 90 % position interval 1.5 s ahead, per direction."""


def scale_of(row: dict) -> tuple[float, float]:
    """The output scale ``(x, y)`` of a grid row."""
    return row["output_scale"]["x"], row["output_scale"]["y"]


@dataclass
class Calibration:
    """``grid``: one dict per setting of the chosen candidate (``candidate`` index into the fold
    folders, ``latent_temperature``, ``output_scale`` ``{"x", "y"}``, ``mixture_weight`` (1: no
    companion), ``nll_exact``, ``nll_exact_by_direction``,
    ``coverage_90`` ``{"x", "y"}`` at 1.5 s, ``min_ade_m``), out-of-fold; ``chosen``: its index;
    ``candidates_nll_exact``: every candidate's uncalibrated out-of-fold NLL; ``nested``: the
    nested estimate (:func:`calibrate_nested`) or None."""

    grid: list[dict]
    chosen: int
    candidates_nll_exact: list[float]
    nested: dict | None = None

    def summary(self) -> dict:
        return {**self.grid[self.chosen], "grid": self.grid, "candidates_nll_exact": self.candidates_nll_exact,
                "coverage_band": list(COVERAGE_BAND), "nested": self.nested}


def _in_band(coverage: float) -> bool:
    return COVERAGE_BAND[0] <= coverage <= COVERAGE_BAND[1]


def _choose(grid: list[dict]) -> int:
    """The row with the best exact NLL among those covering within the band in both directions,
    else the one whose worse direction is closest to 90 %."""
    inside = [k for k, g in enumerate(grid) if all(_in_band(c) for c in g["coverage_90"].values())]
    if inside:
        return min(inside, key=lambda k: grid[k]["nll_exact"])
    return min(range(len(grid)), key=lambda k: max(abs(c - 0.9) for c in grid[k]["coverage_90"].values()))


def _direction_scale(rows: list[dict], direction: str) -> float:
    """The scale for ``direction`` among ``rows`` of one temperature: the best NLL of that direction
    among those covering within the band in it, else the coverage closest to 90 %."""
    inside = [r for r in rows if _in_band(r["coverage_90"][direction])]
    if inside:
        best = min(inside, key=lambda r: r["nll_exact_by_direction"][direction])
    else:
        best = min(rows, key=lambda r: abs(r["coverage_90"][direction] - 0.9))
    return best["output_scale"][direction]


def calibrated(model: CVAE, temperature: float, scale: tuple[float, float], companion: CVAE | None = None,
               weight: float = 1.0) -> CVAE | Mixture:
    """A copy of ``model`` calibrated with ``temperature`` and ``scale`` (x, y), mixed with
    ``companion`` (conditioned like it, :func:`~.mixture.companion_for`) at ``weight`` when that is
    below 1."""
    model = copy.deepcopy(model).set_calibration(temperature, scale)
    return model if weight >= 1.0 else Mixture([model, companion_for(model, companion)], [weight, 1.0 - weight])


def _scored(pairs: list, trials: TrialSet, temperature: float, scale: tuple[float, float], samples: int,
            seed: int, companion: CVAE | None = None, weight: float = 1.0) -> InstanceMetrics:
    """The instances of every ``(model, held-out trial ids)`` of ``pairs``, each scored by
    :func:`calibrated` (a copy of its model, mixed with ``companion`` at ``weight``). A copy: models sent to pool workers
    arrive in memory shared between the workers (torch's multiprocessing pickler), so calibrating
    them in place would let concurrent grid points overwrite each other's setting."""
    parts = []
    for model, held in pairs:
        fold = trials.subset(np.flatnonzero(np.isin(trials.trial_ids, held)))
        parts.append(evaluate_instances(calibrated(model, temperature, scale, companion, weight), fold, build_exemplars(fold),
                                        samples=samples, ade_samples=20, seed=seed))
    return InstanceMetrics.concatenate(parts)


def _row(candidate: int, temperature: float, scale: tuple[float, float], metrics: InstanceMetrics,
         weight: float = 1.0) -> dict:
    s = metrics.summary()
    return {"candidate": candidate, "latent_temperature": temperature, "output_scale": dict(zip(("x", "y"), scale)),
            "mixture_weight": weight,
            "nll_exact": s["nll_exact"],
            "nll_exact_by_direction": s["nll_exact_by_direction"],
            "coverage_90": {d: s["coverage"][d]["1.5"]["90"] for d in ("x", "y")}, "min_ade_m": s["min_ade_m"]}


def _score_job(job: tuple) -> dict:
    """One grid point, ``(candidate, temperature, scale, pairs, trials, samples, seed, companion,
    weight)``, as a row."""
    torch.set_num_threads(1)
    c, temperature, scale, pairs, trials, samples, seed, companion, weight = job
    return _row(c, temperature, scale, _scored(pairs, trials, temperature, scale, samples, seed, companion, weight),
                weight)


def _scored_rows(candidate: int, pairs: list, trials: TrialSet, settings: list, samples: int, seed: int, log,
                 pool: Executor | None, companion: CVAE | None = None):
    """Rows of ``settings`` ``[(temperature, scale, weight)]`` of one candidate, scored in ``pool``."""
    jobs = [(candidate, t, scale, pairs, trials, samples, seed, companion, w) for t, scale, w in settings]
    for row in (pool.map(_score_job, jobs) if pool is not None else map(_score_job, jobs)):
        scale = row["output_scale"]
        mixed = f", mixture weight {row['mixture_weight']:g}" if row["mixture_weight"] < 1 else ""
        log(f"candidate {candidate + 1}, temperature {row['latent_temperature']:g}, scale x {scale['x']:g} "
            f"y {scale['y']:g}{mixed}: NLL {row['nll_exact']:.2f}, 90 % coverage at 1.5 s x "
            f"{100 * row['coverage_90']['x']:.0f} %, y {100 * row['coverage_90']['y']:.0f} %")
        yield row


def _grid(candidate: int, pairs: list, trials: TrialSet, temperatures, scales, samples: int, seed: int, log,
          pool: Executor | None) -> list[dict]:
    """The settings of one candidate (a list of ``(model, held-out ids)``) scored in ``pool``'s
    processes (or here): every (temperature, scale) with the scale in both directions, then per
    temperature the per-direction choice (:func:`_direction_scale`) where it differs."""
    def scored(settings):
        return _scored_rows(candidate, pairs, trials, [(t, scale, 1.0) for t, scale in settings], samples, seed, log,
                            pool)

    grid = list(scored([(t, (s, s)) for t in temperatures for s in scales]))
    per_direction = []
    for t in temperatures:
        rows = [r for r in grid if r["latent_temperature"] == t]
        sx, sy = _direction_scale(rows, "x"), _direction_scale(rows, "y")
        if sx != sy:
            per_direction.append((t, (sx, sy)))
    return grid + list(scored(per_direction))


def _uncalibrated_nll(pairs: list, trials: TrialSet) -> float:
    """Mean exact NLL over the held-out instances of ``(model, held-out ids)`` pairs, uncalibrated."""
    nll = []
    for model, held in pairs:
        fold = trials.subset(np.flatnonzero(np.isin(trials.trial_ids, held)))
        nll.append(evaluate(copy.deepcopy(model).set_calibration(1.0, 1.0), build_exemplars(fold)).nll_exact)
    return float(np.concatenate(nll).mean())


def _search(candidates: list[list], trials: TrialSet, temperatures, scales, samples: int, seed: int, log,
            pool: Executor | None, companion: CVAE | None = None,
            weights=MIX_WEIGHTS) -> tuple[list[float], list[dict], int]:
    """The recipe by likelihood, then its calibration by coverage: the candidate (a list of
    ``(model, held-out ids)``) with the best uncalibrated out-of-fold exact NLL, and its grid and
    chosen setting (:func:`_choose`); with a ``companion``, then the mixture weight among
    ``weights`` and 1 by the same rule, the calibration fixed. Returns every candidate's NLL, the
    grid (mixture rows last), the chosen row."""
    scores = [_uncalibrated_nll(pairs, trials) for pairs in candidates]
    best = int(np.argmin(scores))
    if len(candidates) > 1:
        log("uncalibrated out-of-fold NLL of the candidates: " + ", ".join(f"{v:.2f}" for v in scores)
            + f"; chosen: candidate {best + 1}")
    grid = _grid(best, candidates[best], trials, temperatures, scales, samples, seed, log, pool)
    chosen = _choose(grid)
    if companion is None:
        return scores, grid, chosen
    pick = grid[chosen]
    settings = [(pick["latent_temperature"], scale_of(pick), w) for w in weights]
    mixed = list(_scored_rows(best, candidates[best], trials, settings, samples, seed, log, pool, companion))
    options = [pick, *mixed]
    return scores, grid + mixed, [chosen, *range(len(grid), len(grid) + len(mixed))][_choose(options)]


def calibrate(trials: TrialSet, folds: str | list, temperatures=TEMPERATURES, scales=SCALES, samples: int = 100,
              seed: int = 0, log: Callable[[str], None] = print, nested: bool = False, workers: int = 1,
              companion: CVAE | None = None, weights=MIX_WEIGHTS) -> Calibration:
    """Choose a candidate and its calibration on the out-of-fold models in ``folds`` (a folder
    written by ``crossval --out`` on ``trials``, or a list of them: candidate recipes; module
    docstring), and with a ``companion`` (a model not trained on ``trials``) the weight of the
    mixture with it among ``weights`` and 1. With ``nested``, also :func:`calibrate_nested`.
    ``workers`` > 1 scores the grid in that many processes."""
    folders = [folds] if isinstance(folds, (str, Path)) else list(folds)
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) if workers > 1 else None
    try:
        scores, grid, chosen = _search([out_of_fold_models(f, mixtures=False) for f in folders], trials, temperatures,
                                       scales, samples, seed, log, pool, companion, weights)
        estimate = (calibrate_nested(trials, folders, temperatures, scales, samples, seed, log, pool, companion, weights)
                    if nested else None)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    return Calibration(grid, chosen, scores, estimate)


def calibrate_nested(trials: TrialSet, folders: list, temperatures=TEMPERATURES, scales=SCALES, samples: int = 100,
                     seed: int = 0, log: Callable[[str], None] = print, pool: Executor | None = None,
                     companion: CVAE | None = None, weights=MIX_WEIGHTS) -> dict:
    """The nested estimate of choosing a candidate recipe and its calibration: for each outer fold
    K, the choice of :func:`calibrate` made on the inner out-of-fold models of K alone
    (``FOLDER/nested/fold_K/fold_J.pt``, written by ``crossval --nested --out``: trained without
    folds K and J, holding out J), applied to that candidate's model of K at its inner-chosen steps
    (``FOLDER/nested/fold_K.pt``) and scored on fold K. No choice involves fold K's scores.
    Returns ``nll_exact``, ``nll_exact_by_direction``, ``coverage_90``, ``min_ade_m`` over every
    fold's instances, and ``folds`` (per fold: its choice and scores)."""
    outer = [[model for model, _ in out_of_fold_models(Path(f) / "nested", mixtures=False)] for f in folders]
    held = [h for _, h in out_of_fold_models(Path(folders[0]) / "nested")]
    parts, per_fold = [], []
    for k in range(len(held)):
        inner = [out_of_fold_models(Path(f) / "nested" / f"fold_{k + 1}", mixtures=False) for f in folders]
        scores, grid, chosen = _search(inner, trials, temperatures, scales, samples, seed, lambda _: None, pool,
                                       companion, weights)
        pick = grid[chosen]
        c, temperature, scale, weight = pick["candidate"], pick["latent_temperature"], scale_of(pick), pick["mixture_weight"]
        metrics = _scored([(outer[c][k], held[k])], trials, temperature, scale, samples, seed, companion, weight)
        parts.append(metrics)
        row = _row(c, temperature, scale, metrics, weight)
        per_fold.append({**row, "instances": len(metrics),
                         "inner": {"candidates_nll_exact": scores, **{k: pick[k] for k in ("nll_exact", "coverage_90")}}})
        log(f"outer fold {k + 1}: chose {'candidate ' + str(c + 1) + ', ' if len(folders) > 1 else ''}temperature "
            f"{temperature:g}, scale x {scale[0]:g} y {scale[1]:g}"
            f"{f', mixture weight {weight:g}' if companion is not None else ''} on its inner folds; held-out NLL {row['nll_exact']:.2f} "
            f"(x {row['nll_exact_by_direction']['x']:.2f}, y {row['nll_exact_by_direction']['y']:.2f}), 90 % coverage "
            f"at 1.5 s x {100 * row['coverage_90']['x']:.0f} %, y {100 * row['coverage_90']['y']:.0f} %")
    total = _row(-1, float("nan"), (float("nan"), float("nan")), InstanceMetrics.concatenate(parts))
    return {k: total[k] for k in ("nll_exact", "nll_exact_by_direction", "coverage_90", "min_ade_m")} | {
        "fold_mean_nll_exact": float(np.mean([f["nll_exact"] for f in per_fold])), "folds": per_fold}
