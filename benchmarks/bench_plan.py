"""Benchmark: the two-stage planner at the paper's budget (every candidate × 16 samples, best 32 ×
1024: 98,304 human futures per plan), naive vs ours, and the decision quality of real-time plans.

Measured in one run, same process, same model:

* ``cpu``: the CPU's model name and matrix instructions (native bfloat16, int8 dot products, AMX),
  on which the bfloat16 and int8 figures depend (docs/planner.md, Speed);
* ``matmul_peak_gflops``: PyTorch's float32 matrix multiply at the decoder's shapes (the ceiling
  for this work on this machine);
* ``naive_seconds``: the same plan with the decoder's sampling loop written plainly in eager
  PyTorch over the whole batch (:meth:`CVAE.sample_actions`, one call per stage);
* ``seconds``: our planner (median of ``--repeats``); ``speedup`` and ``achieved_gflops`` (the
  decoder's matrix-multiply FLOPs per plan over the plan's time);
* ``bfloat16_seconds``: our planner with the decoder's matrix multiplies in bfloat16;
* ``int8_seconds``: our planner with the fused, compiled decoder steps and int8 hidden-state
  matrix multiplies (``precision="int8"``, :mod:`trafficweaving.model.fused_decoder`; compiled in
  a warm-up plan first), and ``int8_speedup`` against the naive loop;
* ``float32_compiled_seconds``: the same fused, compiled steps with float32 weights
  (``precision="float32-compiled"``: the fastest where the CPU has no int8 dot products), and
  ``float32_compiled_speedup``;
* real-time plans (``--deadline``, default 0.3 s) on recorded situations (simulated human–human
  trials, the other car playing the robot; or, with ``--episodes``, the closest calls of
  closed-loop episodes, where choices matter most): how often its first free window equals the full-budget
  plan's, its expected-cost regret against the full-budget choice (both re-scored with 2048 fresh
  samples; also relative to the spread of expected costs over the candidates), over
  ``--realtime-plans`` real-time plans per situation, and, as the noise floor, the same for a second
  full-budget plan with another seed;
  the same two figures for full-budget plans in bfloat16 and in int8; with ``--baseline-model``
  (e.g. ``--model fast --baseline-model default``), the naive loop samples the baseline, and the
  int8 full-budget plans' next windows are compared with the baseline's float32 full-budget ones
  (agreement, regret re-scored by the baseline) beside the baseline's own noise floor; and how often the real-time
  plan's first free window equals that of a full-budget plan sampled in the real-time plans'
  precision (``--realtime-precision``), with, as that precision's noise floor, the same for two
  such full-budget plans with different seeds.

    python benchmarks/bench_plan.py [--threads N] [--situations 18] [--deadline 0.3] [--model default]
                                    [--baseline-model default]
                                    [--episodes SIMULATE_OUT_DIR] [--realtime-plans 1]

``--threads`` is an integer in 1..os.cpu_count(), ``--repeats``, ``--situations`` and
``--realtime-plans`` positive.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from trafficweaving.data.trials import load_trials
from trafficweaving.dynamics import future_states
from trafficweaving.errors import InputError
from trafficweaving.model.registry import load_model
from trafficweaving.model.cvae import ACCEL, STATE_DIM
from trafficweaving.model.predictor import PRECISIONS, HumanPredictor, cpu_matrix_features
from trafficweaving.planning.candidates import ACCELERATIONS, STEPS_PER_WINDOW, Action, robot_candidates
from trafficweaving.planning.costs import PaperCost
from trafficweaving.planning.mpc import HOLD_STEPS
from trafficweaving.planning.planner import Budget, Planner, example_history
from trafficweaving.scenario import HORIZON, LANE_CENTRE_Y, lane_of
from trafficweaving.sim.generate import generate_trials
from trafficweaving.validate import integer, positive_seconds, thread_count


def matmul_peak(rows: int, k: int, n: int, repeats: int = 30) -> float:
    a, b, c = torch.randn(rows, k), torch.randn(k, n), torch.randn(rows, n)
    for _ in range(3):
        torch.addmm(c, a, b)
    start = time.perf_counter()
    for _ in range(repeats):
        torch.addmm(c, a, b)
    return 2 * rows * k * n * repeats / (time.perf_counter() - start) / 1e9


def decoder_flops(model, futures: int) -> float:
    """Matrix-multiply FLOPs of sampling ``futures`` human futures (gates and mixture head, per step)."""
    units, m = model.config.decoder_units, model.config.components
    return 2.0 * futures * HORIZON * ((units + 8) * 4 * units + units * 6 * m)


@torch.no_grad()
def naive_plan(model, history: np.ndarray, first: int, cost, budget: Budget, seed: int = 0) -> float:
    """The plan with plain eager sampling over the whole batch; returns seconds."""
    g = torch.Generator().manual_seed(seed)
    start = time.perf_counter()
    candidates = robot_candidates(history[-1, 0], first)
    std = lambda a: model.states_to_standard(torch.as_tensor(a, dtype=torch.float32))  # noqa: E731
    past, futures = std(history).reshape(len(history), 2 * STATE_DIM), std(candidates.states)
    count = len(candidates)
    x = torch.cat([model.encode_history(past[None], torch.tensor([len(history) - 1])).expand(count, -1),
                   model.encode_robot_future(futures, past[-1, :STATE_DIM].expand(count, -1))], -1)
    robot_inputs = torch.cat([past[-1, :STATE_DIM].expand(count, 1, -1), futures[:, :-1]], 1)
    present = model.actions_to_standard(torch.as_tensor(history[-1, 1, ACCEL], dtype=torch.float32))
    robot = torch.as_tensor(candidates.states, dtype=torch.float32)
    human_present = torch.as_tensor(history[-1, 1], dtype=torch.float32)

    def scores(index, n):
        log_p = torch.log_softmax(model.p_z_logits(x[index]), -1)
        classes = torch.distributions.Categorical(logits=log_p).sample((n,))  # [n, C', N_z]
        z = torch.nn.functional.one_hot(classes, model.config.latent_classes).flatten(2).float()
        actions = model.sample_actions(model.zx(z, x[index]), robot_inputs[index], present.expand(len(index), -1), g)
        human = future_states(human_present, model.actions_to_physical(actions))
        return cost(robot[index].unsqueeze(0), human).mean(0)

    first_cost = scores(torch.arange(count), budget.first_stage_samples)
    finalists = torch.topk(first_cost, budget.finalists, largest=False).indices
    scores(finalists, budget.second_stage_samples)
    return time.perf_counter() - start


def expected_cost(planner: Planner, history, first, cost, index: int, samples: int = 2048) -> float:
    """Expected cost of one candidate, re-scored with fresh samples."""
    return float(planner.score(history, first, cost, [index], samples)[0][0])


def situations(count: int, seed: int = 7):
    """(history, first action, cost) at contested moments of simulated human–human trials: agent 0
    plays the robot, at steps t >= 8 where the cars are within 10 m of each other and the robot
    has not yet reached its goal lane (every 4th such step), the fixed window being the robot's
    recorded acceleration (nearest action) and lane."""
    trials, _ = generate_trials(4 * count, seed=seed, progress=False)
    out = []
    for i in range(len(trials)):
        robot, human = trials.trajectory(i, 0), trials.trajectory(i, 1)
        goal = "right" if trials.start_lanes[i, 0] == "left" else "left"
        contested = [t for t in range(8, len(robot) - 1)
                     if abs(robot[t, 0] - human[t, 0]) < 10.0 and abs(robot[t, 1] - LANE_CENTRE_Y[goal]) > 1.0]
        for t in contested[::4]:
            accel = min(ACCELERATIONS, key=lambda a: abs(a - robot[t, 4]))
            lane = str(lane_of(robot[t, 1]))
            out.append((np.stack([robot[: t + 1], human[: t + 1]], 1), Action.of(accel, lane).index,
                        PaperCost(goal_y=LANE_CENTRE_Y[goal])))
    rng = np.random.default_rng(seed)
    return [out[k] for k in sorted(rng.choice(len(out), size=min(count, len(out)), replace=False))]


def closest_calls(folder: Path, count: int):
    """(history, first action, cost) at the closest calls of closed-loop episodes (the episode logs
    of ``trafficweaving simulate --out FOLDER``): the robot's plan steps (every 3 steps from step
    8) in the second before each episode's smallest robot–human distance, from the ``count``
    closest episodes; the fixed window as in :func:`situations`."""
    calls = []
    for path in sorted(Path(folder).glob("episodes/episode_*.parquet")):
        trials = load_trials(path)
        car = trials.metadata["episode"]["robot_car"]
        robot, human = trials.trajectory(0, car), trials.trajectory(0, 1 - car)
        goal = "right" if trials.start_lanes[0, car] == "left" else "left"
        distance = np.hypot(robot[:, 0] - human[:, 0], robot[:, 1] - human[:, 1])
        closest = int(np.argmin(distance))
        steps = [t for t in range(HOLD_STEPS, closest, STEPS_PER_WINDOW) if closest - t <= 10]
        calls += [(distance[closest], robot, human, t, goal) for t in steps]
    calls.sort(key=lambda call: call[0])
    out = []
    for _, robot, human, t, goal in calls[:count]:
        accel = min(ACCELERATIONS, key=lambda a: abs(a - robot[t + 1, 4]))
        out.append((np.stack([robot[: t + 1], human[: t + 1]], 1), Action.of(accel, str(lane_of(robot[t, 1]))).index,
                    PaperCost(goal_y=LANE_CENTRE_Y[goal])))
    return out


def arguments() -> tuple[argparse.Namespace, int]:
    """The command line's arguments, checked, and the thread count."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--model", default="default")
    parser.add_argument("--baseline-model", help="the naive loop samples this model instead (e.g. default, beside "
                        "--model fast), and the real-time figures compare --model's int8 full-budget choices with "
                        "this model's float32 ones")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--situations", type=int, default=18)
    parser.add_argument("--deadline", type=float, default=0.3)
    parser.add_argument("--realtime-plans", type=int, default=1, help="real-time plans per situation")
    parser.add_argument("--realtime-precision", default="auto", choices=PRECISIONS)
    parser.add_argument("--skip-naive", action="store_true")
    parser.add_argument("--random-numbers", choices=("common", "independent"), default="common",
                        help="whether the candidates share their random numbers (HumanPredictor's "
                        "common_random_numbers) in every plan of the benchmark")
    parser.add_argument("--episodes", type=Path, help="take the real-time situations from the closest calls of "
                        "these closed-loop episodes (simulate's --out folder) instead of simulated trials")
    args = parser.parse_args()
    try:
        threads = thread_count("--threads", args.threads)
        integer("--repeats", args.repeats, 1)
        integer("--situations", args.situations, 1)
        integer("--realtime-plans", args.realtime_plans, 1)
        positive_seconds("--deadline", args.deadline)
    except InputError as error:
        parser.error(str(error))
    return args, threads


