"""Benchmark: the decoder's rows per chunk, in full-budget plans (the paper's 98,304 futures).

One planner per chunk size, same model, precision and situation; their plans alternate (A B C A B C
...), so that a drift in the machine's speed falls on all alike, and each size's time is given as
the median of its ratios to the first size's plan of the same round. The default chunk of a model
is :func:`trafficweaving.model.sampler.chunk_rows_for` its decoder's units (``default_chunk_rows``) (docs/planner.md, Speed).

    python benchmarks/bench_chunks.py [--model fast] [--precision int8] [--chunks 2048 4096 8192]
                                      [--rounds 10] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import statistics

import torch

from trafficweaving.model.predictor import PRECISIONS, HumanPredictor
from trafficweaving.model.registry import load_model
from trafficweaving.planning.costs import PaperCost
from trafficweaving.planning.planner import Budget, Planner, example_history
from trafficweaving.scenario import LANE_CENTRE_Y


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="fast")
    parser.add_argument("--precision", choices=PRECISIONS, default="int8")
    parser.add_argument("--chunks", type=int, nargs="+", default=[2048, 4096, 8192])
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    if min(args.chunks) < 1 or args.rounds < 1 or args.threads < 1:
        parser.error("--chunks, --rounds and --threads must be positive")
    torch.set_num_threads(args.threads)
    model = load_model(args.model)
    history, cost = example_history(), PaperCost(goal_y=LANE_CENTRE_Y["left"])
    planners = {rows: Planner(HumanPredictor(model, precision=args.precision, chunk_rows=rows), Budget())
                for rows in args.chunks}
    for planner in planners.values():  # warm-up (and, in int8, the compilation)
        planner.plan(history, 0, cost)
    seconds = {rows: [] for rows in planners}
    for _ in range(args.rounds):
        for rows, planner in planners.items():
            seconds[rows].append(planner.plan(history, 0, cost).seconds)
    first = args.chunks[0]
    print(json.dumps({
        "model": args.model, "precision": args.precision, "threads": args.threads, "rounds": args.rounds,
        "default_chunk_rows": getattr(HumanPredictor(model).rollout, "chunk_rows", None),
        "seconds": {rows: round(statistics.median(s), 3) for rows, s in seconds.items()},
        f"ratio_to_{first}": {rows: round(statistics.median(a / b for a, b in zip(s, seconds[first])), 3)
                               for rows, s in seconds.items()}}))


if __name__ == "__main__":
    main()
