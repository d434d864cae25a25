"""Command-line interface: ``trafficweaving <command> ...`` (also ``python -m trafficweaving``).

Every reporting command takes ``--json`` and then prints exactly one JSON object on stdout.
Bad input ends with a one-line message on stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import time
from pathlib import Path

from .atomic import check_output_file, check_output_folder
from .errors import InputError
from .scenario import HORIZON, MIN_HISTORY, MIN_TRIAL_STEPS, REPLAN_PERIOD_S, STUDY_TRIALS

SEED_MAX = 2**32 - 1
"""Largest ``--seed`` (NumPy and PyTorch accept every seed in 0..2³²-1 on every platform)."""


class _Terminated(BaseException):
    """Raised in the main thread when SIGTERM arrives, so that open outputs are cleaned up."""


class _Parser(argparse.ArgumentParser):
    """argparse with the project's error convention: one line on stderr and exit status 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


# ---------------------------------------------------------------- option types
def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None


def _int_at_least(low: int, high: int | None = None):
    """An argparse type: an integer in ``low..high``."""
    def parse(text: str) -> int:
        value = _integer(text)
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"expected an integer in {low}..{high if high is not None else ''}, got {value}"
                                             if high is not None else f"expected an integer >= {low}, got {value}")
        return value
    return parse


def _float_in(low: float, high: float, include_low: bool = False, include_high: bool = False):
    """An argparse type: a finite float in the interval from ``low`` to ``high``."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        above = value >= low if include_low else value > low
        below = value <= high if include_high else value < high
        if not (math.isfinite(value) and above and below):
            interval = f"{'[' if include_low else '('}{low:g}, {high:g}{']' if include_high else ')'}"
            raise argparse.ArgumentTypeError(f"expected a finite number in {interval}, got {text}")
        return value
    return parse


def _floats_in(low: float, high: float):
    """An argparse type: a comma-separated list of finite floats in ``(low, high)``."""
    one = _float_in(low, high)

    def parse(text: str) -> tuple[float, ...]:
        try:
            return tuple(one(part) for part in text.split(","))
        except argparse.ArgumentTypeError as exc:
            raise argparse.ArgumentTypeError(f"{exc} in the list {text!r}") from None
    return parse


POSITIVE = _int_at_least(1)
NON_NEGATIVE = _int_at_least(0)
SEED = _int_at_least(0, SEED_MAX)


def _json_safe(value):
    """``value`` with every non-finite float replaced by None (JSON has no NaN or Infinity) and
    NumPy scalars as Python numbers."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if hasattr(value, "item") and getattr(value, "ndim", None) == 0:
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _emit(args, payload: dict, text: str) -> None:
    print(json.dumps(_json_safe(payload), allow_nan=False) if args.json else text)


# ---------------------------------------------------------------- commands
def _log(args):
    """Progress lines: stderr under ``--json`` (stdout holds the one JSON object), else stdout."""
    return (lambda line: print(line, file=sys.stderr)) if args.json else print


def _fmt(value) -> str:
    return "n/a" if value is None else f"{value:.3f}"


def cmd_generate(args) -> None:
    from .model.checkpoint import choose_device
    from .sim.generate import generate_trials

    out = check_output_file(args.out, "--out")
    start = time.perf_counter()
    try:
        trials, report = generate_trials(args.trials, seed=args.seed, pairs=args.pairs, progress=not args.json,
                                         drivers=args.drivers, device=choose_device(args.device))
    except ValueError as exc:
        raise InputError(str(exc)) from None
    trials.write_parquet(out)
    seconds = time.perf_counter() - start
    rejected = sum(report.rejected.values())
    payload = {"trials": len(trials), "simulated": report.simulated, "rejected": rejected,
               "rejected_by_reason": report.rejected, "drivers": args.drivers, "seed": args.seed, "out": str(out),
               "seconds": round(seconds, 3)}
    reasons = ", ".join(f"{k} {v}" for k, v in report.rejected.items())
    _emit(args, payload, f"wrote {len(trials)} valid trials to {out} in {seconds:.1f} s "
                         f"({report.simulated} simulated; rejected {rejected}: {reasons})")


def cmd_import(args) -> None:
    out = check_output_file(args.out, "--out")
    if args.source == "hitl":
        from .data.hitl import read_hitl

        trials = read_hitl(args.inputs)
        trials.write_parquet(out)
        _emit(args, {"trials": len(trials), "out": str(out)}, f"imported {len(trials)} human-in-the-loop trials into {out}")
    else:
        from .data.rosbag import read_rosbags

        if len(args.inputs) != 1:
            raise InputError(f"import rosbag takes one folder of .bag files, got {len(args.inputs)} paths")
        result = read_rosbags(args.inputs[0])
        result.trials.write_parquet(out)
        rejected_total = sum(result.rejected.values())
        _emit(args, {"trials": len(result.trials), "rejected": rejected_total,
                     "rejected_by_reason": result.rejected, "out": str(out)},
              f"imported {len(result.trials)} trials into {out}; rejected {rejected_total} bags "
              f"({', '.join(f'{k} {v}' for k, v in result.rejected.items()) or 'none'})")


def cmd_stats(args) -> None:
    from .data.behaviour import behaviour_samples, compare_behaviour, format_comparison, summarise
    from .data.stats import format_table1, format_table1_test, table1, table1_test
    from .data.trials import load_trials

    if Path(args.data).is_dir():
        return _stats_of_drives(args)
    trials = load_trials(args.data)
    reference = load_trials(args.reference) if args.reference else None
    t1 = table1(trials)
    humans = behaviour_samples(trials, role="human")
    payload = {
        "trials": len(trials),
        "steps": {"min": int(trials.lengths.min()), "mean": float(trials.lengths.mean()),
                  "max": int(trials.lengths.max())},
        "table1": t1["table1"],
        "table1_counts": t1["counts"],
        "table1_vs_paper": table1_test(t1["table1"], t1["counts"]),
        "behaviour": {name: summarise(values) for name, values in humans.items()},
    }
    text = [f"{args.data}: {len(trials)} trials, {trials.lengths.min()}–{trials.lengths.max()} steps "
            f"(mean {trials.lengths.mean():.1f}) of {trials.dt} s", format_table1(t1["table1"], t1["counts"]),
            format_table1_test(payload["table1_vs_paper"])]
    if reference is not None:
        comparison = compare_behaviour(humans, behaviour_samples(reference, role="human"))
        payload["behaviour_vs_reference"] = comparison
        text += [f"Human behaviour vs {args.reference}:", format_comparison(comparison)]
    _emit(args, payload, "\n".join(text))


