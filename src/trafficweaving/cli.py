"""Command-line interface: ``trafficweaving <command> ...`` (also ``python -m trafficweaving``).

Every reporting command takes ``--json`` and then prints exactly one JSON object on stdout.
Bad input ends with a one-line message on stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from .errors import InputError

DEFAULT_HITL_DIRS = ("../shared/reference/hitl", "shared/reference/hitl")
DEMO_REAL_PICKS = [(2, 1, 10), (7, 1, 20), (12, 1, 25)]
"""(trial, human agent, t) of the real trials drawn in the demo's prediction figure."""


def _emit(args, payload: dict, text: str) -> None:
    print(json.dumps(payload) if args.json else text)


def _table1_text(table: dict, counts: dict) -> str:
    from .data.stats import TABLE1_PAPER

    def cell(dv, k):
        value = table[dv][k]
        ours = "   -  " if value is None else f"{100 * value:5.1f}%"
        return f"{ours} (paper {100 * TABLE1_PAPER[dv][k]:4.1f}%, n={counts[dv][k]})"

    lines = ["Table I: fraction of trials where the car starting in the left lane passes in front",
             f"{'tco':>5} | {'Δv = -2 m/s':^30} | {'Δv = +2 m/s':^30}"]
    for k in ("1", "2", "3"):
        lines.append(f"{k + ' s':>5} | {cell('-2', k):^30} | {cell('2', k):^30}")
    lines.append(f"Δv = 0 (all tco): {cell('0', 'all')}")
    return "\n".join(lines)


# ---------------------------------------------------------------- commands
def cmd_generate(args) -> None:
    from .data.generate import generate_trials

    if args.trials < 1:
        raise InputError(f"--trials must be a positive integer, got {args.trials}")
    start = time.perf_counter()
    trials, report = generate_trials(args.trials, seed=args.seed, pairs=args.pairs, progress=not args.json)
    trials.write_parquet(args.out)
    seconds = time.perf_counter() - start
    payload = {"trials": len(trials), "simulated": report.simulated, "rejected": report.rejected,
               "seed": args.seed, "out": str(args.out), "seconds": round(seconds, 3)}
    rejected = ", ".join(f"{k} {v}" for k, v in report.rejected.items())
    _emit(args, payload, f"wrote {len(trials)} valid trials to {args.out} in {seconds:.1f} s "
                         f"({report.simulated} simulated; rejected: {rejected})")


def cmd_import(args) -> None:
    if args.source == "hitl":
        from .data.hitl import read_hitl

        trials = read_hitl(args.inputs)
        trials.write_parquet(args.out)
        _emit(args, {"trials": len(trials), "out": str(args.out)},
              f"imported {len(trials)} human-in-the-loop trials into {args.out}")
    else:
        from .data.rosbag import read_rosbags

        if len(args.inputs) != 1:
            raise InputError(f"import rosbag takes one folder of .bag files, got {len(args.inputs)} paths")
        result = read_rosbags(args.inputs[0])
        result.trials.write_parquet(args.out)
        rejected_total = sum(result.rejected.values())
        _emit(args, {"trials": len(result.trials), "rejected": rejected_total,
                     "rejected_by_reason": result.rejected, "out": str(args.out)},
              f"imported {len(result.trials)} trials into {args.out}; rejected {rejected_total} bags "
              f"({', '.join(f'{k} {v}' for k, v in result.rejected.items()) or 'none'})")


def cmd_stats(args) -> None:
    from .data.behaviour import behaviour_samples, compare_behaviour, format_comparison, summarise
    from .data.stats import table1
    from .data.trials import load_trials

    trials = load_trials(args.data)
    t1 = table1(trials)
    humans = behaviour_samples(trials, role="human")
    payload = {
        "trials": len(trials),
        "steps": {"min": int(trials.lengths.min()), "mean": float(trials.lengths.mean()),
                  "max": int(trials.lengths.max())},
        "table1": t1["table1"],
        "table1_counts": t1["counts"],
        "behaviour": {name: summarise(values) for name, values in humans.items()},
    }
    text = [f"{args.data}: {len(trials)} trials, {trials.lengths.min()}–{trials.lengths.max()} steps "
            f"(mean {trials.lengths.mean():.1f}) of {trials.dt} s", _table1_text(t1["table1"], t1["counts"])]
    if args.reference:
        reference = behaviour_samples(load_trials(args.reference), role="human")
        comparison = compare_behaviour(humans, reference)
        payload["behaviour_vs_reference"] = comparison
        text += [f"Human behaviour vs {args.reference}:", format_comparison(comparison)]
    _emit(args, payload, "\n".join(text))