def speed(args: argparse.Namespace, threads: int, model, exact: HumanPredictor, low: HumanPredictor, budget: Budget,
          history: np.ndarray, first: int, cost: PaperCost, baseline=None) -> tuple[dict, Planner, Planner]:
    """The report's speed figures (module docstring) and the float32 and int8 full-budget planners;
    the naive loop samples ``baseline`` when given."""
    common = args.random_numbers == "common"
    report = {"threads": threads, "futures": budget.futures, "random_numbers": args.random_numbers,
              "cpu": cpu_matrix_features()}
    report["matmul_peak_gflops"] = round(matmul_peak(2048, 136, 512), 1)
    planner = Planner(exact, budget)
    planner.plan(history, first, cost)  # warm-up
    ours = [planner.plan(history, first, cost).seconds for _ in range(args.repeats)]
    report["seconds"] = round(statistics.median(ours), 3)
    report["achieved_gflops"] = round(decoder_flops(model, budget.futures) / report["seconds"] / 1e9, 1)
    fast = Planner(low, budget)
    fast.plan(history, first, cost)
    report["bfloat16_seconds"] = round(statistics.median(fast.plan(history, first, cost).seconds for _ in range(args.repeats)), 3)
    quantised = Planner(HumanPredictor(model, precision="int8", common_random_numbers=common), budget)
    quantised.plan(history, first, cost)  # warm-up: compiles the fused steps (cached on disk after the first run)
    report["int8_seconds"] = round(statistics.median(quantised.plan(history, first, cost).seconds
                                                     for _ in range(args.repeats)), 3)
    compiled = Planner(HumanPredictor(model, precision="float32-compiled", common_random_numbers=common), budget)
    compiled.plan(history, first, cost)  # warm-up: compiles the fused steps for float32 weights
    report["float32_compiled_seconds"] = round(statistics.median(compiled.plan(history, first, cost).seconds
                                                                 for _ in range(args.repeats)), 3)
    if not args.skip_naive:
        report["naive_model"] = args.baseline_model or args.model
        report["naive_seconds"] = round(naive_plan(model if baseline is None else baseline, history, first, cost, budget), 3)
        report["speedup"] = round(report["naive_seconds"] / report["seconds"], 2)
        report["int8_speedup"] = round(report["naive_seconds"] / report["int8_seconds"], 2)
        report["float32_compiled_speedup"] = round(report["naive_seconds"] / report["float32_compiled_seconds"], 2)
    return report, planner, quantised