def _stats_of_drives(args) -> None:
    """``stats DIR``: a folder of browser recordings (``trafficweaving drive``), the study's
    progress: trials per pair (room session), completed and aborted, and Table I so far."""
    from .data.stats import format_table1, format_table1_test, table1_test
    from .web.recording import load_recordings
    from .web.study import folder_progress, format_progress

    if args.reference:
        raise InputError("--reference: compares a dataset file's drivers (expected stats FILE.parquet --reference "
                         "REF, not a folder)")
    progress = folder_progress(load_recordings(args.data))
    progress["table1_vs_paper"] = table1_test(progress["table1"], progress["table1_counts"])
    text = [f"{args.data}: trials recorded {progress['files']}, completed {progress['completed']}, aborted "
            f"{progress['aborted']} (stopped, a page gone, a server error)", format_progress(progress),
            f"Table I so far (completed human-human trials: {progress['human_human_completed']}):",
            format_table1(progress["table1"], progress["table1_counts"]), format_table1_test(progress["table1_vs_paper"])]
    _emit(args, {"folder": str(args.data), **progress}, "\n".join(text))


def cmd_plot(args) -> None:
    from .data.trials import load_trials
    from .viz.figures import write_dataset_figures

    out = check_output_folder(args.out, "--out")
    trials = load_trials(args.data)
    reference = load_trials(args.reference) if args.reference else None
    paths = write_dataset_figures(trials, out, reference)
    _emit(args, {"figures": [str(p) for p in paths]}, "\n".join(f"wrote {p}" for p in paths))


def _train_config(args):
    """The :class:`TrainConfig` of ``train`` / ``crossval`` options: the paper's schedule from
    scratch, the fine-tuning defaults with ``--init``; ``--lr`` etc. override either."""
    from dataclasses import replace

    from .model.train import FINE_TUNING, TrainConfig

    fraction = getattr(args, "validation_fraction", 0.2)
    if fraction == 0 and (getattr(args, "patience", None) or 0) > 0:
        raise InputError("--patience needs a validation set (expected --validation-fraction above 0)")
    tc = TrainConfig(steps=args.steps, seed=args.seed, validation_fraction=fraction)
    if args.init:
        tc = replace(tc, **FINE_TUNING)
    overrides = {"lr_initial": args.lr, "validate_every": args.validate_every,
                 "patience": getattr(args, "patience", None), "objective": args.objective, "hold_lr": args.hold_lr,
                 "trainable": args.train_parts, "robot_future": args.robot_future}
    tc = replace(tc, **{k: v for k, v in overrides.items() if v is not None})
    return replace(tc, lr_final=min(tc.lr_final, tc.lr_initial), checkpoint_every=min(tc.checkpoint_every, tc.validate_every))


def _model_spec(spec: str, what: str) -> str:
    """Check a ``--model``-style value early (before long work): a shipped model's name,
    ``authors:PATH`` or a checkpoint file; the full validation happens when it is loaded."""
    from .model.checkpoint import SHIPPED_MODELS

    path = spec.removeprefix("authors:") if spec.startswith("authors:") else spec
    if not path:
        raise InputError(f"{what} {spec!r}: empty path (expected a checkpoint path, {', '.join(SHIPPED_MODELS)}, "
                         f"or authors:PATH to the authors' weights.npz)")
    if spec not in SHIPPED_MODELS and not Path(path).is_file():
        raise InputError(f"{what} {spec}: no such file (expected a checkpoint path, {', '.join(SHIPPED_MODELS)}, "
                         f"or authors:PATH to the authors' weights.npz)")
    return spec


def cmd_train(args) -> None:
    from .data.trials import load_trials
    from .model.checkpoint import choose_device
    from .model.train import train

    if args.init and args.resume:
        raise InputError("--init and --resume exclude each other (expected one: fine-tune a model, or continue a run)")
    out = check_output_file(args.out, "--out")
    tc = _train_config(args)
    device = choose_device(args.device)
    trials = load_trials(args.data)
    result = train(trials, out, args.variant, tc, resume=args.resume, device=device, progress=not args.json,
                   log=_log(args), init=args.init)
    validation = result.validation or {"instances": 0, "nll_exact": None, "nll_is": None, "nll_naive": None}
    payload = {"variant": result.model.config.name, "steps": result.step, **validation,
               "best_step": result.best_step, "init": args.init,
               "steps_per_second": round(result.steps_per_second, 2), "out": str(out)}
    _emit(args, payload, f"trained {payload['variant']} for {result.step} steps "
                         f"({result.steps_per_second:.1f} steps/s) -> {out}\n"
                         f"validation ({validation['instances']} exemplars): "
                         f"NLL exact {_fmt(validation['nll_exact'])}, IS {_fmt(validation['nll_is'])}, "
                         f"naive {_fmt(validation['nll_naive'])} nats")


def cmd_crossval(args) -> None:
    from .data.trials import load_trials
    from .model.checkpoint import choose_device, load_model
    from .model.crossval import crossval

    out = check_output_folder(args.out, "--out") if args.out is not None else None
    if args.reference is not None:
        load_model(_model_spec(args.reference, "--reference"))  # a bad reference fails before the folds train
    tc = _train_config(args)
    device = choose_device(args.device)
    trials = load_trials(args.data)
    if args.init is not None:
        _model_spec(args.init, "--init")
    result = crossval(trials, args.folds, tc, variant=args.variant, init=args.init, reference=args.reference,
                      seed=args.seed, device=device, progress=not args.json, log=_log(args),
                      out=out, beat_reference=args.beat_reference, nested=args.nested, workers=args.workers)
    summary = result.summary()
    payload = {**summary, "data": args.data, "init": args.init, "variant": args.variant, "out": args.out}
    ref = summary["reference"]
    lines = [f"{args.folds}-fold cross-validation by trial on {args.data} "
             f"({'fine-tuning ' + args.init if args.init else 'training from scratch'})",
             f"held-out exact NLL at the chosen {summary['steps']} steps: "
             + " ".join(f"{v:.2f}" for v in summary["folds"]) + f"  mean {summary['nll_exact']:.3f}",
             f"nested (each fold at the steps chosen by {summary['nested']['method']}): "
             + " ".join(f"{v:.2f}" for v in summary["nested"]["folds"]) + f"  mean {summary['nested']['nll_exact']:.3f}"]
    if ref:
        lines.append(f"reference {ref['model']}: " + " ".join(f"{v:.2f}" for v in ref["folds"]) + f"  mean {ref['nll_exact']:.3f}")
    _emit(args, payload, "\n".join(lines))


