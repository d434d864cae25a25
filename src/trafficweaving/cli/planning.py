"""The planner's command: ``bench plan``."""

from __future__ import annotations

import os

from .common import POSITIVE, _emit, _float_in, _int_at_least


def add_parsers(sub) -> None:
    """Add ``bench`` to the subparsers ``sub``."""
    from ..model.predictor import MAX_PLAN_FUTURES, PRECISIONS
    from ..planning.candidates import N_CANDIDATES

    p = sub.add_parser("bench", help="time the planner")
    p.add_argument("what", choices=("plan",), help="plan: one two-stage plan at the paper's budget")
    p.add_argument("--model", default="default")
    p.add_argument("--repeats", type=POSITIVE, default=3)
    p.add_argument("--deadline", type=_float_in(0, 3600), help="real-time deadline: return within this many seconds")
    p.add_argument("--first-stage-samples", type=_int_at_least(1, MAX_PLAN_FUTURES // N_CANDIDATES), default=16,
                   help=f"human futures per candidate, 1..{MAX_PLAN_FUTURES // N_CANDIDATES} (default 16)")
    p.add_argument("--finalists", type=_int_at_least(1, N_CANDIDATES), default=32)
    p.add_argument("--second-stage-samples", type=_int_at_least(1, MAX_PLAN_FUTURES), default=1024,
                   help=f"human futures per finalist (default 1024); a plan samples at most {MAX_PLAN_FUTURES} in all "
                        f"({N_CANDIDATES} × first stage + finalists × second stage)")
    p.add_argument("--precision", choices=PRECISIONS, default="auto",
                   help="decoder matrix multiplies; int8 and float32-compiled: fused and compiled steps (CPU only); "
                        "auto (default): int8 on CPUs with int8 dot products, else float32-compiled, where a C++ "
                        "compiler is found (docs/planner.md, Speed)")
    p.add_argument("--threads", type=_int_at_least(1, os.cpu_count() or 1),
                   help=f"CPU threads, 1..{os.cpu_count() or 1} (default: PyTorch's choice)")
    p.add_argument("--device", default="auto")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bench)


def cmd_bench(args) -> None:
    from ..planning.planner import Budget
    from ..sim.bench import bench_plan

    budget = Budget(args.first_stage_samples, args.finalists, args.second_stage_samples)
    payload = bench_plan(args.model, budget, args.repeats, deadline=args.deadline, precision=args.precision,
                         threads=args.threads, device=args.device)
    _emit(args, payload, f"plan: {payload['futures']} human futures for {payload['candidates']} candidates in "
                         f"{payload['seconds']:.3f} s (median of {args.repeats}; {payload['device']}, "
                         f"{payload['threads']} threads)")
