"""The human-model commands: ``train``, ``crossval``, ``distil``, ``calibrate``, ``mix``, ``evaluate``
and ``predict``."""

from __future__ import annotations

import os
from pathlib import Path

from ..atomic import check_output_file, check_output_folder
from ..errors import InputError
from ..scenario import HORIZON, MIN_HISTORY
from ..model.spec import check_model_spec
from .common import NON_NEGATIVE, POSITIVE, SEED, _emit, _float_in, _floats_in, _fmt, _int_at_least, _log


def add_parsers(sub) -> None:
    """Add the human-model commands to the subparsers ``sub``."""
    _add_fitting(sub)
    _add_calibration(sub)
    _add_evaluation(sub)


def _processes() -> int:
    """The most processes of a local pool (each holds the data and models)."""
    from ..sim.batch import WORKERS_PER_CPU

    return WORKERS_PER_CPU * (os.cpu_count() or 1)


def _add_fitting(sub) -> None:
    """``train``, ``crossval`` and ``distil``."""
    from ..model.crossval import MAX_FOLDS
    from ..sim.batch import WORKERS_PER_CPU

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

    processes = _processes()
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
    p.add_argument("--teacher-folds", metavar="DIR", help="distil instead: each fit distils the teacher trained without "
                   "the same folds, from this folder of `crossval --nested --out` (same --folds, --seed); with the "
                   "options of `distil`; --init: the student to start from; --lr default 1e-3, --validate-every "
                   "default 100")
    _add_student_options(p)
    _add_schedule_options(p, steps=1000)
    p.set_defaults(func=cmd_crossval)

    p = sub.add_parser("distil", help="a human model with a smaller decoder that predicts what a larger one does "
                                      "(docs/model.md, the fast model)")
    p.add_argument("--data", required=True, help="Parquet dataset: the situations and recorded actions it learns on")
    p.add_argument("--teacher", required=True, metavar="MODEL",
                   help="the model to distil (checkpoint or default; a mixture's first component; calibration reset)")
    p.add_argument("--out", required=True, help="the student's checkpoint (calibrate it afterwards)")
    p.add_argument("--steps", type=POSITIVE, default=3000, help="Adam steps of 64 situations (default 3000)")
    p.add_argument("--lr", type=_float_in(0, 1), help="initial learning rate in (0, 1) (default 1e-3, decaying towards 1e-4)")
    p.add_argument("--init", metavar="STUDENT", help="start from this student's decoder (a `distil` checkpoint of the "
                                                     "same sizes; default: a new decoder)")
    p.add_argument("--variant", choices=("cvae-hold",), help="cvae-hold: give a cvae teacher hold modes, switched off, "
                   "so that the student has a hold head to learn later (from another teacher, with --init)")
    _add_student_options(p)
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--device", default="auto", help="auto (CUDA when available), cpu, cuda, cuda:N")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_distil)


def _add_student_options(p) -> None:
    """The student's size and the distillation's data (:class:`~trafficweaving.model.distil.DistilConfig`)."""
    from ..model.distil import DistilConfig

    d = DistilConfig()
    p.add_argument("--decoder-units", type=_int_at_least(1, 1024), default=d.decoder_units,
                   help=f"the student's decoder LSTM units (default {d.decoder_units})")
    p.add_argument("--components", type=_int_at_least(1, 64), default=d.components,
                   help=f"the student's GMM components per step (default {d.components})")
    p.add_argument("--teacher-samples", type=_int_at_least(1, 256), default=d.teacher_samples,
                   help=f"teacher futures per situation and step (default {d.teacher_samples})")
    p.add_argument("--perturbed-fraction", type=_float_in(0, 1, include_low=True, include_high=True),
                   default=d.perturbed_fraction, help="share of situations whose robot future is replaced by a random "
                                                      f"one (default {d.perturbed_fraction:g})")
    p.add_argument("--real-weight", type=_float_in(0, 100, include_low=True), default=d.real_weight,
                   help=f"weight of the recorded actions' exact NLL (default {d.real_weight:g})")
    p.add_argument("--hold-modes-lr", type=_float_in(0, 1, include_low=True), default=d.hold_lr,
                   help=f"constant learning rate of the hold modes' logits (default {d.hold_lr:g}; 0: frozen)")


def _distil_config(args):
    from ..model.distil import DistilConfig

    return DistilConfig(decoder_units=args.decoder_units, components=args.components,
                        teacher_samples=args.teacher_samples, perturbed_fraction=args.perturbed_fraction,
                        real_weight=args.real_weight, hold_lr=args.hold_modes_lr)