def cmd_plot(args) -> None:
    from .data.trials import load_trials

    trials = load_trials(args.data)
    reference = load_trials(args.reference) if args.reference else None
    paths = write_figures(trials, Path(args.out), reference)
    _emit(args, {"figures": [str(p) for p in paths]}, "\n".join(f"wrote {p}" for p in paths))


def write_figures(trials, out: Path, reference=None) -> list[Path]:
    """Write the dataset figures (trajectories, profiles, Table I, and behaviour vs ``reference``
    when given) into folder ``out``; returns their paths."""
    from .data.behaviour import behaviour_samples
    from .data.stats import table1
    from .viz.figures import plot_behaviour, plot_profiles, plot_table1, plot_trajectories

    out.mkdir(parents=True, exist_ok=True)
    paths = [
        plot_trajectories(trials, out / "trajectories.png"),
        plot_profiles(trials, out / "profiles.png"),
        plot_table1(table1(trials)["table1"], out / "table1.png"),
    ]
    if reference is not None:
        paths.append(plot_behaviour(behaviour_samples(trials, "human"), behaviour_samples(reference, "human"),
                                    out / "behaviour_vs_reference.png"))
    return paths


def _train_config(args):
    """The :class:`TrainConfig` of ``train`` / ``crossval`` options: the paper's schedule from
    scratch, the fine-tuning defaults with ``--init``; ``--lr`` etc. override either."""
    from dataclasses import replace

    from .model.train import FINE_TUNING, TrainConfig

    for name in ("steps", "validate_every"):
        value = getattr(args, name, None)
        if value is not None and value < 1:
            raise InputError(f"--{name.replace('_', '-')} must be a positive integer, got {value}")
    if (getattr(args, "patience", None) or 0) < 0:
        raise InputError(f"--patience must be 0 (off) or a positive integer, got {args.patience}")
    if args.lr is not None and not 0 < args.lr < 1:
        raise InputError(f"--lr must be a learning rate in (0, 1), got {args.lr}")
    fraction = getattr(args, "validation_fraction", 0.2)
    if not 0 <= fraction < 1:
        raise InputError(f"--validation-fraction must be in [0, 1), got {fraction}")
    if fraction == 0 and (getattr(args, "patience", None) or 0) > 0:
        raise InputError("--patience needs a validation set (expected --validation-fraction above 0)")
    tc = TrainConfig(steps=args.steps, seed=args.seed, validation_fraction=fraction)
    if args.init:
        tc = replace(tc, **FINE_TUNING)
    overrides = {"lr_initial": args.lr, "validate_every": args.validate_every,
                 "patience": getattr(args, "patience", None)}
    tc = replace(tc, **{k: v for k, v in overrides.items() if v is not None})
    return replace(tc, lr_final=min(tc.lr_final, tc.lr_initial), checkpoint_every=min(tc.checkpoint_every, tc.validate_every))


def _log(args):
    return (lambda line: print(line, file=sys.stderr)) if args.json else print


def cmd_train(args) -> None:
    from .data.trials import load_trials
    from .model.checkpoint import choose_device
    from .model.train import train

    if args.init and args.resume:
        raise InputError("--init and --resume exclude each other (expected one: fine-tune a model, or continue a run)")
    tc = _train_config(args)
    trials = load_trials(args.data)
    result = train(trials, args.out, args.variant, tc, resume=args.resume,
                   device=choose_device(args.device), progress=not args.json, log=_log(args), init=args.init)
    validation = result.validation or {"instances": 0, "nll_exact": None, "nll_is": None, "nll_naive": None}
    payload = {"variant": result.model.config.name, "steps": result.step, **validation,
               "best_step": result.best_step, "init": args.init,
               "steps_per_second": round(result.steps_per_second, 2), "out": str(args.out)}
    _emit(args, payload, f"trained {payload['variant']} for {result.step} steps "
                         f"({result.steps_per_second:.1f} steps/s) -> {args.out}\n"
                         f"validation ({validation['instances']} exemplars): "
                         f"NLL exact {_fmt(validation['nll_exact'])}, IS {_fmt(validation['nll_is'])}, "
                         f"naive {_fmt(validation['nll_naive'])} nats")


