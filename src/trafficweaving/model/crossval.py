"""k-fold cross-validation by trial: train (or fine-tune) on k−1 folds, score the held-out fold.

Every fold's held-out exact NLL is recorded along training (a curve over steps), so the number of
steps is chosen by the folds: the chosen step minimises the mean held-out curve (optionally only
among the steps at which every fold beats the reference model).

The nested estimate scores each fold at steps chosen without it. Properly (``nested=True``), by an
inner cross-validation of the other k−1 folds: a model is also trained without each pair of folds
{i, j} and scored on both, so that outer fold i's inner folds are the other outer folds (k(k−1)/2
extra fits, not k(k−1)). Without it, cheaply, from the other folds' curves, whose models did train
on the fold. A reference model (e.g. the authors') is scored on the same folds, in both directions.
With ``out``, each fold's model at the chosen step is saved (``fold_K.pt``, K = 1..k) with the
trial ids it held out, so out-of-fold predictions of every trial can be analysed
(:func:`out_of_fold_models`).
"""

from __future__ import annotations

import itertools
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..data.trials import TrialSet
from ..errors import InputError
from ..scenario import MIN_TRIAL_STEPS
from .checkpoint import load_checkpoint, save_checkpoint
from .cvae import CVAE, CVAEConfig
from .distil import DistilConfig, distil, teacher_model
from .evaluate import evaluate
from .exemplars import build_exemplars
from .mixture import Mixture
from .registry import load_model
from .train import NO_EXEMPLARS, initial_model, train
from .train_config import TrainConfig

MAX_FOLDS = 100
"""Most folds: each is a fit of its own (``nested`` adds k(k−1)/2 more), whose held-out scores are
kept to the end, and with ``out`` its weights at every validation (:data:`MAX_KEPT_MODELS`)."""
MAX_KEPT_MODELS = 4096
"""Most model copies a cross-validation with ``out`` keeps until it has chosen the steps, one per
fit and validation: about 1 MB each at the paper's sizes, so at most about 4 GB."""


def fold_assignment(n_trials: int, folds: int, seed: int = 0) -> list[np.ndarray]:
    """``folds`` sorted arrays of trial indices: a seeded shuffle of ``0..n_trials-1`` cut into
    near-equal parts."""
    order = np.random.default_rng(seed).permutation(n_trials)
    return [np.sort(part) for part in np.array_split(order, folds)]