def _add_calibration(sub) -> None:
    """``calibrate`` and ``mix``."""
    from ..model.calibrate import MIX_WEIGHTS, SCALES, TEMPERATURES
    from ..model.metrics import MAX_SAMPLES
    from ..sim.batch import WORKERS_PER_CPU

    processes = _processes()
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


def _add_evaluation(sub) -> None:
    """``evaluate`` and ``predict``."""
    from ..model.evaluate import MAX_NLL_SAMPLES
    from ..model.metrics import MAX_SAMPLES

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


def _add_schedule_options(p, steps: int) -> None:
    """Options shared by ``train`` and ``crossval``."""
    from ..model.cvae import ROBOT_FUTURES, VARIANTS
    from ..model.train_config import OBJECTIVES, TRAINABLE

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


def _train_config(args, **train_only):
    """The :class:`~trafficweaving.model.train_config.TrainConfig` of the options of
    :func:`_add_schedule_options` (and ``train_only``: ``train``'s own)."""
    from ..model.train_config import config_from_options

    return config_from_options(args.steps, args.seed, fine_tuning=bool(args.init), lr_initial=args.lr,
                               validate_every=args.validate_every, objective=args.objective, hold_lr=args.hold_lr,
                               trainable=args.train_parts, robot_future=args.robot_future, **train_only)


def cmd_train(args) -> None:
    from ..data.trials import load_trials
    from ..model.device import choose_device
    from ..model.train import train

    if args.init and args.resume:
        raise InputError("--init and --resume exclude each other (expected one: fine-tune a model, or continue a run)")
    out = check_output_file(args.out, "--out")
    tc = _train_config(args, validation_fraction=args.validation_fraction, patience=args.patience)
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
    from ..data.trials import load_trials
    from ..model.crossval import crossval
    from ..model.device import choose_device
    from ..model.registry import load_model

    out = check_output_folder(args.out, "--out") if args.out is not None else None
    if args.reference is not None:
        load_model(check_model_spec(args.reference, "--reference"))  # a bad reference fails before the folds train
    if args.teacher_folds is not None:
        from ..model.distil import distil_schedule

        if args.variant is not None:
            raise InputError("--teacher-folds excludes --variant (the students have their teachers' variant)")
        tc = distil_schedule(args.steps, args.seed, args.lr, args.validate_every)
    else:
        tc = _train_config(args)
    device = choose_device(args.device)
    trials = load_trials(args.data)
    if args.init is not None:
        check_model_spec(args.init, "--init")
    result = crossval(trials, args.folds, tc, variant=args.variant, init=args.init, reference=args.reference,
                      seed=args.seed, device=device, progress=not args.json, log=_log(args),
                      out=out, beat_reference=args.beat_reference, nested=args.nested, workers=args.workers,
                      teacher_folds=args.teacher_folds, distillation=_distil_config(args))
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


def cmd_distil(args) -> None:
    from ..data.trials import load_trials
    from ..model.device import choose_device
    from ..model.distil import distil, distil_schedule, teacher_model
    from ..model.registry import load_model

    out = check_output_file(args.out, "--out")
    device = choose_device(args.device)
    teacher = teacher_model(check_model_spec(args.teacher, "--teacher"), device, args.variant)
    init = None if args.init is None else load_model(check_model_spec(args.init, "--init"), device)
    trials = load_trials(args.data)
    student = distil(trials, teacher, out, _distil_config(args), distil_schedule(args.steps, args.seed, args.lr),
                     device=device, progress=not args.json, log=_log(args),
                     fields={"teacher": args.teacher, "student_init": args.init}, init=init)
    c = student.config
    _emit(args, {"out": str(out), "teacher": args.teacher, "decoder_units": c.decoder_units, "components": c.components,
                 "steps": args.steps},
          f"distilled {args.teacher} into {c.decoder_units} units, {c.components} components ({args.steps} steps) -> {out}")


def cmd_mix(args) -> None:
    """A mixture of a model with a companion at a given weight (and of its fold models)."""
    from ..model.workflows import mix_checkpoint

    payload = mix_checkpoint(args.model, args.companion, args.weight, args.out, person_weight=args.person_weight,
                             folds=args.folds, out_folds=args.out_folds)
    person = "" if args.person_weight is None else f"; facing a person {args.person_weight:g} and {1.0 - args.person_weight:g}"
    written = f" and {payload['folds']} fold models in {Path(args.out_folds)}" if payload["folds"] else ""
    _emit(args, payload, f"mixed {args.model} ({args.weight:g}) with {args.companion} ({1 - args.weight:g}{person}) -> "
                         f"{payload['out']}{written}")