def cmd_crossval(args) -> None:
    from .data.trials import load_trials
    from .model.checkpoint import choose_device
    from .model.crossval import crossval

    tc = _train_config(args)
    trials = load_trials(args.data)
    result = crossval(trials, args.folds, tc, variant=args.variant, init=args.init, reference=args.reference,
                      seed=args.seed, device=choose_device(args.device), progress=not args.json, log=_log(args),
                      out=args.out, beat_reference=args.beat_reference)
    summary = result.summary()
    payload = {**summary, "data": args.data, "init": args.init, "variant": args.variant, "out": args.out}
    ref = summary["reference"]
    lines = [f"{args.folds}-fold cross-validation by trial on {args.data} "
             f"({'fine-tuning ' + args.init if args.init else 'training from scratch'})",
             f"held-out exact NLL at the chosen {summary['steps']} steps: "
             + " ".join(f"{v:.2f}" for v in summary["folds"]) + f"  mean {summary['nll_exact']:.3f}",
             f"nested (each fold at the steps its other folds choose): mean {summary['nested']['nll_exact']:.3f}"]
    if ref:
        lines.append(f"reference {ref['model']}: " + " ".join(f"{v:.2f}" for v in ref["folds"]) + f"  mean {ref['nll_exact']:.3f}")
    _emit(args, payload, "\n".join(lines))


def cmd_calibrate(args) -> None:
    from .data.trials import load_trials
    from .model.calibrate import calibrate
    from .model.checkpoint import default_model_path, model_from_checkpoint, read_checkpoint, save_checkpoint
    from .model.crossval import out_of_fold_models

    if args.samples < 2:
        raise InputError(f"--samples must be at least 2, got {args.samples}")
    path = default_model_path() if args.model == "default" else Path(args.model)
    payload = read_checkpoint(path)  # a bad --model fails before the long grid
    trials = load_trials(args.data)
    result = calibrate(trials, args.folds, samples=args.samples, seed=args.seed, log=_log(args))
    summary = result.summary()
    temperature, scale = summary["latent_temperature"], summary["output_scale"]
    model = model_from_checkpoint(payload, path).set_calibration(temperature, scale)
    kept = {k: v for k, v in payload.items() if k not in ("format", "version", "config", "state_dict")}
    save_checkpoint(args.out, model, **{**kept, "calibration": summary})
    if args.out_folds:
        Path(args.out_folds).mkdir(parents=True, exist_ok=True)
        for k, (fold_model, held) in enumerate(out_of_fold_models(args.folds)):
            save_checkpoint(Path(args.out_folds) / f"fold_{k + 1}.pt", fold_model.set_calibration(temperature, scale),
                            held_out_trials=held, calibration=summary)
    cov = summary["coverage_90"]
    _emit(args, {**summary, "model": str(args.model), "out": str(args.out)},
          f"calibrated {args.model} -> {args.out}: latent temperature {temperature:g}, output scale {scale:g} "
          f"(out-of-fold NLL {summary['nll_exact']:.2f}, 90 % coverage at 1.5 s x {100 * cov['x']:.0f} %, "
          f"y {100 * cov['y']:.0f} %)")


def _fmt(value) -> str:
    return "n/a" if value is None else f"{value:.3f}"


