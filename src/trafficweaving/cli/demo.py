"""The end-to-end command: ``demo``."""

from __future__ import annotations

from ..atomic import check_output_folder
from ..scenario import STUDY_TRIALS
from .common import SEED, _int_at_least


def add_parsers(sub) -> None:
    """Add ``demo`` to the subparsers ``sub``."""
    from ..sim.generate import MAX_TRIALS

    p = sub.add_parser("demo", help="the main job, end to end, on the shipped defaults")
    p.add_argument("--out", default="out", help="output folder (default: out)")
    p.add_argument("--trials", type=_int_at_least(1, MAX_TRIALS), default=STUDY_TRIALS,
                   help=f"synthetic trials to generate, at most {MAX_TRIALS} (default {STUDY_TRIALS}, as the paper)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--hitl", help="folder of the authors' .jld recordings (default: ../shared/reference/hitl if present)")
    p.set_defaults(func=cmd_demo, json=False)


def cmd_demo(args) -> None:
    """The main job (:mod:`trafficweaving.demo`)."""
    from ..demo import run_demo

    run_demo(check_output_folder(args.out, "--out"), trials=args.trials, seed=args.seed, hitl=args.hitl)