def decision_quality(args: argparse.Namespace, model, planner: Planner, exact: HumanPredictor, low: HumanPredictor,
                     quantised: Planner, budget: Budget, history: np.ndarray, first: int, cost: PaperCost,
                     baseline=None) -> dict:
    """The report's ``realtime`` figures (module docstring), from ``planner`` (float32, full budget:
    the reference and the re-scoring), the bfloat16 and int8 full-budget planners, and real-time
    plans at ``--realtime-precision``; with ``baseline`` (a model), also how often the int8
    full-budget plan's next window equals the baseline's float32 full-budget plan's, and its regret
    re-scored by the baseline, beside the baseline's own noise floor (two of its plans, different
    seeds)."""
    common = args.random_numbers == "common"
    agree, regret, agree_full, regret_full, agree_bf16, regret_bf16, late, spread = [], [], [], [], [], [], [], []
    agree_int8, regret_int8, agree_same, agree_same_full = [], [], [], []
    agree_base, regret_base, agree_base_floor, regret_base_floor = [], [], [], []
    base_exact = None if baseline is None else HumanPredictor(baseline, precision="float32", common_random_numbers=common)
    base_planner = None if baseline is None else Planner(base_exact, budget)
    realtime = Planner(HumanPredictor(model, precision=args.realtime_precision, common_random_numbers=common), budget,
                       seed=1)
    realtime.plan(history, first, cost, deadline=args.deadline)  # warm-up: measures its speed
    chosen = situations(args.situations) if args.episodes is None else closest_calls(args.episodes, args.situations)
    for k, (hist, fixed, c) in enumerate(chosen):
        full = Planner(exact, budget, seed=100 + k).plan(hist, fixed, c)
        other = Planner(exact, budget, seed=200 + k).plan(hist, fixed, c)
        lower = Planner(low, budget, seed=300 + k).plan(hist, fixed, c)
        coarse = Planner(quantised.human_model, budget, seed=400 + k).plan(hist, fixed, c)
        reference = expected_cost(planner, hist, fixed, c, full.index)
        # the full budget in the real-time precision, and a second such plan (that precision's noise floor)
        same = {"float32": full, "bfloat16": lower, "int8": coarse}.get(realtime.human_model.precision)
        if same is None:  # float32-compiled
            same = Planner(realtime.human_model, budget, seed=450 + k).plan(hist, fixed, c)
        same_other = other if same is full else Planner(realtime.human_model, budget, seed=500 + k).plan(hist, fixed, c)
        agree_same_full.append(same_other.actions[1] == same.actions[1])
        situation_spread = float(np.std(full.first_stage_cost))  # how much candidates differ here
        for _ in range(args.realtime_plans):
            rt = realtime.plan(hist, fixed, c, deadline=args.deadline)
            late.append(rt.seconds)
            spread.append(situation_spread)
            agree.append(rt.actions[1] == full.actions[1])
            agree_same.append(rt.actions[1] == same.actions[1])
            regret.append(expected_cost(planner, hist, fixed, c, rt.index) - reference)
        agree_full.append(other.actions[1] == full.actions[1])
        regret_full.append(expected_cost(planner, hist, fixed, c, other.index) - reference)
        agree_bf16.append(lower.actions[1] == full.actions[1])
        regret_bf16.append(expected_cost(planner, hist, fixed, c, lower.index) - reference)
        agree_int8.append(coarse.actions[1] == full.actions[1])
        regret_int8.append(expected_cost(planner, hist, fixed, c, coarse.index) - reference)
        if baseline is not None:
            base = Planner(base_exact, budget, seed=600 + k).plan(hist, fixed, c)
            base_other = Planner(base_exact, budget, seed=700 + k).plan(hist, fixed, c)
            base_reference = expected_cost(base_planner, hist, fixed, c, base.index)
            agree_base.append(coarse.actions[1] == base.actions[1])
            regret_base.append(expected_cost(base_planner, hist, fixed, c, coarse.index) - base_reference)
            agree_base_floor.append(base_other.actions[1] == base.actions[1])
            regret_base_floor.append(expected_cost(base_planner, hist, fixed, c, base_other.index) - base_reference)
    baseline_figures = {} if baseline is None else {
        "baseline_model": args.baseline_model,
        "int8_vs_baseline_agreement": round(float(np.mean(agree_base)), 3),
        "int8_vs_baseline_regret_mean": round(float(np.mean(regret_base)), 2),
        "int8_vs_baseline_regret_median": round(float(np.median(regret_base)), 2),
        "baseline_full_vs_full_agreement": round(float(np.mean(agree_base_floor)), 3),
        "baseline_full_vs_full_regret_mean": round(float(np.mean(regret_base_floor)), 2),
        "baseline_full_vs_full_regret_median": round(float(np.median(regret_base_floor)), 2),
    }
    return {**baseline_figures,
        "deadline": args.deadline, "situations": len(chosen), "plans": len(late), "max_seconds": round(max(late), 3),
        "within_deadline": int(sum(s <= args.deadline for s in late)),
        "first_action_agreement": round(float(np.mean(agree)), 3),
        "regret_mean": round(float(np.mean(regret)), 2), "regret_median": round(float(np.median(regret)), 2),
        "regret_p90": round(float(np.percentile(regret, 90)), 2),
        "regret_relative_mean": round(float(np.mean(np.array(regret) / np.array(spread))), 4),
        "full_vs_full_agreement": round(float(np.mean(agree_full)), 3),
        "full_vs_full_regret_mean": round(float(np.mean(regret_full)), 2),
        "bfloat16_agreement": round(float(np.mean(agree_bf16)), 3),
        "bfloat16_regret_mean": round(float(np.mean(regret_bf16)), 2),
        "int8_agreement": round(float(np.mean(agree_int8)), 3),
        "int8_regret_mean": round(float(np.mean(regret_int8)), 2),
        "same_precision_agreement": round(float(np.mean(agree_same)), 3),
        "same_precision_full_vs_full_agreement": round(float(np.mean(agree_same_full)), 3),
    }


def main() -> None:
    args, threads = arguments()
    torch.set_num_threads(threads)
    model = load_model(args.model)
    common = args.random_numbers == "common"
    exact, low = (HumanPredictor(model, precision=p, common_random_numbers=common) for p in ("float32", "bfloat16"))
    budget = Budget()
    history, first = example_history(), Action.of(0.0, "right").index
    cost = PaperCost(goal_y=LANE_CENTRE_Y["left"])
    baseline = None if args.baseline_model is None else load_model(args.baseline_model)
    report, planner, quantised = speed(args, threads, model, exact, low, budget, history, first, cost, baseline)
    print(json.dumps(report), flush=True)
    report["realtime"] = decision_quality(args, model, planner, exact, low, quantised, budget, history, first, cost,
                                          baseline)
    print(json.dumps(report))


if __name__ == "__main__":
    main()