def cmd_calibrate(args) -> None:
    from ..model.calibrate import scale_of
    from ..model.workflows import calibrate_checkpoint

    payload = calibrate_checkpoint(args.data, args.model, args.folds, args.out, args.temperatures, args.scales,
                                   samples=args.samples, seed=args.seed, nested=args.nested, workers=args.workers,
                                   companion=args.companion, out_folds=args.out_folds, log=_log(args))
    temperature, scale, weight, cov = (payload["latent_temperature"], scale_of(payload), payload["mixture_weight"],
                                       payload["coverage_90"])
    mixed = f", mixed with {args.companion} at weight {weight:g}" if weight < 1 else ""
    lines = [f"calibrated {payload['model']} -> {payload['out']}: latent temperature {temperature:g}, output scale x "
             f"{scale[0]:g}, y {scale[1]:g}{mixed} "
             f"(out-of-fold NLL {payload['nll_exact']:.2f}, 90 % coverage at 1.5 s x {100 * cov['x']:.0f} %, "
             f"y {100 * cov['y']:.0f} %)"]
    if payload["nested"] is not None:
        n = payload["nested"]
        lines.append(f"nested (every choice made on each fold's inner folds): NLL {n['fold_mean_nll_exact']:.2f} per fold "
                     f"({n['nll_exact']:.2f} per instance; x {n['nll_exact_by_direction']['x']:.2f}, y "
                     f"{n['nll_exact_by_direction']['y']:.2f}), 90 % coverage at 1.5 s x {100 * n['coverage_90']['x']:.0f} %, "
                     f"y {100 * n['coverage_90']['y']:.0f} %")
    _emit(args, payload, "\n".join(lines))


def cmd_evaluate(args) -> None:
    from ..model.metrics import DIRECTIONS, PHASES, evaluate_file

    payload, described = evaluate_file(args.model, args.data, samples=args.samples,
                                       coverage_samples=args.coverage_samples, ade_samples=args.ade_samples,
                                       max_sampled=args.max_sampled_instances, seed=args.seed, device=args.device,
                                       per_instance=args.per_instance)
    pct = lambda v: "n/a" if v is None else f"{100 * v:.0f}"  # noqa: E731
    meters = lambda v: "n/a" if v is None else f"{v:.2f}"  # noqa: E731
    by_phase = payload["nll_exact_by_phase"]
    phases = ", ".join(f"{p} {_fmt(by_phase[p]['nll_exact'])} (n={by_phase[p]['instances']})" for p in PHASES)
    coverage = "; ".join(f"{d} " + ", ".join(f"{h} s {pct(c['50'])}/{pct(c['90'])}" for h, c in payload["coverage"][d].items())
                         for d in DIRECTIONS)
    _emit(args, payload, f"{args.model} ({described}) on {args.data}: {payload['instances']} instances\n"
                         f"NLL per instance (nats, 15×2 accelerations in m/s²): exact {_fmt(payload['nll_exact'])}, "
                         f"importance-sampled {_fmt(payload['nll_is'])}, naive {_fmt(payload['nll_naive'])}\n"
                         f"  exact by direction (15 accelerations): x {_fmt(payload['nll_exact_by_direction']['x'])}, "
                         f"y {_fmt(payload['nll_exact_by_direction']['y'])}\n"
                         f"  exact by lane-change phase: {phases}\n"
                         f"Sampled positions ({payload['sampled_instances']} instances, {args.coverage_samples} samples each):\n"
                         f"  coverage of the 50/90 % central intervals (%): {coverage}\n"
                         f"  minADE {meters(payload['min_ade_m'])} m, minFDE {meters(payload['min_fde_m'])} m "
                         f"(best of {args.ade_samples})"
                         + (f"\nper-instance values: {Path(args.per_instance)}" if args.per_instance is not None else ""))


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
    from ..data.trials import load_trials
    from ..model.device import choose_device
    from ..model.mixture import describe
    from ..model.registry import load_model
    from ..viz.model_figures import plot_predictions

    out = check_output_file(args.out, "--out")
    trials = load_trials(args.data)
    trials.require_dt()
    picks = [_parse_pick(text, trials) for text in args.at]
    model = load_model(args.model, choose_device(args.device))
    path = plot_predictions(model, trials, picks, out, samples=args.samples, seed=args.seed,
                            title=f"{args.model} ({describe(model)}) on {Path(args.data).name}")
    _emit(args, {"out": str(path), "panels": len(picks)}, f"wrote {path}")