def cmd_mix(args) -> None:
    """A mixture of a model with a companion at a given weight (and of its fold models)."""
    from .model.checkpoint import load_companion, model_from_checkpoint, model_path, read_checkpoint, save_checkpoint
    from .model.crossval import out_of_fold_models
    from .model.mixture import Mixture, companion_for

    if (args.folds is None) != (args.out_folds is None):
        raise InputError("mix: --folds and --out-folds go together (the fold models to mix, and where to write them)")
    out = check_output_file(args.out, "--out")
    out_folds = check_output_folder(args.out_folds, "--out-folds") if args.out_folds is not None else None
    path = model_path(args.model)
    payload = read_checkpoint(path)
    if "mixture" in payload:
        raise InputError(f"--model {path}: is a mixture already (expected one model to mix with --companion)")
    model = model_from_checkpoint(payload, path)
    folds = out_of_fold_models(args.folds, mixtures=False) if args.folds is not None else []
    mixed_with = [(f"--model {args.model}", model), *((f"a fold model in {args.folds}", m) for m, _ in folds)]
    companion = load_companion(_model_spec(args.companion, "--companion"), mixed_with)
    recipe = {"companion": args.companion, "weight": args.weight, "person_weight": args.person_weight}
    person = None if args.person_weight is None else [args.person_weight, 1.0 - args.person_weight]

    def mixed(m):
        return Mixture([m, companion_for(m, companion)], [args.weight, 1.0 - args.weight], person)

    save_checkpoint(out, mixed(model), **{**payload, "mixture_recipe": recipe})  # the model's own fields replaced
    for k, (fold_model, held) in enumerate(folds):
        save_checkpoint(out_folds / f"fold_{k + 1}.pt", mixed(fold_model), held_out_trials=held, mixture_recipe=recipe)
    written = f" and {len(folds)} fold models in {out_folds}" if folds else ""
    _emit(args, {"out": str(out), **recipe, "folds": len(folds)},
          f"mixed {args.model} ({args.weight:g}) with {args.companion} ({1 - args.weight:g}"
          f"{'' if person is None else f'; facing a person {person[0]:g} and {person[1]:g}'}) -> {out}{written}")


def cmd_calibrate(args) -> None:
    from .data.trials import load_trials
    from .model.calibrate import calibrate, calibrated, scale_of
    from .model.checkpoint import load_checkpoint, load_companion, model_path, save_checkpoint
    from .model.crossval import out_of_fold_models

    if len(args.model) != len(args.folds):
        raise InputError(f"{len(args.model)} --model for {len(args.folds)} --folds (expected one model trained on every "
                         f"fold per folder of fold models, in the same order)")
    out = check_output_file(args.out, "--out")
    out_folds = check_output_folder(args.out_folds, "--out-folds") if args.out_folds is not None else None
    paths = [model_path(m) for m in args.model]
    loaded = [load_checkpoint(path) for path in paths]  # a bad --model fails before the long grid
    for path, (_, payload) in zip(paths, loaded):
        if "mixture" in payload:
            raise InputError(f"--model {path}: is a mixture, already calibrated (expected the model trained on every fold "
                             f"by the recipe of its --folds)")
    scored = [(f"--model {m}", model) for m, (model, _) in zip(args.model, loaded)]  # every model the grid scores
    for folder in args.folds:
        folders = [Path(folder)]
        if args.nested:
            nested = Path(folder) / "nested"
            inner = len(out_of_fold_models(nested, mixtures=False))
            folders += [nested, *(nested / f"fold_{k + 1}" for k in range(inner))]
        scored += [(f"a fold model in {f}", m) for f in folders for m, _ in out_of_fold_models(f, mixtures=False)]
    companion = (load_companion(_model_spec(args.companion, "--companion"), scored) if args.companion is not None
                 else None)
    trials = load_trials(args.data)
    result = calibrate(trials, args.folds, args.temperatures, args.scales, samples=args.samples, seed=args.seed,
                       log=_log(args), nested=args.nested, workers=args.workers, companion=companion)
    summary = result.summary() | ({"companion": args.companion} if companion is not None else {})
    candidate, temperature, scale = summary["candidate"], summary["latent_temperature"], scale_of(summary)
    weight = summary["mixture_weight"]
    model, payload = loaded[candidate]
    model = calibrated(model, temperature, scale, companion, weight)
    kept = {k: v for k, v in payload.items() if k not in ("format", "version", "config", "state_dict", "mixture")}
    save_checkpoint(out, model, **{**kept, "calibration": summary})
    if out_folds is not None:
        for k, (fold_model, held) in enumerate(out_of_fold_models(args.folds[candidate])):
            save_checkpoint(out_folds / f"fold_{k + 1}.pt", calibrated(fold_model, temperature, scale, companion, weight),
                            held_out_trials=held, calibration=summary)
    cov = summary["coverage_90"]
    mixed = f", mixed with {args.companion} at weight {weight:g}" if weight < 1 else ""
    lines = [f"calibrated {args.model[candidate]} -> {out}: latent temperature {temperature:g}, output scale x "
             f"{scale[0]:g}, y {scale[1]:g}{mixed} "
             f"(out-of-fold NLL {summary['nll_exact']:.2f}, 90 % coverage at 1.5 s x {100 * cov['x']:.0f} %, "
             f"y {100 * cov['y']:.0f} %)"]
    if result.nested is not None:
        n = result.nested
        lines.append(f"nested (every choice made on each fold's inner folds): NLL {n['fold_mean_nll_exact']:.2f} per fold "
                     f"({n['nll_exact']:.2f} per instance; x {n['nll_exact_by_direction']['x']:.2f}, y "
                     f"{n['nll_exact_by_direction']['y']:.2f}), 90 % coverage at 1.5 s x {100 * n['coverage_90']['x']:.0f} %, "
                     f"y {100 * n['coverage_90']['y']:.0f} %")
    _emit(args, {**summary, "model": str(args.model[candidate]), "folds": str(args.folds[candidate]),
                 "candidates": [str(f) for f in args.folds], "out": str(out)},
          "\n".join(lines))


