"""k-fold cross-validation by trial: train (or fine-tune) on k−1 folds, score the held-out fold.

Every fold's held-out exact NLL is recorded along training (a curve over steps), so the number of
steps is chosen by the folds: the chosen step minimises the mean held-out curve (optionally only
among the steps at which every fold beats the reference model), and ``nested`` scores each fold at
the step chosen the same way from the *other* folds' curves alone, an estimate that no choice made
on a fold flatters. A reference model (e.g. the authors') is scored on the same folds. With ``out``, each fold's model at the chosen step is saved (``fold_K.pt``, K = 1..k) with
the trial ids it held out, so out-of-fold predictions of every trial can be analysed
(:func:`out_of_fold_models`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..data.trials import TrialSet
from ..errors import InputError
from ..scenario import MIN_TRIAL_STEPS
from .checkpoint import load_checkpoint, load_model, save_checkpoint
from .cvae import CVAE
from .evaluate import evaluate
from .exemplars import build_exemplars
from .train import NO_EXEMPLARS, TrainConfig, train


def fold_assignment(n_trials: int, folds: int, seed: int = 0) -> list[np.ndarray]:
    """``folds`` sorted arrays of trial indices: a seeded shuffle of ``0..n_trials-1`` cut into
    near-equal parts."""
    order = np.random.default_rng(seed).permutation(n_trials)
    return [np.sort(part) for part in np.array_split(order, folds)]


@dataclass
class CrossvalResult:
    """``fold_trials``: trial indices of each fold; ``steps [E]`` the evaluated step counts;
    ``curves [K, E]`` held-out exact NLL of each fold at each step (physical units);
    ``instances [K]``; ``reference``: per-fold exact NLL of a reference model (or None)."""

    fold_trials: list[np.ndarray]
    steps: np.ndarray
    curves: np.ndarray
    instances: np.ndarray
    reference: np.ndarray | None = None
    reference_name: str | None = None
    beat_reference: bool = False  # choose only among steps where every fold beats the reference

    def _choose(self, folds: np.ndarray) -> int:
        """Index into ``steps`` minimising the mean over ``folds`` (indices) of the held-out NLL,
        among the steps where each of those folds beats the reference when ``beat_reference``
        (all steps if there is none)."""
        mean = self.curves[folds].mean(0)
        if self.beat_reference and self.reference is not None:
            better = (self.curves[folds] < self.reference[folds, None]).all(0)
            if better.any():
                mean = np.where(better, mean, np.inf)
        return int(np.argmin(mean))

    @property
    def chosen(self) -> int:
        """Index into ``steps`` chosen from every fold's curve."""
        return self._choose(np.arange(len(self.curves)))

    def nested(self) -> tuple[np.ndarray, np.ndarray]:
        """Per fold: the step chosen from the other folds' curves, and the fold's NLL there."""
        k = len(self.curves)
        picks = np.array([self._choose(np.delete(np.arange(k), i)) for i in range(k)])
        return self.steps[picks], self.curves[np.arange(k), picks]

    def summary(self) -> dict:
        """JSON-ready: ``folds`` and ``nll_exact`` at the chosen step, the nested estimate, the mean
        curve, and the reference's per-fold and mean NLL."""
        folds = self.curves[:, self.chosen]
        nested_steps, nested = self.nested()
        out = {
            "folds": [float(v) for v in folds],
            "nll_exact": float(folds.mean()),
            "steps": int(self.steps[self.chosen]),
            "nested": {"steps": [int(s) for s in nested_steps], "folds": [float(v) for v in nested],
                       "nll_exact": float(nested.mean())},
            "curve": [[int(s), float(v)] for s, v in zip(self.steps, self.curves.mean(0))],
            "trials_per_fold": [len(f) for f in self.fold_trials],
            "instances_per_fold": [int(n) for n in self.instances],
            "selection": "mean" + (", every fold better than the reference" if self.beat_reference else ""),
            "reference": None,
        }
        if self.reference is not None:
            out["reference"] = {"model": self.reference_name, "folds": [float(v) for v in self.reference],
                                "nll_exact": float(self.reference.mean())}
        return out


