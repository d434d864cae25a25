"""The data commands: ``generate``, ``import``, ``stats`` and ``plot``."""

from __future__ import annotations

import time
from pathlib import Path

from ..atomic import check_output_file, check_output_folder
from ..errors import InputError
from ..scenario import STUDY_TRIALS
from .common import SEED, _emit, _int_at_least


def add_parsers(sub) -> None:
    """Add the data commands to the subparsers ``sub``."""
    from ..sim.generate import MAX_PAIRS, MAX_TRIALS

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


def cmd_generate(args) -> None:
    from ..model.device import choose_device
    from ..sim.generate import generate_trials

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
        from ..data.hitl import read_hitl

        trials = read_hitl(args.inputs)
        trials.write_parquet(out)
        _emit(args, {"trials": len(trials), "out": str(out)}, f"imported {len(trials)} human-in-the-loop trials into {out}")
    else:
        from ..data.rosbag import read_rosbags

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
    from ..data.behaviour import format_comparison
    from ..data.stats import dataset_stats, format_table1, format_table1_test
    from ..data.trials import load_trials

    if Path(args.data).is_dir():
        return _stats_of_drives(args)
    trials = load_trials(args.data)
    reference = load_trials(args.reference) if args.reference else None
    payload = dataset_stats(trials, reference)
    text = [f"{args.data}: {len(trials)} trials, {trials.lengths.min()}–{trials.lengths.max()} steps "
            f"(mean {trials.lengths.mean():.1f}) of {trials.dt} s", format_table1(payload["table1"], payload["table1_counts"]),
            format_table1_test(payload["table1_vs_paper"])]
    if reference is not None:
        text += [f"Human behaviour vs {args.reference}:", format_comparison(payload["behaviour_vs_reference"])]
    _emit(args, payload, "\n".join(text))


def _stats_of_drives(args) -> None:
    """``stats DIR``: the study's progress in a folder of browser recordings."""
    from ..web.study import study_stats

    if args.reference:
        raise InputError("--reference: compares a dataset file's drivers (expected stats FILE.parquet --reference "
                         "REF, not a folder)")
    _emit(args, *study_stats(args.data))


def cmd_plot(args) -> None:
    from ..data.trials import load_trials
    from ..viz.figures import write_dataset_figures

    out = check_output_folder(args.out, "--out")
    trials = load_trials(args.data)
    reference = load_trials(args.reference) if args.reference else None
    paths = write_dataset_figures(trials, out, reference)
    _emit(args, {"figures": [str(p) for p in paths]}, "\n".join(f"wrote {p}" for p in paths))