def cmd_evaluate(args) -> None:
    from .data.trials import load_trials
    from .model.checkpoint import choose_device, load_model
    from .model.exemplars import build_exemplars
    from .model.metrics import DIRECTIONS, PHASES, evaluate_instances
    from .model.mixture import describe

    per_instance = check_output_file(args.per_instance, "--per-instance") if args.per_instance is not None else None
    model = load_model(args.model, choose_device(args.device))
    trials = load_trials(args.data)
    exemplars = build_exemplars(trials)
    if len(exemplars) == 0:
        raise InputError(f"{args.data}: no prediction instances (expected human agents in trials of at least "
                         f"{MIN_TRIAL_STEPS} steps)")
    metrics = evaluate_instances(model, trials, exemplars, samples=args.coverage_samples, ade_samples=args.ade_samples,
                                 max_sampled=args.max_sampled_instances, nll_samples=args.samples, seed=args.seed)
    result = metrics.summary()
    if per_instance is not None:
        metrics.write_parquet(per_instance, {"model": args.model, "data": str(args.data), "seed": args.seed,
                                             "samples": args.samples, "coverage_samples": args.coverage_samples,
                                             "ade_samples": args.ade_samples})
    payload = {**result, "model": args.model, "variant": model.config.name}
    pct = lambda v: "n/a" if v is None else f"{100 * v:.0f}"  # noqa: E731
    meters = lambda v: "n/a" if v is None else f"{v:.2f}"  # noqa: E731
    phases = ", ".join(f"{p} {_fmt(result['nll_exact_by_phase'][p]['nll_exact'])} (n={result['nll_exact_by_phase'][p]['instances']})"
                       for p in PHASES)
    coverage = "; ".join(f"{d} " + ", ".join(f"{h} s {pct(c['50'])}/{pct(c['90'])}" for h, c in result["coverage"][d].items())
                         for d in DIRECTIONS)
    _emit(args, payload, f"{args.model} ({describe(model)}) on {args.data}: {result['instances']} instances\n"
                         f"NLL per instance (nats, 15×2 accelerations in m/s²): exact {_fmt(result['nll_exact'])}, "
                         f"importance-sampled {_fmt(result['nll_is'])}, naive {_fmt(result['nll_naive'])}\n"
                         f"  exact by direction (15 accelerations): x {_fmt(result['nll_exact_by_direction']['x'])}, "
                         f"y {_fmt(result['nll_exact_by_direction']['y'])}\n"
                         f"  exact by lane-change phase: {phases}\n"
                         f"Sampled positions ({result['sampled_instances']} instances, {args.coverage_samples} samples each):\n"
                         f"  coverage of the 50/90 % central intervals (%): {coverage}\n"
                         f"  minADE {meters(result['min_ade_m'])} m, minFDE {meters(result['min_fde_m'])} m "
                         f"(best of {args.ade_samples})"
                         + (f"\nper-instance values: {per_instance}" if per_instance is not None else ""))


def _parse_pick(text: str, trials) -> tuple[int, int, int]:
    """``TRIAL:T`` or ``TRIAL:T:AGENT`` (trial index, present step, human agent) for ``predict --at``."""
    try:
        parts = [int(v) for v in text.split(":")]
        if len(parts) not in (2, 3):
            raise ValueError
    except ValueError:
        raise InputError(f"--at {text!r}: expected TRIAL:T or TRIAL:T:AGENT (integers)") from None
    i, t = parts[:2]
    if not 0 <= i < len(trials):
        raise InputError(f"--at {text!r}: trial index {i} is outside 0..{len(trials) - 1}")
    humans = [a for a in (0, 1) if trials.roles[i, a] == "human"]
    agent = parts[2] if len(parts) == 3 else (humans[0] if humans else 1)
    if agent not in (0, 1):
        raise InputError(f"--at {text!r}: agent must be 0 or 1")
    first, last = MIN_HISTORY - 1, int(trials.lengths[i]) - HORIZON - 1
    if not first <= t <= last:
        raise InputError(f"--at {text!r}: t must be within {first}..{last} for trial {i} ({trials.lengths[i]} steps)")
    return i, agent, t


def cmd_predict(args) -> None:
    from .data.trials import load_trials
    from .model.checkpoint import choose_device, load_model
    from .model.mixture import describe
    from .viz.model_figures import plot_predictions

    out = check_output_file(args.out, "--out")
    trials = load_trials(args.data)
    trials.require_dt()
    picks = [_parse_pick(text, trials) for text in args.at]
    model = load_model(args.model, choose_device(args.device))
    path = plot_predictions(model, trials, picks, out, samples=args.samples, seed=args.seed,
                            title=f"{args.model} ({describe(model)}) on {Path(args.data).name}")
    _emit(args, {"out": str(path), "panels": len(picks)}, f"wrote {path}")


def cmd_bench(args) -> None:
    import statistics

    import torch

    from .model.checkpoint import choose_device, load_model
    from .model.predictor import MAX_PLAN_FUTURES, HumanPredictor, cpu_matrix_features
    from .planning.candidates import N_CANDIDATES, Action
    from .planning.costs import PaperCost
    from .planning.planner import Budget, Planner, example_history
    from .scenario import LANE_CENTRE_Y

    budget = Budget(args.first_stage_samples, args.finalists, args.second_stage_samples)
    if budget.futures > MAX_PLAN_FUTURES:
        raise InputError(f"--first-stage-samples {budget.first_stage_samples}, --finalists {budget.finalists} and "
                         f"--second-stage-samples {budget.second_stage_samples} sample {budget.futures} human futures "
                         f"a plan ({N_CANDIDATES} candidates × first stage + finalists × second stage; expected at most "
                         f"{MAX_PLAN_FUTURES})")
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    device = choose_device(args.device)
    human_model = HumanPredictor(load_model(args.model, device), precision=args.precision)
    planner = Planner(human_model, budget)
    history, first = example_history(), Action.of(0.0, "right").index
    cost = PaperCost(goal_y=LANE_CENTRE_Y["left"])
    planner.plan(history, first, cost, deadline=args.deadline)  # warm-up: allocations, measured speed
    opening, seconds, futures = None, [], []
    for _ in range(args.repeats):  # a plan holds its candidates and futures (MBs): keep the first and the last
        plan = planner.plan(history, first, cost, deadline=args.deadline)
        opening = plan if opening is None else opening
        seconds.append(plan.seconds)
        futures.append(plan.futures)
    payload = {"futures": min(futures), "seconds": statistics.median(seconds),
               "seconds_all": [round(s, 4) for s in seconds], "candidates": len(opening.candidates),
               "first_stage_samples": opening.first_stage_samples, "shortlist_samples": opening.shortlist_samples,
               "finalists": len(opening.finalists),
               "second_stage_samples": opening.second_stage_samples, "deadline": args.deadline,
               "device": str(device), "threads": torch.get_num_threads(), "model": args.model,
               "precision": human_model.precision,
               "timings": {k: round(v, 4) for k, v in plan.timings.items()}, "cpu": cpu_matrix_features()}
    _emit(args, payload, f"plan: {payload['futures']} human futures for {payload['candidates']} candidates in "
                         f"{payload['seconds']:.3f} s (median of {args.repeats}; {device}, {payload['threads']} threads)")