def cmd_evaluate(args) -> None:
    from .data.trials import load_trials
    from .model.checkpoint import choose_device, load_model
    from .model.exemplars import build_exemplars
    from .model.metrics import DIRECTIONS, PHASES, evaluate_instances

    if args.samples < 1:
        raise InputError(f"--samples must be a positive integer, got {args.samples}")
    if args.coverage_samples < 2:
        raise InputError(f"--coverage-samples must be at least 2, got {args.coverage_samples}")
    if args.ade_samples < 1:
        raise InputError(f"--ade-samples must be a positive integer, got {args.ade_samples}")
    if args.max_sampled_instances is not None and args.max_sampled_instances < 0:
        raise InputError(f"--max-sampled-instances must be 0 or more, got {args.max_sampled_instances}")
    if args.per_instance is not None and Path(args.per_instance).is_dir():
        raise InputError(f"--per-instance {args.per_instance}: is a folder (expected a .parquet file to write)")
    model = load_model(args.model, choose_device(args.device))
    trials = load_trials(args.data)
    exemplars = build_exemplars(trials)
    if len(exemplars) == 0:
        raise InputError(f"{args.data}: no prediction instances (expected human agents in trials of at least 21 steps)")
    metrics = evaluate_instances(model, trials, exemplars, samples=args.coverage_samples, ade_samples=args.ade_samples,
                                 max_sampled=args.max_sampled_instances, nll_samples=args.samples, seed=args.seed)
    result = metrics.summary()
    if args.per_instance is not None:
        metrics.write_parquet(args.per_instance, {"model": args.model, "data": str(args.data), "seed": args.seed,
                                                  "samples": args.samples, "coverage_samples": args.coverage_samples,
                                                  "ade_samples": args.ade_samples})
    payload = {**result, "model": args.model, "variant": model.config.name}
    pct = lambda v: "n/a" if v is None else f"{100 * v:.0f}"  # noqa: E731
    meters = lambda v: "n/a" if v is None else f"{v:.2f}"  # noqa: E731
    phases = ", ".join(f"{p} {_fmt(result['nll_exact_by_phase'][p]['nll_exact'])} (n={result['nll_exact_by_phase'][p]['instances']})"
                       for p in PHASES)
    coverage = "; ".join(f"{d} " + ", ".join(f"{h} s {pct(c['50'])}/{pct(c['90'])}" for h, c in result["coverage"][d].items())
                         for d in DIRECTIONS)
    _emit(args, payload, f"{args.model} ({model.config.name}) on {args.data}: {result['instances']} instances\n"
                         f"NLL per instance (nats, 15×2 accelerations in m/s²): exact {result['nll_exact']:.3f}, "
                         f"importance-sampled {_fmt(result['nll_is'])}, naive {result['nll_naive']:.3f}\n"
                         f"  exact by direction (15 accelerations): x {_fmt(result['nll_exact_by_direction']['x'])}, "
                         f"y {_fmt(result['nll_exact_by_direction']['y'])}\n"
                         f"  exact by lane-change phase: {phases}\n"
                         f"Sampled positions ({result['sampled_instances']} instances, {args.coverage_samples} samples each):\n"
                         f"  coverage of the 50/90 % central intervals (%): {coverage}\n"
                         f"  minADE {meters(result['min_ade_m'])} m, minFDE {meters(result['min_fde_m'])} m "
                         f"(best of {args.ade_samples})"
                         + (f"\nper-instance values: {args.per_instance}" if args.per_instance is not None else ""))


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
    last = int(trials.lengths[i]) - 16
    if not 4 <= t <= last:
        raise InputError(f"--at {text!r}: t must be within 4..{last} for trial {i} ({trials.lengths[i]} steps)")
    return i, agent, t


def cmd_predict(args) -> None:
    from .data.trials import load_trials
    from .model.checkpoint import choose_device, load_model
    from .viz.model_figures import plot_predictions

    if args.samples < 1:
        raise InputError(f"--samples must be a positive integer, got {args.samples}")
    trials = load_trials(args.data)
    picks = [_parse_pick(text, trials) for text in args.at]
    model = load_model(args.model, choose_device(args.device))
    path = plot_predictions(model, trials, picks, args.out, samples=args.samples, seed=args.seed,
                            title=f"{args.model} ({model.config.name}) on {Path(args.data).name}")
    _emit(args, {"out": str(path), "panels": len(picks)}, f"wrote {path}")


