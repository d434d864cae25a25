"""The ``mix`` and ``calibrate`` workflows: every check, load and write a command needs, in order,
so a command only parses its options and prints what these return (the payload of ``--json``)."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

from ..atomic import check_output_file, check_output_folder
from ..data.trials import load_trials
from ..errors import InputError
from .calibrate import SCALES, TEMPERATURES, calibrate, calibrated, scale_of
from .checkpoint import load_checkpoint, model_from_checkpoint, read_checkpoint, save_checkpoint
from .crossval import out_of_fold_models
from .mixture import Mixture, companion_for
from .registry import load_companion, model_path


def mix_checkpoint(model: str, companion: str, weight: float, out: str | Path, person_weight: float | None = None,
                   folds: str | Path | None = None, out_folds: str | Path | None = None) -> dict:
    """Write to ``out`` the mixture of ``model`` (a checkpoint or a shipped model's name) at
    ``weight`` with ``companion`` (a model spec, conditioned like ``model``) at ``1 - weight``;
    with ``person_weight``, ``model``'s weight facing a person. With ``folds`` (a ``crossval --out``
    folder), its fold models mixed alike into ``out_folds``. Every input is checked before any
    write. Returns ``out``, the recipe (``companion``, ``weight``, ``person_weight``) and the
    number of ``folds`` mixed."""
    if (folds is None) != (out_folds is None):
        raise InputError("mix: --folds and --out-folds go together (the fold models to mix, and where to write them)")
    out = check_output_file(out, "--out")
    out_folds = check_output_folder(out_folds, "--out-folds") if out_folds is not None else None
    path = model_path(model)
    payload = read_checkpoint(path)
    if "mixture" in payload:
        raise InputError(f"--model {path}: is a mixture already (expected one model to mix with --companion)")
    first = model_from_checkpoint(payload, path)
    fold_models = out_of_fold_models(folds, mixtures=False) if folds is not None else []
    mixed_with = [(f"--model {model}", first), *((f"a fold model in {folds}", m) for m, _ in fold_models)]
    other = load_companion(companion, mixed_with)
    recipe = {"companion": companion, "weight": weight, "person_weight": person_weight}
    person = None if person_weight is None else [person_weight, 1.0 - person_weight]

    def mixed(m):
        return Mixture([m, companion_for(m, other)], [weight, 1.0 - weight], person)

    save_checkpoint(out, mixed(first), **{**payload, "mixture_recipe": recipe})  # the model's own fields replaced
    for k, (fold_model, held) in enumerate(fold_models):
        save_checkpoint(out_folds / f"fold_{k + 1}.pt", mixed(fold_model), held_out_trials=held, mixture_recipe=recipe)
    return {"out": str(out), **recipe, "folds": len(fold_models)}


def _scored_models(models: list[str], loaded: list[tuple], folds: Sequence[str | Path], nested: bool) -> list[tuple]:
    """Every model a calibration grid scores, ``[(name in messages, model)]``: the ``--model``
    models, then the fold models of each folder (with ``nested``, also its inner ones)."""
    scored = [(f"--model {m}", model) for m, (model, _) in zip(models, loaded)]
    for folder in folds:
        folders = [Path(folder)]
        if nested:
            inner_folder = Path(folder) / "nested"
            inner = len(out_of_fold_models(inner_folder, mixtures=False))
            folders += [inner_folder, *(inner_folder / f"fold_{k + 1}" for k in range(inner))]
        scored += [(f"a fold model in {f}", m) for f in folders for m, _ in out_of_fold_models(f, mixtures=False)]
    return scored


def calibrate_checkpoint(data: str | Path, models: Sequence[str], folds: Sequence[str | Path], out: str | Path,
                         temperatures=TEMPERATURES, scales=SCALES, samples: int = 100, seed: int = 0,
                         nested: bool = False, workers: int = 1, companion: str | None = None,
                         out_folds: str | Path | None = None, log: Callable[[str], None] = print) -> dict:
    """Choose among candidate recipes and calibrate (:func:`~.calibrate.calibrate` on the Parquet
    dataset ``data``): ``models[i]`` (a checkpoint or shipped name) trained on every fold by the
    recipe whose fold models are in ``folds[i]``. Writes the chosen model, calibrated (and mixed
    with ``companion`` at the chosen weight), to ``out``, and with ``out_folds`` its fold models
    alike. Every input is checked before the grid. Returns the calibration summary with the chosen
    ``model`` and ``folds``, the ``candidates`` folders and ``out``."""
    if len(models) != len(folds):
        raise InputError(f"{len(models)} --model for {len(folds)} --folds (expected one model trained on every "
                         f"fold per folder of fold models, in the same order)")
    out = check_output_file(out, "--out")
    out_folds = check_output_folder(out_folds, "--out-folds") if out_folds is not None else None
    paths = [model_path(m) for m in models]
    loaded = [load_checkpoint(path) for path in paths]  # a bad --model fails before the long grid
    for path, (_, payload) in zip(paths, loaded):
        if "mixture" in payload:
            raise InputError(f"--model {path}: is a mixture, already calibrated (expected the model trained on every fold "
                             f"by the recipe of its --folds)")
    scored = _scored_models(models, loaded, folds, nested)
    other = load_companion(companion, scored) if companion is not None else None
    trials = load_trials(data)
    result = calibrate(trials, folds, temperatures, scales, samples=samples, seed=seed, log=log, nested=nested,
                       workers=workers, companion=other)
    summary = result.summary() | ({"companion": companion} if other is not None else {})
    candidate, temperature, scale = summary["candidate"], summary["latent_temperature"], scale_of(summary)
    weight = summary["mixture_weight"]
    model, payload = loaded[candidate]
    save_checkpoint(out, calibrated(model, temperature, scale, other, weight),
                    **{**payload, "calibration": summary})  # the model's own fields replaced
    if out_folds is not None:
        for k, (fold_model, held) in enumerate(out_of_fold_models(folds[candidate])):
            save_checkpoint(out_folds / f"fold_{k + 1}.pt", calibrated(fold_model, temperature, scale, other, weight),
                            held_out_trials=held, calibration=summary)
    return {**summary, "model": str(models[candidate]), "folds": str(folds[candidate]),
            "candidates": [str(f) for f in folds], "out": str(out)}