def cmd_simulate(args) -> None:
    """Closed-loop episodes of a robot against a human (:mod:`trafficweaving.sim.batch`)."""
    from .sim.batch import simulate, summary_table

    summary = simulate(args.episodes, args.robot, args.human, seed=args.seed, workers=args.workers,
                       engine=args.engine, address=args.address, out=args.out,
                       model=_model_spec(args.model, "--model"), deadline=args.deadline, device=args.device,
                       precision=args.precision, progress=not args.json)
    _emit(args, summary, summary_table(summary))


def cmd_realism(args) -> None:
    """Closed-loop realism of a human agent on recorded trials (:mod:`trafficweaving.sim.realism`)."""
    import numpy as np

    from .data.trials import load_trials
    from .model.checkpoint import choose_device
    from .sim.humans import HUMAN_SPECS, ModelDriver, human_agent
    from .sim.realism import realism

    if (args.human is None) == (args.folds is None):
        raise InputError(f"realism needs one of --human SPEC ({HUMAN_SPECS}) or --folds DIR (out-of-fold models)")
    device = choose_device(args.device)
    if args.human is not None:
        made = {}

        def agent(other: str):
            """The --human agent facing ``other``, made once."""
            if other not in made:
                try:
                    made[other] = human_agent(args.human, device, other=other)
                except InputError as exc:
                    raise InputError(f"--human {args.human}: {exc}") from None
            return made[other]

        agent("robot")  # a bad --human fails before the data is read
        agents = lambda ids, other: [(ids, agent(other))]  # noqa: E731
    trials = load_trials(args.data)
    if args.folds is not None:
        from .model.crossval import out_of_fold_models

        folds = out_of_fold_models(args.folds)
        held = np.concatenate([np.asarray(ids) for _, ids in folds])
        missing = np.setdiff1d(trials.trial_ids[(trials.roles == "human").any(axis=1)], held)
        if len(missing):
            raise InputError(f"--folds {args.folds}: trial {missing[0]} of {args.data} is held out by no fold (expected "
                             f"the folds of `trafficweaving crossval --out` on the same data)")
        agents = lambda ids, other: [(np.asarray(h), ModelDriver(m.to(device), other=other)) for m, h in folds]  # noqa: E731
    try:
        result = realism(trials, agents, rollouts=args.rollouts, seed=args.seed, progress=not args.json)
    except InputError:
        raise
    except ValueError as exc:
        raise InputError(f"{args.data}: {exc}") from None
    summary = {"human": args.human or f"out-of-fold:{args.folds}", "data": str(args.data), "seed": args.seed,
               **result.summary()}
    groups = ", ".join(f"{g} {v:.3f}" for g, v in summary["groups"].items())
    rates = "; ".join(f"{k.replace('_', ' ')} {100 * summary[k + '_rate']:.1f} % (real {100 * summary['real_' + k + '_rate']:.1f} %)"
                      for k in ("swap", "off_road", "collision", "at_fault_collision"))
    _emit(args, summary, f"{summary['human']}: realism {summary['realism']:.3f} ({groups}) over {summary['streams']} "
                         f"recorded humans × {summary['rollouts']} rollouts\n{rates}")


def cmd_plot_episode(args) -> None:
    """The paper's Fig. 6 of one trial or episode, and optionally its animation."""
    from .atomic import same_file
    from .data.trials import load_trials
    from .viz.episode_figures import MAX_ANIMATION_STEPS, animate_episode, plot_episode

    out = check_output_file(args.out, "--out")
    gif = check_output_file(args.gif, "--gif") if args.gif is not None else None
    if gif is not None and same_file(out, gif):
        raise InputError(f"--gif {gif}: the same file as --out {out} (expected another path: the animation would "
                         f"replace the figure)")
    trials = load_trials(args.data)
    if args.trial >= len(trials):
        raise InputError(f"--trial {args.trial}: {args.data} has {len(trials)} trials (expected 0..{len(trials) - 1})")
    length = int(trials.lengths[args.trial])
    plans = None
    if gif is not None:
        if length > MAX_ANIMATION_STEPS:
            raise InputError(f"--gif: trial {args.trial} of {args.data} has {length} steps (expected at most "
                             f"{MAX_ANIMATION_STEPS}, one frame each)")
        if "episode" in trials.metadata:
            from .sim.episodes import rerun_with_plans

            plans = rerun_with_plans(trials)
    payload = {"figure": str(plot_episode(trials, args.trial, out))}
    if gif is not None:
        roles = tuple(str(r) for r in trials.roles[args.trial])
        payload["animation"] = str(animate_episode(trials.states[args.trial, :, :length], roles, gif, plans or [],
                                                   title=str(trials.sources[args.trial])))
        payload["plans_drawn"] = len(plans or [])
    _emit(args, payload, "\n".join(f"wrote {path}" for key, path in payload.items() if key != "plans_drawn")
          + (f" ({payload['plans_drawn']} plans drawn)" if gif is not None else ""))


def cmd_drive(args) -> None:
    """The browser human-in-the-loop app (:mod:`trafficweaving.web`)."""
    from .web.room import DriveConfig
    from .web.server import serve

    config = DriveConfig(mode=args.mode, countdown_s=args.countdown, model=_model_spec(args.model, "--model"),
                         deadline=args.deadline, threads=args.threads)
    serve(config, args.host, args.port, check_output_folder(args.out, "--out"), allowed_hosts=args.allowed_host,
          open_browser=not args.no_browser)


def cmd_demo(args) -> None:
    """The main job (:mod:`trafficweaving.demo`)."""
    from .demo import run_demo

    run_demo(check_output_folder(args.out, "--out"), trials=args.trials, seed=args.seed, hitl=args.hitl)


# ---------------------------------------------------------------- parser
def _add_schedule_options(p, steps: int) -> None:
    """Options shared by ``train`` and ``crossval``."""
    from .model.cvae import ROBOT_FUTURES, VARIANTS
    from .model.train import OBJECTIVES, TRAINABLE

    p.add_argument("--variant", choices=tuple(VARIANTS), help="model variant (default cvae; with --init, the model's own, "
                                                              "or cvae-hold to give a cvae model hold modes, switched off)")
    p.add_argument("--init", metavar="MODEL", help="fine-tune this checkpoint or authors:PATH (its own schedule: --lr, "
                                                   "--steps, --patience)")
    p.add_argument("--steps", type=POSITIVE, default=steps, help=f"training steps (default {steps})")
    p.add_argument("--lr", type=_float_in(0, 1), help="initial learning rate in (0, 1) (default 1e-3, or 1e-4 with --init)")
    p.add_argument("--validate-every", type=POSITIVE, help="steps between validations (default 1000, or 50 with --init)")
    p.add_argument("--objective", choices=OBJECTIVES, help="training objective: elbo (the paper's, needs q), exact "
                                                           "(-log Σ_z p(z|x) p(y|x,z)); default elbo, or exact for a model without q")
    p.add_argument("--train-parts", choices=tuple(TRAINABLE), help="what learns: all (default), decoder (decoder, "
                                                                   "GMM and hold heads), hold (the hold head alone)")
    p.add_argument("--hold-lr", type=_float_in(0, 1), help="constant learning rate of the hold modes' logits "
                                                           "(default: the main learning rate)")
    p.add_argument("--robot-future", choices=ROBOT_FUTURES, help="what the model takes as the other car's future: "
                   "recorded (the paper's, for planning; default) or guess (the other car holding its present "
                   "acceleration: a driver model, docs/realism.md); with --init, default the init's")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--device", default="auto", help="auto (CUDA when available), cpu, cuda, cuda:N")
    p.add_argument("--json", action="store_true")


