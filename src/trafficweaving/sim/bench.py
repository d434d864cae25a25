"""The planner timed on one contested situation with a loaded human model (``trafficweaving bench
plan``); benchmarks/bench_plan.py measures more (naive baseline, precisions, decision quality)."""

from __future__ import annotations

import statistics

import torch

from ..errors import InputError
from ..model.device import choose_device
from ..model.registry import load_model
from ..model.predictor import MAX_PLAN_FUTURES, HumanPredictor, cpu_matrix_features
from ..planning.candidates import N_CANDIDATES, Action
from ..planning.costs import PaperCost
from ..planning.planner import Budget, Planner, example_history
from ..scenario import LANE_CENTRE_Y


def bench_plan(model: str, budget: Budget, repeats: int, deadline: float | None = None, precision: str = "auto",
               threads: int | None = None, device: str = "auto") -> dict:
    """Time ``repeats`` plans of :func:`~trafficweaving.planning.planner.example_history` after
    one warm-up plan: the median and every plan's ``seconds``, the sampled ``futures``, the stage
    sizes, the last plan's ``timings`` (s) and the CPU's matrix features. ``model``: a
    ``--model`` spec; ``deadline`` (s): the real-time deadline, None for the full ``budget``;
    ``threads``: PyTorch's CPU threads (None: its choice)."""
    if budget.futures > MAX_PLAN_FUTURES:
        raise InputError(f"--first-stage-samples {budget.first_stage_samples}, --finalists {budget.finalists} and "
                         f"--second-stage-samples {budget.second_stage_samples} sample {budget.futures} human futures "
                         f"a plan ({N_CANDIDATES} candidates × first stage + finalists × second stage; expected at most "
                         f"{MAX_PLAN_FUTURES})")
    if threads is not None:
        torch.set_num_threads(threads)
    device = choose_device(device)
    human_model = HumanPredictor(load_model(model, device), precision=precision)
    planner = Planner(human_model, budget)
    history, first = example_history(), Action.of(0.0, "right").index
    cost = PaperCost(goal_y=LANE_CENTRE_Y["left"])
    planner.plan(history, first, cost, deadline=deadline)  # warm-up: allocations, measured speed
    opening, seconds, futures = None, [], []
    for _ in range(repeats):  # a plan holds its candidates and futures (MBs): keep the first and the last
        plan = planner.plan(history, first, cost, deadline=deadline)
        opening = plan if opening is None else opening
        seconds.append(plan.seconds)
        futures.append(plan.futures)
    return {"futures": min(futures), "seconds": statistics.median(seconds),
            "seconds_all": [round(s, 4) for s in seconds], "candidates": len(opening.candidates),
            "first_stage_samples": opening.first_stage_samples, "shortlist_samples": opening.shortlist_samples,
            "finalists": len(opening.finalists),
            "second_stage_samples": opening.second_stage_samples, "deadline": deadline,
            "device": str(device), "threads": torch.get_num_threads(), "model": model,
            "precision": human_model.precision,
            "timings": {k: round(v, 4) for k, v in plan.timings.items()}, "cpu": cpu_matrix_features()}