@dataclass
class CrossvalResult:
    """``fold_trials``: trial indices of each fold; ``steps [E]`` the evaluated step counts;
    ``curves [K, E]`` held-out exact NLL of each fold at each step (physical units), ``directions
    [K, E, 2]`` its x and y parts (exact NLL of one direction's accelerations alone);
    ``instances [K]``; ``reference``: per-fold exact NLL of a reference model (or None) and
    ``reference_directions [K, 2]``. ``inner [K, K, E]`` (nested runs only): ``inner[i, j]`` is the
    exact NLL on fold j of the model trained without folds i and j, the inner cross-validation of
    outer fold i (diagonal unused)."""

    fold_trials: list[np.ndarray]
    steps: np.ndarray
    curves: np.ndarray
    instances: np.ndarray
    reference: np.ndarray | None = None
    reference_name: str | None = None
    beat_reference: bool = False  # choose only among steps where every fold beats the reference
    directions: np.ndarray | None = None
    reference_directions: np.ndarray | None = None
    inner: np.ndarray | None = None

    def _choose(self, curves: np.ndarray, folds: np.ndarray) -> int:
        """Index into ``steps`` minimising the mean over ``folds`` (indices) of ``curves [K, E]``,
        among the steps where each of those folds beats the reference when ``beat_reference``
        (all steps if there is none)."""
        mean = curves[folds].mean(0)
        if self.beat_reference and self.reference is not None:
            better = (curves[folds] < self.reference[folds, None]).all(0)
            if better.any():
                mean = np.where(better, mean, np.inf)
        return int(np.argmin(mean))

    @property
    def chosen(self) -> int:
        """Index into ``steps`` chosen from every fold's curve."""
        return self._choose(self.curves, np.arange(len(self.curves)))

    def nested_picks(self) -> np.ndarray:
        """Per outer fold, the index into ``steps`` chosen without it: by its inner cross-validation
        (``inner``) in a nested run, else from the other folds' curves (whose models trained on it)."""
        k = len(self.curves)
        others = [np.delete(np.arange(k), i) for i in range(k)]
        if self.inner is not None:
            return np.array([self._choose(self.inner[i], others[i]) for i in range(k)])
        return np.array([self._choose(self.curves, others[i]) for i in range(k)])

    def nested(self) -> tuple[np.ndarray, np.ndarray]:
        """Per fold: the step chosen without it (:meth:`nested_picks`), and the fold's NLL there."""
        picks = self.nested_picks()
        return self.steps[picks], self.curves[np.arange(len(self.curves)), picks]

    def summary(self) -> dict:
        """JSON-ready: ``folds`` and ``nll_exact`` at the chosen step, the nested estimate, the mean
        curve, the x and y parts, and the reference's per-fold and mean NLL."""
        folds = self.curves[:, self.chosen]
        picks = self.nested_picks()
        nested_steps, nested = self.nested()
        out = {
            "folds": [float(v) for v in folds],
            "nll_exact": float(folds.mean()),
            "steps": int(self.steps[self.chosen]),
            "nested": {"steps": [int(s) for s in nested_steps], "folds": [float(v) for v in nested],
                       "nll_exact": float(nested.mean()),
                       "method": "inner cross-validation" if self.inner is not None else "the other folds' curves"},
            "curve": [[int(s), float(v)] for s, v in zip(self.steps, self.curves.mean(0))],
            "trials_per_fold": [len(f) for f in self.fold_trials],
            "instances_per_fold": [int(n) for n in self.instances],
            "selection": "mean" + (", every fold better than the reference" if self.beat_reference else ""),
            "reference": None,
        }
        if self.directions is not None:
            at = lambda index: {d: [float(v) for v in self.directions[np.arange(len(index)), index, k]]  # noqa: E731
                                for k, d in enumerate(("x", "y"))}
            out["folds_by_direction"] = at(np.full(len(folds), self.chosen))
            out["nested"]["folds_by_direction"] = at(picks)
        if self.reference is not None:
            out["reference"] = {"model": self.reference_name, "folds": [float(v) for v in self.reference],
                                "nll_exact": float(self.reference.mean())}
            if self.reference_directions is not None:
                out["reference"]["folds_by_direction"] = {d: [float(v) for v in self.reference_directions[:, k]]
                                                          for k, d in enumerate(("x", "y"))}
        return out


@dataclass
class _Fit:
    """One fine-tuning (or training) run of a cross-validation: trained on every fold but ``held``,
    scored on each held fold at each step: ``scores[f] [E, 3]`` (exact, x, y NLL means) and the
    weights at each step (``weights``: step -> CPU state dict; only the steps that are kept)."""

    held: tuple[int, ...]
    steps: list[int]
    scores: dict
    weights: dict
    config: CVAEConfig | None = None


def _fit(trials: TrialSet, parts: list[np.ndarray], held: tuple[int, ...], tc: TrainConfig, variant, init, device,
         keep_weights: bool, distillation: tuple[Path, DistilConfig] | None, progress: bool, log) -> _Fit:
    """Train on every fold of ``parts`` but ``held`` and score each held fold along the way; with
    ``distillation``, distil instead the teacher trained without the same folds (:func:`teacher_file`)."""
    train_idx = np.sort(np.concatenate([p for i, p in enumerate(parts) if i not in held]))
    held_sets = {f: build_exemplars(trials.subset(parts[f])) for f in held}
    scores = {f: [] for f in held}
    steps, weights, config = [], {}, []

    def record(step, model):
        steps.append(step)
        config[:] = [model.config]
        for f, exemplars in held_sets.items():
            e = evaluate(model, exemplars)
            scores[f].append([float(e.nll_exact.mean()), *e.nll_direction.mean(0).tolist()])
        if keep_weights:
            weights[step] = _cpu_copy(model)

    if distillation is not None:
        folder, dc = distillation
        teacher = teacher_model(str(teacher_file(folder, held)), device)
        start = None if init is None else load_model(str(init), device)
        distil(trials.subset(train_idx), teacher, dc=dc, tc=tc, device=device, progress=bool(progress), log=log,
               on_validate=record, init=start)
        return _Fit(held, steps, {f: np.array(v) for f, v in scores.items()}, weights, config[0])
    if init is not None:
        record(0, initial_model(init, variant, tc.robot_future)[0].to(device))  # as fine-tuning starts
    # no validation set of train's own: record() scores each held fold at the validation steps
    train(trials.subset(train_idx), None, variant, replace(tc, validation_fraction=0.0), device=device,
          progress=bool(progress), log=log, init=init, on_validate=record)
    return _Fit(held, steps, {f: np.array(v) for f, v in scores.items()}, weights, config[0])