def cmd_bench(args) -> None:
    import statistics

    import torch

    from .model.checkpoint import choose_device, load_model
    from .planning.candidates import Action
    from .planning.costs import PaperCost
    from .planning.planner import Budget, Planner, example_history
    from .scenario import LANE_CENTRE_Y

    if args.repeats < 1:
        raise InputError(f"--repeats must be a positive integer, got {args.repeats}")
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    device = choose_device(args.device)
    planner = Planner(load_model(args.model, device), Budget(args.first_stage_samples, args.finalists, args.second_stage_samples),
                      precision=args.precision)
    history, first = example_history(), Action.of(0.0, "right").index
    cost = PaperCost(goal_y=LANE_CENTRE_Y["left"])
    planner.plan(history, first, cost, deadline=args.deadline)  # warm-up: allocations, measured speed
    plans = [planner.plan(history, first, cost, deadline=args.deadline) for _ in range(args.repeats)]
    seconds = [p.seconds for p in plans]
    payload = {"futures": min(p.futures for p in plans), "seconds": statistics.median(seconds),
               "seconds_all": [round(s, 4) for s in seconds], "candidates": len(plans[0].candidates),
               "first_stage_samples": plans[0].first_stage_samples, "finalists": len(plans[0].finalists),
               "second_stage_samples": plans[0].second_stage_samples, "deadline": args.deadline,
               "device": str(device), "threads": torch.get_num_threads(), "model": args.model,
               "precision": str(planner.sampler.batched.matmul_dtype).removeprefix("torch."),
               "timings": {k: round(v, 4) for k, v in plans[-1].timings.items()}}
    _emit(args, payload, f"plan: {payload['futures']} human futures for {payload['candidates']} candidates in "
                         f"{payload['seconds']:.3f} s (median of {args.repeats}; {device}, {payload['threads']} threads)")


def find_hitl_dir(explicit: str | None) -> Path | None:
    """The folder of the authors' human-in-the-loop ``.jld`` files: ``explicit`` if given, else the
    first of ``DEFAULT_HITL_DIRS`` that exists (relative to the working directory)."""
    if explicit:
        path = Path(explicit)
        if not path.is_dir():
            raise InputError(f"{path}: not a folder (expected the folder of the authors' .jld files)")
        return path
    return next((Path(d) for d in DEFAULT_HITL_DIRS if Path(d).is_dir()), None)


def cmd_demo(args) -> None:
    """The main job: a human–human dataset on the shipped driver model, its Table I, statistics and
    figures, compared with the authors' real human drivers when their recordings are at hand."""
    from .data.behaviour import behaviour_samples, compare_behaviour, format_comparison
    from .data.generate import generate_trials
    from .data.stats import table1

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    trials, report = generate_trials(args.trials, seed=args.seed, progress=True)
    trials.write_parquet(out / "human_human.parquet")
    print(f"generated {len(trials)} valid human–human trials in {time.perf_counter() - start:.1f} s "
          f"({report.simulated} simulated, rejected {report.rejected}) -> {out / 'human_human.parquet'}")
    t1 = table1(trials)
    print(_table1_text(t1["table1"], t1["counts"]))

    reference = None
    hitl_dir = find_hitl_dir(args.hitl)
    if hitl_dir is not None:
        from .data.hitl import read_hitl

        reference = read_hitl(sorted(hitl_dir.glob("*.jld")))
        reference.write_parquet(out / "hitl.parquet")
        comparison = compare_behaviour(behaviour_samples(trials, "human"), behaviour_samples(reference, "human"))
        print(f"\nSimulated human drivers vs the {len(reference)} real human-in-the-loop trials in {hitl_dir}:")
        print(format_comparison(comparison))
    else:
        print("\n(authors' human-in-the-loop recordings not found; pass --hitl DIR to compare with real drivers)")
    for path in write_figures(trials, out / "figures", reference):
        print(f"wrote {path}")
    _demo_human_model(trials, reference, out / "figures")
    _demo_planner(out / "figures")


def _demo_planner(figures: Path) -> None:
    """One full-budget plan with the shipped model, drawn beside braking and accelerating alternatives."""
    from .model.checkpoint import load_model
    from .planning.candidates import Action
    from .planning.costs import PaperCost
    from .planning.planner import Planner, example_history
    from .scenario import LANE_CENTRE_Y
    from .viz.planning_figures import plot_plan

    planner = Planner(load_model("default"))
    path = plot_plan(planner, example_history(), Action.of(0.0, "right").index, PaperCost(goal_y=LANE_CENTRE_Y["left"]),
                     figures / "plan.png")
    print(f"\nplanned against {planner.budget.futures} sampled human futures "
          f"(4096 candidates × {planner.budget.first_stage_samples}, best {planner.budget.finalists} × "
          f"{planner.budget.second_stage_samples}); wrote {path}")