def build_parser() -> argparse.ArgumentParser:
    from .model.calibrate import MIX_WEIGHTS, SCALES, TEMPERATURES
    from .model.crossval import MAX_FOLDS
    from .model.evaluate import MAX_NLL_SAMPLES
    from .model.metrics import MAX_SAMPLES
    from .model.predictor import MAX_PLAN_FUTURES, PRECISIONS
    from .planning.candidates import N_CANDIDATES
    from .sim.batch import MAX_EPISODES, RAY_ADDRESS_FORMS, RAY_CONNECT_TIMEOUT_S, WORKERS_PER_CPU
    from .sim.generate import MAX_PAIRS, MAX_TRIALS
    from .sim.humans import HUMAN_SPECS
    from .sim.realism import MAX_ROLLOUTS, ROLLOUT_BYTES, ROLLOUTS
    from .web.options import COUNTDOWN_S, MODES, PLAN_DEADLINE_S

    parser = _Parser(prog="trafficweaving", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("generate", help="generate synthetic human–human trials")
    p.add_argument("--trials", type=_int_at_least(1, MAX_TRIALS), default=STUDY_TRIALS,
                   help=f"number of valid trials, at most {MAX_TRIALS} (default {STUDY_TRIALS}, as the paper)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--pairs", type=_int_at_least(1, MAX_PAIRS), default=19,
                   help=f"pairs of simulated drivers, at most {MAX_PAIRS} (default 19, as the study)")
    p.add_argument("--drivers", default="synthetic", help="who drives both cars: synthetic (the simulated drivers, "
                   "default) or any human agent, e.g. model:driver (self-play; docs/realism.md); replay:FILE "
                   "replays each recording from its own start")
    p.add_argument("--device", default="cpu", help="a model driver's device: cpu (default), auto, cuda, cuda:N")
    p.add_argument("--out", required=True, help="output Parquet file")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_generate)

    p = sub.add_parser("import", help="import the authors' recordings")
    p.add_argument("source", choices=("hitl", "rosbag"), help="hitl: .jld files; rosbag: a folder of ROS1 bags")
    p.add_argument("inputs", nargs="+", help=".jld files (hitl) or one folder (rosbag)")
    p.add_argument("--out", required=True, help="output Parquet file")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_import)

    p = sub.add_parser("stats", help="dataset summary: Table I and marginal driving behaviour (a drive folder: the "
                                     "study's progress per pair)")
    p.add_argument("data", help="Parquet dataset, or a folder of trafficweaving drive recordings")
    p.add_argument("--reference", help="a second dataset (e.g. imported real trials) to compare the humans with")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_stats)

    p = sub.add_parser("plot", help="dataset figures (PNG)")
    p.add_argument("data", help="Parquet dataset")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--reference", help="a second dataset to compare behaviour with")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_plot)

    p = sub.add_parser("train", help="train a CVAE human model, or fine-tune one (--init)")
    p.add_argument("--data", required=True, help="Parquet dataset (trials split 80/20 by trial)")
    p.add_argument("--out", required=True, help="output checkpoint (.pt), written every 1000 steps (50 when fine-tuning)")
    _add_schedule_options(p, steps=50_000)
    p.add_argument("--patience", type=NON_NEGATIVE, help="early stopping: validations without improvement before "
                                                         "stopping (default 0: off); the best weights are kept")
    p.add_argument("--validation-fraction", type=_float_in(0, 1, include_low=True), default=0.2,
                   help="fraction of the trials held out for validation, split by trial (0: train on all, no validation)")
    p.add_argument("--resume", help="continue the run saved in this training checkpoint")
    p.set_defaults(func=cmd_train)

    processes = WORKERS_PER_CPU * (os.cpu_count() or 1)  # of a local process pool: each holds the data and models
    p = sub.add_parser("crossval", help="k-fold cross-validation by trial (choosing the number of steps by the folds)")
    p.add_argument("--data", required=True, help="Parquet dataset")
    p.add_argument("--folds", type=_int_at_least(2, MAX_FOLDS), default=5, help=f"folds, 2..{MAX_FOLDS} (default 5)")
    p.add_argument("--reference", help="a model scored on the same folds (checkpoint, default, or authors:PATH)")
    p.add_argument("--out", help="folder for each fold's model at the chosen steps (fold_K.pt, with its held-out trials)")
    p.add_argument("--beat-reference", action="store_true",
                   help="choose the steps only among those where every fold beats the --reference model")
    p.add_argument("--nested", action="store_true",
                   help="also train without each pair of folds, so that each fold's steps are chosen by an inner "
                        "cross-validation without it (the nested estimate); --out then also gets nested/ for calibrate --nested")
    p.add_argument("--workers", type=_int_at_least(1, processes), default=1,
                   help=f"fits run in this many processes, 1..{processes} ({WORKERS_PER_CPU} per CPU core here; "
                        f"default 1)")
    _add_schedule_options(p, steps=1000)
    p.set_defaults(func=cmd_crossval)

    p = sub.add_parser("calibrate", help="choose a model's latent temperature and output scale on out-of-fold predictions")
    p.add_argument("--data", required=True, help="the Parquet dataset the cross-validation ran on")
    p.add_argument("--folds", required=True, action="append", help="folder of fold models written by `crossval --out`; "
                   "repeated: candidate recipes, the best is chosen with its calibration")
    p.add_argument("--model", required=True, action="append", help="the checkpoint to calibrate (or default), trained on "
                   "every fold; one per --folds, in the same order")
    p.add_argument("--nested", action="store_true", help="also report the nested estimate: each fold's candidate and "
                   "calibration chosen on its inner folds (needs folders written by `crossval --nested --out`)")
    p.add_argument("--workers", type=_int_at_least(1, processes), default=1,
                   help=f"the grid is scored in this many processes, 1..{processes} ({WORKERS_PER_CPU} per CPU core here; "
                        f"default 1)")
    p.add_argument("--temperatures", type=_floats_in(0, 100), default=TEMPERATURES,
                   help=f"latent temperatures of the grid, comma-separated (default {','.join(f'{v:g}' for v in TEMPERATURES)})")
    p.add_argument("--scales", type=_floats_in(0, 100), default=SCALES,
                   help=f"output scales of the grid, comma-separated (default {','.join(f'{v:g}' for v in SCALES)})")
    p.add_argument("--companion", help="a model not trained on --data (e.g. authors:PATH) to mix the calibrated model with, "
                   "the weight chosen out-of-fold among " + ", ".join(f"{w:g}" for w in MIX_WEIGHTS) + " and 1; one model "
                   "(not a mixture) with --model's standardisation")
    p.add_argument("--out", required=True, help="the calibrated checkpoint")
    p.add_argument("--out-folds", help="also write the calibrated fold models here (for out-of-fold reports)")
    p.add_argument("--samples", type=_int_at_least(2, MAX_SAMPLES), default=100,
                   help=f"sampled futures per instance for the coverage, 2..{MAX_SAMPLES}")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("mix", help="a mixture of a model with a companion model at a given weight (docs/realism.md)")
    p.add_argument("--model", required=True, help="the first component: a checkpoint or a shipped model's name")
    p.add_argument("--companion", required=True, help="the second component (e.g. authors:PATH), conditioned like --model")
    p.add_argument("--weight", required=True, type=_float_in(0, 1), help="--model's weight, strictly between 0 and 1")
    p.add_argument("--person-weight", type=_float_in(0, 1, include_low=True, include_high=True),
                   help="--model's weight when the mixture drives a car facing a person (self-play; default --weight)")
    p.add_argument("--out", required=True, help="the mixture's checkpoint")
    p.add_argument("--folds", help="also mix the fold models of `crossval --out` in this folder ...")
    p.add_argument("--out-folds", help="... and write them here (for out-of-fold reports: `realism --folds`)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_mix)

    p = sub.add_parser("evaluate", help="NLL, coverage and displacement errors of a human model on every human agent of a dataset")
    p.add_argument("--model", default="default", help="checkpoint path, default, or authors:PATH")
    p.add_argument("--data", required=True, help="Parquet dataset")
    p.add_argument("--samples", type=_int_at_least(1, MAX_NLL_SAMPLES), default=50,
                   help=f"latent samples of the sampled NLL estimators, 1..{MAX_NLL_SAMPLES}")
    p.add_argument("--coverage-samples", type=_int_at_least(2, MAX_SAMPLES), default=100,
                   help=f"sampled futures per instance for the position coverage, 2..{MAX_SAMPLES}")
    p.add_argument("--ade-samples", type=_int_at_least(1, MAX_SAMPLES), default=20,
                   help=f"sampled futures per instance for minADE/minFDE, 1..{MAX_SAMPLES}")
    p.add_argument("--max-sampled-instances", type=NON_NEGATIVE, default=5000,
                   help="sample futures for at most this many instances (chosen at random with --seed; default 5000)")
    p.add_argument("--per-instance", metavar="FILE.parquet", help="also write every instance's values to this Parquet file")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--device", default="auto")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("predict", help="figure of sampled human futures (the paper's Fig. 3)")
    p.add_argument("--model", default="default", help="checkpoint path, default, or authors:PATH")
    p.add_argument("--data", required=True, help="Parquet dataset")
    p.add_argument("--at", action="append", required=True, metavar="TRIAL:T[:AGENT]",
                   help="trial index and present step (repeat for more panels); agent defaults to the first human")
    p.add_argument("--samples", type=_int_at_least(1, MAX_SAMPLES), default=50,
                   help=f"sampled futures per panel, 1..{MAX_SAMPLES} (default 50)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--device", default="auto")
    p.add_argument("--out", required=True, help="output PNG")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_predict)

    p = sub.add_parser("bench", help="time the planner")
    p.add_argument("what", choices=("plan",), help="plan: one two-stage plan at the paper's budget")
    p.add_argument("--model", default="default")
    p.add_argument("--repeats", type=POSITIVE, default=3)
    p.add_argument("--deadline", type=_float_in(0, 3600), help="real-time mode: return within this many seconds")
    p.add_argument("--first-stage-samples", type=_int_at_least(1, MAX_PLAN_FUTURES // N_CANDIDATES), default=16,
                   help=f"human futures per candidate, 1..{MAX_PLAN_FUTURES // N_CANDIDATES} (default 16)")
    p.add_argument("--finalists", type=_int_at_least(1, N_CANDIDATES), default=32)
    p.add_argument("--second-stage-samples", type=_int_at_least(1, MAX_PLAN_FUTURES), default=1024,
                   help=f"human futures per finalist (default 1024); a plan samples at most {MAX_PLAN_FUTURES} in all "
                        f"({N_CANDIDATES} × first stage + finalists × second stage)")
    p.add_argument("--precision", choices=PRECISIONS, default="auto",
                   help="decoder matrix multiplies; auto: bfloat16 on CPUs with native bfloat16, else float32")
    p.add_argument("--threads", type=_int_at_least(1, os.cpu_count() or 1),
                   help=f"CPU threads, 1..{os.cpu_count() or 1} (default: PyTorch's choice)")
    p.add_argument("--device", default="auto")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("simulate", help="closed-loop episodes of a robot against a human, with metrics and CIs")
    p.add_argument("--episodes", type=_int_at_least(1, MAX_EPISODES), required=True,
                   help=f"episodes 0..N-1 (each from --seed and its index), N in 1..{MAX_EPISODES}")
    p.add_argument("--robot", default="planner", help="planner (default: within nuPlan's comfort limits until time "
                                                      "runs short, the human beside brakes along with it or the "
                                                      "human ahead brakes hard, then decisive; makes room beside "
                                                      "the human), "
                                                      "planner-decisive (keeps to a lane change and settles on the "
                                                      "lane centre), planner-paper (the paper's exactly), "
                                                      "planner-comfort (within nuPlan's comfort limits), "
                                                      "planner-cautious (CVaR), planner-cv or rules")
    p.add_argument("--human", required=True, help=HUMAN_SPECS)
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--model", default="default", help="the planner's human model: checkpoint path, default, or authors:PATH")
    timing = p.add_mutually_exclusive_group()
    timing.add_argument("--deadline", type=_float_in(0, 3600), default=REPLAN_PERIOD_S,
                        help=f"the planner's real-time mode: plan within this many seconds (default {REPLAN_PERIOD_S}, "
                             f"the replanning period)")
    timing.add_argument("--full-budget", dest="deadline", action="store_const", const=None,
                        help="plan with the paper's fixed sample counts however long it takes (~1-2 s a plan on a CPU)")
    p.add_argument("--workers", type=POSITIVE, default=1, help=f"episodes run at once (default 1: in this process), "
                   f"at most {WORKERS_PER_CPU} per CPU core here ({WORKERS_PER_CPU * (os.cpu_count() or 1)}), or "
                   f"{MAX_EPISODES} on a Ray cluster")
    p.add_argument("--engine", choices=("local", "ray"), default="local",
                   help="local: a process pool; ray: Ray tasks (pip install 'trafficweaving[ray]')")
    p.add_argument("--address", help=f"with --engine ray: the Ray cluster to join, {RAY_ADDRESS_FORMS}, its head "
                   f"answering within {RAY_CONNECT_TIMEOUT_S:g} s (default: a new local instance)")
    p.add_argument("--device", default="cpu", help="the models' device: cpu (default), auto, cuda, cuda:N")
    p.add_argument("--precision", choices=PRECISIONS, default="auto", help="the planner's sampling precision (default "
                   "auto: bfloat16 where the CPU has it; int8: fused and compiled, docs/planner.md)")
    p.add_argument("--out", default="simulation", help="output folder (default ./simulation): "
                   "episodes/episode_NNNNNN.parquet and summary.json; a rerun resumes")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("realism", help="closed-loop realism of a human agent on recorded trials (WOSAC-style, docs/realism.md)")
    p.add_argument("--human", help=f"the agent: {HUMAN_SPECS}")
    p.add_argument("--folds", metavar="DIR", help="instead of --human: the fold models of `crossval --out DIR` on the "
                   "same data, each driving the trials it did not train on (out-of-fold)")
    p.add_argument("--data", required=True, help="recorded trials (Parquet); every car labelled human is rolled out")
    p.add_argument("--rollouts", type=_int_at_least(2, MAX_ROLLOUTS), default=ROLLOUTS,
                   help=f"rollouts per recorded human, 2..{MAX_ROLLOUTS} (default {ROLLOUTS}; each holds about "
                        f"{ROLLOUT_BYTES // 1000} kB while they run)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--device", default="cpu", help="a model agent's device: cpu (default), auto, cuda, cuda:N")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_realism)

    p = sub.add_parser("plot-episode", help="the paper's Fig. 6 of an episode (or any trial), and its animation")
    p.add_argument("data", help="an episode log (simulate's DIR/episodes/episode_K.parquet) or any dataset")
    p.add_argument("--trial", type=NON_NEGATIVE, default=0, help="which trial of the file (default 0)")
    p.add_argument("--out", required=True, help="output PNG (Fig. 6: accelerations over time and (x, y) paths)")
    p.add_argument("--gif", help="also an animated GIF; for a planner's episode with each plan's chosen future "
                                 "and sampled human futures (the episode is run again to recover them)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_plot_episode)

    p = sub.add_parser("drive", help="drive the human car against the planner in the browser (or two people at "
                                     "two browsers: --mode human-human)")
    p.add_argument("--port", type=_int_at_least(0, 65535), default=8000, help="TCP port (default 8000; 0: any free port)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1: this machine only; "
                   "another address needs the printed link's key and each room's token)")
    p.add_argument("--allowed-host", action="append", default=[], metavar="NAME[:PORT]",
                   help="another name pages may use for this server (repeatable; default port: --port); requests "
                        "for any other host than the served address are refused")
    p.add_argument("--no-browser", action="store_true", help="do not open the page in the browser")
    p.add_argument("--mode", choices=MODES, default="robot",
                   help="robot: a person against the planner; human-human: rooms of two browsers, one person each")
    p.add_argument("--model", default="default", help="the planner's human model: checkpoint path, default, or authors:PATH")
    p.add_argument("--out", default="drives", help="folder the trials are recorded in (default: drives)")
    p.add_argument("--deadline", type=_float_in(0, REPLAN_PERIOD_S), default=PLAN_DEADLINE_S,
                   help=f"the planner's real-time deadline per plan, s, in (0, {REPLAN_PERIOD_S:g}) (default "
                        f"{PLAN_DEADLINE_S})")
    p.add_argument("--threads", type=_int_at_least(1, os.cpu_count() or 1),
                   help=f"planner CPU threads, 1..{os.cpu_count() or 1} (default: all cores but one)")
    p.add_argument("--countdown", type=_int_at_least(0, 10), default=COUNTDOWN_S,
                   help=f"seconds of countdown before a trial, 0..10 (default {COUNTDOWN_S})")
    p.set_defaults(func=cmd_drive, json=False)

    p = sub.add_parser("demo", help="the main job, end to end, on the shipped defaults")
    p.add_argument("--out", default="out", help="output folder (default: out)")
    p.add_argument("--trials", type=_int_at_least(1, MAX_TRIALS), default=STUDY_TRIALS,
                   help=f"synthetic trials to generate, at most {MAX_TRIALS} (default {STUDY_TRIALS}, as the paper)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--hitl", help="folder of the authors' .jld recordings (default: ../shared/reference/hitl if present)")
    p.set_defaults(func=cmd_demo, json=False)
    return parser


def _raise_terminated(signum, frame):
    raise _Terminated


def _die_by_signal(signum: int) -> None:
    """Exit as killed by ``signum`` (the shell convention: status 128 + signum), after cleanup."""
    sys.stdout.flush()
    signal.signal(signum, signal.SIG_DFL)
    os.kill(os.getpid(), signum)
    sys.exit(128 + signum)  # if the signal could not end the process


def main(argv: list[str] | None = None) -> int:
    """Run one command. Bad input: one line on stderr and status 2. SIGTERM and Ctrl-C (SIGINT):
    temporary files are removed, a one-line notice is printed, and the process ends by that
    signal (status 143 and 130 in a shell); also while the parser's imports (PyTorch) load."""
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    where = "trafficweaving"
    try:
        try:
            args = build_parser().parse_args(argv)
        except SystemExit as exc:  # --help (0) or a malformed option (2, one line printed)
            return int(exc.code or 0)
        where = f"trafficweaving {args.command}"
        args.func(args)
    except InputError as exc:
        print(f"{where}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # unwritable output path, full disk, ...
        print(f"{where}: error: {exc.filename or ''}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, _Terminated) as exc:
        signum = signal.SIGINT if isinstance(exc, KeyboardInterrupt) else signal.SIGTERM
        print(f"\n{where}: interrupted ({signal.Signals(signum).name}); no partial output was left", file=sys.stderr)
        _die_by_signal(signum)
    finally:
        signal.signal(signal.SIGTERM, previous)
    return 0