def teacher_file(folder: Path, held: tuple[int, ...]) -> Path:
    """The teacher of the fit without folds ``held`` (0-based), in a folder written by ``crossval
    --nested --out``: the model trained without the same folds, ``nested/fold_K.pt`` (held fold K,
    at the steps chosen without it) or ``nested/fold_I/fold_J.pt`` (held folds I and J)."""
    names = [f"fold_{k + 1}" for k in held]
    return folder.joinpath("nested", *names[:-1], names[-1] + ".pt")


def check_teachers(folder: Path, ids: list[list[int]], helds: list[tuple[int, ...]]) -> None:
    """Refuse a teacher folder whose models do not hold out exactly the folds each fit holds out
    (``ids``: the trial ids of each fold): a teacher that trained on a fold would leak it into the
    student's score."""
    for held in helds:
        path = teacher_file(folder, held)
        if not path.is_file():
            raise InputError(f"--teacher-folds {folder}: no {path.relative_to(folder)} (expected a folder written by "
                             f"`trafficweaving crossval --nested --out` with the same --folds and --seed)")
        _, payload = load_checkpoint(path)
        if sorted(payload.get("held_out_trials", [])) != sorted(ids[held[-1]]) or (
                len(held) == 2 and payload.get("crossval", {}).get("outer_fold") != held[0] + 1):
            raise InputError(f"{path}: holds out other trials than fold {held[-1] + 1} of this cross-validation (expected "
                             f"teachers cross-validated on the same data with the same --folds and --seed)")


def _fit_job(job: tuple) -> _Fit:
    """:func:`_fit` in a worker process (one torch thread: the workers share the cores)."""
    torch.set_num_threads(1)
    return _fit(*job, progress=False, log=lambda _: None)