def _demo_human_model(trials, reference, figures: Path) -> None:
    """The shipped human model on the real trials (when at hand) and its predictions as a figure."""
    from .model.checkpoint import default_model_path, load_checkpoint
    from .model.evaluate import evaluate
    from .model.exemplars import build_exemplars
    from .viz.model_figures import plot_predictions

    model, payload = load_checkpoint(default_model_path())
    if reference is not None:
        result = evaluate(model, build_exemplars(reference)).summary()
        print(f"\nShipped human model ({model.config.name}: {payload.get('summary', 'see docs/model.md')}) on the "
              f"{len(reference)} real trials: {result['instances']} instances, NLL exact {result['nll_exact']:.3f}, "
              f"IS {_fmt(result['nll_is'])}, naive {result['nll_naive']:.3f} nats (the authors' model: -12.717)")
        cv = payload.get("crossval")
        if cv:  # trained on these trials: the honest score is the cross-validated one
            print(f"  in-sample: the model was fine-tuned on these trials; {len(cv['folds'])}-fold cross-validated by trial "
                  f"it scores {cv['nll_exact']:.3f} (nested {cv['nested']['nll_exact']:.3f}; the authors' model "
                  f"{cv['reference']['nll_exact']:.3f} on the same folds)")
        calibration = payload.get("calibration")
        if calibration:
            cov = calibration["coverage_90"]
            print(f"  calibrated out-of-fold (latent temperature {calibration['latent_temperature']:g}, output scale "
                  f"{calibration['output_scale']:g}): NLL {calibration['nll_exact']:.3f}, 90 % position intervals 1.5 s "
                  f"ahead cover {100 * cov['x']:.0f} % (x) and {100 * cov['y']:.0f} % (y) of real positions")
        picks, data, name = DEMO_REAL_PICKS, reference, "predictions_real.png"
    else:
        picks, data, name = [(0, 0, 12), (1, 1, 20)], trials, "predictions_synthetic.png"
    print(f"wrote {plot_predictions(model.to('cpu'), data, picks, figures / name, title='shipped human model: 50 sampled futures')}")