def crossval(trials: TrialSet, folds: int = 5, tc: TrainConfig = TrainConfig(), variant: str | None = None,
             init: str | Path | None = None, reference: str | None = None, seed: int = 0,
             device: torch.device | str = "cpu", progress: bool = True,
             log: Callable[[str], None] = print, out: str | Path | None = None,
             beat_reference: bool = False) -> CrossvalResult:
    """Cross-validate training ``variant`` from scratch, or fine-tuning ``init``, with schedule
    ``tc`` (its ``steps`` is the longest schedule tried; the held-out folds are scored every
    ``validate_every`` steps, and at step 0 when fine-tuning). Folds are by trial, seeded. With
    ``out`` (a folder), save each fold's model at the chosen step; with ``beat_reference``, choose
    only among steps where every fold beats ``reference``."""
    if beat_reference and reference is None:
        raise InputError("--beat-reference needs a --reference model to beat")
    if folds < 2:
        raise InputError(f"--folds must be at least 2, got {folds}")
    if len(trials) < folds:
        raise InputError(f"the data has {len(trials)} trials, fewer than --folds {folds} (expected at least one trial per fold)")
    if len(build_exemplars(trials)) == 0:
        raise InputError(f"the data has no prediction instances ({NO_EXEMPLARS}; expected agents with role 'human')")
    parts = fold_assignment(len(trials), folds, seed)
    tc = replace(tc, validation_exemplars=10**9, patience=0)
    curves, instances, ref, snapshots = [], [], [], []
    ref_model = None if reference is None else load_model(reference, device)
    for k, held_idx in enumerate(parts):
        train_idx = np.sort(np.concatenate([p for i, p in enumerate(parts) if i != k]))
        held, rest = trials.subset(held_idx), trials.subset(train_idx)
        held_ex = build_exemplars(held)
        if len(held_ex) == 0:
            raise InputError(f"fold {k + 1} has no prediction instances (expected every fold to hold human agents "
                             f"in trials of at least {MIN_TRIAL_STEPS} steps; try fewer folds)")
        log(f"fold {k + 1}/{folds}: {len(rest)} training trials, {len(held)} held out ({len(held_ex)} instances)")
        weights = {}  # step -> CPU copy of the fold's weights, for saving the chosen step's model
        keep = lambda step, model: weights.__setitem__(step, _cpu_copy(model))  # noqa: E731
        result = train(rest, None, variant, tc, device=device, progress=progress, log=log, init=init, validation=held,
                       on_validate=keep if out is not None else None)
        history = list(result.history)
        if init is not None:
            initial = load_model(str(init), device).set_calibration(1.0, 1.0)  # as fine-tuning starts
            history.insert(0, (0, float(evaluate(initial, held_ex).nll_exact.mean())))
            weights[0] = _cpu_copy(initial)
        snapshots.append((result.model, weights, trials.trial_ids[held_idx]))
        curves.append([v for _, v in history])
        instances.append(len(held_ex))
        if ref_model is not None:
            ref.append(float(evaluate(ref_model, held_ex).nll_exact.mean()))
        log(f"fold {k + 1}: held-out NLL " + ", ".join(f"{v:.2f}@{s}" for s, v in history)
            + (f"; reference {ref[-1]:.2f}" if ref else ""))
    steps = np.array([s for s, _ in history])
    result = CrossvalResult(parts, steps, np.array(curves), np.array(instances),
                            np.array(ref) if ref else None, reference, beat_reference)
    if out is not None:
        _save_fold_models(Path(out), result, snapshots)
    return result


def _cpu_copy(model: CVAE) -> dict:
    """A CPU copy of ``model``'s state dict."""
    return {name: tensor.detach().cpu().clone() for name, tensor in model.state_dict().items()}


def _save_fold_models(out: Path, result: CrossvalResult, snapshots: list) -> None:
    """``out/fold_K.pt``: fold K's model at the chosen step, with ``held_out_trials`` (trial ids)."""
    out.mkdir(parents=True, exist_ok=True)
    step = int(result.steps[result.chosen])
    for k, (model, weights, held_ids) in enumerate(snapshots):
        model.load_state_dict(weights[step])
        save_checkpoint(out / f"fold_{k + 1}.pt", model, step=step, held_out_trials=[int(i) for i in held_ids],
                        crossval={"folds": len(snapshots), "fold": k + 1, "nll_exact": float(result.curves[k, result.chosen])})


def out_of_fold_models(folder: str | Path) -> list[tuple[CVAE, list[int]]]:
    """The fold models saved by :func:`crossval` with ``out``: ``[(model, held-out trial ids)]``."""
    paths = sorted(Path(folder).glob("fold_*.pt"), key=lambda p: int(p.stem.split("_")[1]))
    if not paths:
        raise InputError(f"{folder}: no fold_K.pt files (expected a folder written by `trafficweaving crossval --out`)")
    models = []
    for path in paths:
        model, payload = load_checkpoint(path)
        if "held_out_trials" not in payload:
            raise InputError(f"{path}: no held_out_trials (expected a fold model written by `trafficweaving crossval --out`)")
        models.append((model, list(payload["held_out_trials"])))
    return models