def crossval(trials: TrialSet, folds: int = 5, tc: TrainConfig = TrainConfig(), variant: str | None = None,
             init: str | Path | None = None, reference: str | None = None, seed: int = 0,
             device: torch.device | str = "cpu", progress: bool = True,
             log: Callable[[str], None] = print, out: str | Path | None = None,
             beat_reference: bool = False, nested: bool = False, workers: int = 1,
             teacher_folds: str | Path | None = None, distillation: DistilConfig = DistilConfig()) -> CrossvalResult:
    """Cross-validate training ``variant`` from scratch, or fine-tuning ``init``, with schedule
    ``tc`` (its ``steps`` is the longest schedule tried; the held-out folds are scored every
    ``validate_every`` steps, and at step 0 when fine-tuning). Folds are by trial, seeded. With
    ``out`` (a folder), save each fold's model at the chosen step; with ``beat_reference``, choose
    only among steps where every fold beats ``reference``. With ``nested``, also train a model
    without each pair of folds {i, j}: the inner cross-validation of outer fold i (its inner folds
    are the other outer folds) chooses fold i's steps, so the nested estimate involves no choice
    made on the fold it scores; ``out`` then also gets ``nested/`` (:func:`_save_fold_models`).
    ``workers`` > 1 runs the fits in that many processes. With ``teacher_folds`` (a folder of a
    nested cross-validation with the same folds, :func:`teacher_file`), each fit distils the teacher
    that was trained without the same folds into a student of ``distillation``'s size
    (:func:`~trafficweaving.model.distil.distil`, ``tc`` from
    :func:`~trafficweaving.model.distil.distil_schedule`; ``init``: the student whose decoder each
    starts from), so no fold is scored by a model whose teacher saw it."""
    if beat_reference and reference is None:
        raise InputError("--beat-reference needs a --reference model to beat")
    if folds < 2 or (nested and folds < 3) or folds > MAX_FOLDS:
        raise InputError(f"--folds must be in {3 if nested else 2}..{MAX_FOLDS}{' for --nested' if nested else ''}, "
                         f"got {folds}")
    fits = folds + (folds * (folds - 1) // 2 if nested else 0)
    kept = fits * (tc.steps // tc.validate_every + 2) if out is not None else 0
    if kept > MAX_KEPT_MODELS:
        raise InputError(f"--out keeps the weights of {fits} fits at each of up to {tc.steps // tc.validate_every + 2} "
                         f"validations (--steps {tc.steps}, --validate-every {tc.validate_every}): {kept} model copies "
                         f"(expected at most {MAX_KEPT_MODELS}, about 1 MB each; validate less often or use fewer folds)")
    if len(trials) < folds:
        raise InputError(f"the data has {len(trials)} trials, fewer than --folds {folds} (expected at least one trial per fold)")
    if len(build_exemplars(trials)) == 0:
        raise InputError(f"the data has no prediction instances ({NO_EXEMPLARS}; expected agents with role 'human')")
    parts = fold_assignment(len(trials), folds, seed)
    held_out = [build_exemplars(trials.subset(p)) for p in parts]
    for k, exemplars in enumerate(held_out):
        if len(exemplars) == 0:
            raise InputError(f"fold {k + 1} has no prediction instances (expected every fold to hold human agents "
                             f"in trials of at least {MIN_TRIAL_STEPS} steps; try fewer folds)")
    tc = replace(tc, validation_exemplars=10**9, patience=0)
    helds = [(k,) for k in range(folds)] + (list(itertools.combinations(range(folds), 2)) if nested else [])
    keep = out is not None
    teaching = None
    if teacher_folds is not None:
        check_teachers(Path(teacher_folds), [[int(i) for i in trials.trial_ids[p]] for p in parts], helds)
        teaching = (Path(teacher_folds), distillation)
    jobs = [(trials, parts, held, tc, variant, init, device, keep, teaching) for held in helds]
    fits = _run_fits(jobs, folds, workers, progress, log)
    steps = np.array(fits[0].steps)
    outer = {fit.held[0]: fit for fit in fits if len(fit.held) == 1}
    curves = np.array([outer[k].scores[k][:, 0] for k in range(folds)])
    directions = np.array([outer[k].scores[k][:, 1:] for k in range(folds)])
    inner = None
    if nested:
        inner = np.full((folds, folds, len(steps)), np.nan)
        for fit in fits:
            if len(fit.held) == 2:
                i, j = fit.held
                inner[i, j], inner[j, i] = fit.scores[j][:, 0], fit.scores[i][:, 0]
    ref = ref_dir = None
    if reference is not None:
        ref_model = load_model(reference, device)
        scored = [evaluate(ref_model, exemplars) for exemplars in held_out]
        ref = np.array([float(e.nll_exact.mean()) for e in scored])
        ref_dir = np.array([e.nll_direction.mean(0) for e in scored])
    instances = np.array([len(exemplars) for exemplars in held_out])
    result = CrossvalResult(parts, steps, curves, instances, ref, reference, beat_reference, directions, ref_dir, inner)
    if out is not None:
        _save_fold_models(Path(out), result, fits, trials)
    return result


def _run_fits(jobs: list[tuple], folds: int, workers: int, progress: bool, log: Callable[[str], None]) -> list[_Fit]:
    """The fits of ``jobs`` (arguments of :func:`_fit`), in order: in ``workers`` processes when
    more than one, each logged as it ends."""
    fits = []
    if workers > 1:
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            for fit in pool.map(_fit_job, jobs):
                fits.append(fit)
                log(_fit_line(fit, folds))
        return fits
    for job in jobs:
        log(f"fitting without fold{'s' if len(job[2]) > 1 else ''} {', '.join(str(f + 1) for f in job[2])}")
        fits.append(_fit(*job, progress=progress, log=log))
        log(_fit_line(fits[-1], folds))
    return fits


def _fit_line(fit: _Fit, folds: int) -> str:
    """One log line: a fit's held-out NLL curve on each fold it held out."""
    return "; ".join(f"without fold{'s' if len(fit.held) > 1 else ''} {'+'.join(str(h + 1) for h in fit.held)}, "
                     f"fold {f + 1}: " + ", ".join(f"{v:.2f}@{s}" for s, v in zip(fit.steps, fit.scores[f][:, 0]))
                     for f in fit.held)


def _cpu_copy(model: CVAE) -> dict:
    """A CPU copy of ``model``'s state dict."""
    return {name: tensor.detach().cpu().clone() for name, tensor in model.state_dict().items()}


def _save(path: Path, weights: dict, like: CVAE, **fields) -> None:
    like.load_state_dict(weights)
    save_checkpoint(path, like, **fields)


def _save_fold_models(out: Path, result: CrossvalResult, fits: list[_Fit], trials: TrialSet) -> None:
    """``out/fold_K.pt``: fold K's model at the chosen step, with ``held_out_trials`` (trial ids).
    In a nested run also ``out/nested/fold_K.pt``, fold K's model at the steps its inner
    cross-validation chose, and ``out/nested/fold_K/fold_J.pt``, the model trained without folds K
    and J at those steps, holding out fold J (the inner out-of-fold models that ``calibrate
    --nested`` chooses fold K's calibration on)."""
    out.mkdir(parents=True, exist_ok=True)
    k_folds = len(result.curves)
    ids = [[int(i) for i in trials.trial_ids[p]] for p in result.fold_trials]
    by_held = {fit.held: fit for fit in fits}
    like = CVAE(fits[0].config)
    step = int(result.steps[result.chosen])
    for k in range(k_folds):
        _save(out / f"fold_{k + 1}.pt", by_held[(k,)].weights[step], like, step=step, held_out_trials=ids[k],
              crossval={"folds": k_folds, "fold": k + 1, "nll_exact": float(result.curves[k, result.chosen])})
    if result.inner is None:
        return
    for k, pick in enumerate(result.nested_picks()):
        step = int(result.steps[pick])
        folder = out / "nested" / f"fold_{k + 1}"
        folder.mkdir(parents=True, exist_ok=True)
        _save(out / "nested" / f"fold_{k + 1}.pt", by_held[(k,)].weights[step], like, step=step, held_out_trials=ids[k],
              crossval={"folds": k_folds, "fold": k + 1, "nll_exact": float(result.curves[k, pick]), "nested": True})
        for j in range(k_folds):
            if j != k:
                _save(folder / f"fold_{j + 1}.pt", by_held[tuple(sorted((k, j)))].weights[step], like, step=step,
                      held_out_trials=ids[j], crossval={"folds": k_folds, "fold": j + 1, "outer_fold": k + 1,
                                                        "nll_exact": float(result.inner[k, j, pick])})


def out_of_fold_models(folder: str | Path, mixtures: bool = True) -> list[tuple[CVAE | Mixture, list[int]]]:
    """The fold models saved by :func:`crossval` with ``out`` (or ``mix --out-folds``, unless not
    ``mixtures``): ``[(model, held-out trial ids)]``."""
    paths = sorted(Path(folder).glob("fold_*.pt"), key=lambda p: int(p.stem.split("_")[1]))
    if not paths:
        raise InputError(f"{folder}: no fold_K.pt files (expected a folder written by `trafficweaving crossval --out`)")
    models = []
    for path in paths:
        model, payload = load_checkpoint(path)
        if not mixtures and isinstance(model, Mixture):
            raise InputError(f"{path}: is a mixture (expected a fold model of `trafficweaving crossval --out`)")
        if "held_out_trials" not in payload:
            raise InputError(f"{path}: no held_out_trials (expected a fold model written by `trafficweaving crossval --out`)")
        models.append((model, list(payload["held_out_trials"])))
    return models