# ---------------------------------------------------------------- parser
def _add_schedule_options(p, steps: int) -> None:
    """Options shared by ``train`` and ``crossval``."""
    from .model.cvae import VARIANTS

    p.add_argument("--variant", choices=tuple(VARIANTS), help="model variant (default cvae; with --init, the model's own)")
    p.add_argument("--init", metavar="MODEL", help="fine-tune this checkpoint (its own schedule: --lr, --steps, --patience)")
    p.add_argument("--steps", type=int, default=steps, help=f"training steps (default {steps})")
    p.add_argument("--lr", type=float, help="initial learning rate (default 1e-3, or 1e-4 with --init)")
    p.add_argument("--validate-every", type=int, help="steps between validations (default 1000, or 50 with --init)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="auto", help="auto (CUDA when available), cpu, cuda, cuda:N")
    p.add_argument("--json", action="store_true")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="trafficweaving", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("generate", help="generate synthetic human–human trials")
    p.add_argument("--trials", type=int, default=1105, help="number of valid trials (default 1105, as the paper)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--pairs", type=int, default=19, help="pairs of simulated drivers (default 19, as the study)")
    p.add_argument("--out", required=True, help="output Parquet file")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_generate)

    p = sub.add_parser("import", help="import the authors' recordings")
    p.add_argument("source", choices=("hitl", "rosbag"), help="hitl: .jld files; rosbag: a folder of ROS1 bags")
    p.add_argument("inputs", nargs="+", help=".jld files (hitl) or one folder (rosbag)")
    p.add_argument("--out", required=True, help="output Parquet file")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_import)

    p = sub.add_parser("stats", help="dataset summary: Table I and marginal driving behaviour")
    p.add_argument("data", help="Parquet dataset")
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
    p.add_argument("--patience", type=int, help="early stopping: validations without improvement before stopping "
                                                "(default 0: off); the best weights are kept")
    p.add_argument("--validation-fraction", type=float, default=0.2,
                   help="fraction of the trials held out for validation, split by trial (0: train on all, no validation)")
    p.add_argument("--resume", help="continue the run saved in this training checkpoint")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("crossval", help="k-fold cross-validation by trial (choosing the number of steps by the folds)")
    p.add_argument("--data", required=True, help="Parquet dataset")
    p.add_argument("--folds", type=int, default=5)
    p.add_argument("--reference", help="a model scored on the same folds (checkpoint, default, or authors:PATH)")
    p.add_argument("--out", help="folder for each fold's model at the chosen steps (fold_K.pt, with its held-out trials)")
    p.add_argument("--beat-reference", action="store_true",
                   help="choose the steps only among those where every fold beats the --reference model")
    _add_schedule_options(p, steps=1000)
    p.set_defaults(func=cmd_crossval)

    p = sub.add_parser("calibrate", help="choose a model's latent temperature and output scale on out-of-fold predictions")
    p.add_argument("--data", required=True, help="the Parquet dataset the cross-validation ran on")
    p.add_argument("--folds", required=True, help="folder of fold models written by `crossval --out`")
    p.add_argument("--model", required=True, help="the checkpoint to calibrate (or default), trained on every fold")
    p.add_argument("--out", required=True, help="the calibrated checkpoint")
    p.add_argument("--out-folds", help="also write the calibrated fold models here (for out-of-fold reports)")
    p.add_argument("--samples", type=int, default=100, help="sampled futures per instance for the coverage")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("evaluate", help="NLL, coverage and displacement errors of a human model on every human agent of a dataset")
    p.add_argument("--model", default="default", help="checkpoint path, default, or authors:PATH")
    p.add_argument("--data", required=True, help="Parquet dataset")
    p.add_argument("--samples", type=int, default=50, help="latent samples of the sampled NLL estimators")
    p.add_argument("--coverage-samples", type=int, default=100, help="sampled futures per instance for the position coverage")
    p.add_argument("--ade-samples", type=int, default=20, help="sampled futures per instance for minADE/minFDE")
    p.add_argument("--max-sampled-instances", type=int, default=5000,
                   help="sample futures for at most this many instances (chosen at random with --seed; default 5000)")
    p.add_argument("--per-instance", metavar="FILE.parquet", help="also write every instance's values to this Parquet file")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="auto")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("predict", help="figure of sampled human futures (the paper's Fig. 3)")
    p.add_argument("--model", default="default", help="checkpoint path, default, or authors:PATH")
    p.add_argument("--data", required=True, help="Parquet dataset")
    p.add_argument("--at", action="append", required=True, metavar="TRIAL:T[:AGENT]",
                   help="trial index and present step (repeat for more panels); agent defaults to the first human")
    p.add_argument("--samples", type=int, default=50)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="auto")
    p.add_argument("--out", required=True, help="output PNG")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_predict)

    p = sub.add_parser("bench", help="time the planner")
    p.add_argument("what", choices=("plan",), help="plan: one two-stage plan at the paper's budget")
    p.add_argument("--model", default="default")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--deadline", type=float, help="real-time mode: return within this many seconds")
    p.add_argument("--first-stage-samples", type=int, default=16)
    p.add_argument("--finalists", type=int, default=32)
    p.add_argument("--second-stage-samples", type=int, default=1024)
    p.add_argument("--precision", choices=("auto", "float32", "bfloat16"), default="auto",
                   help="decoder matrix multiplies; auto: bfloat16 on CPUs with native bfloat16, else float32")
    p.add_argument("--threads", type=int, help="CPU threads (default: PyTorch's choice)")
    p.add_argument("--device", default="auto")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("demo", help="the main job, end to end, on the shipped defaults")
    p.add_argument("--out", default="out", help="output folder (default: out)")
    p.add_argument("--trials", type=int, default=1105)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--hitl", help="folder of the authors' .jld recordings (default: ../shared/reference/hitl if present)")
    p.set_defaults(func=cmd_demo, json=False)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except InputError as exc:
        print(f"trafficweaving {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # unwritable output path, full disk, ...
        print(f"trafficweaving {args.command}: error: {exc.filename or ''}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    return 0
