"""Benchmark: human–human trial generation, vectorised over trials vs one trial at a time.

Both run the same driver model and protocol in the same process; the baseline simulates each
trial as its own batch of one (what a per-trial Python loop costs) on a sample of trials and
is extrapolated per trial. Prints one JSON object.

    python benchmarks/bench_generate.py [--trials 1105] [--baseline-trials 60]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from trafficweaving.sim.drivers import DriverModel, DriverStyles
from trafficweaving.sim.generate import generate_trials, schedule, simulate_trials


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=1105)
    parser.add_argument("--baseline-trials", type=int, default=60)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    generate_trials(50, seed=99)  # warm-up (imports, allocator)
    times = []
    for r in range(args.repeats):
        start = time.perf_counter()
        trials, report = generate_trials(args.trials, seed=r)
        times.append(time.perf_counter() - start)
    vectorised = min(times)

    model = DriverModel()
    rng = np.random.default_rng(0)
    styles = DriverStyles.sample(model, 38, rng)
    ic, pair = schedule(args.baseline_trials, 19, rng)
    start = time.perf_counter()
    for i in range(args.baseline_trials):
        simulate_trials(ic[i:i + 1], pair[i:i + 1], styles, model, rng)
    per_trial = (time.perf_counter() - start) / args.baseline_trials
    baseline = per_trial * report.simulated  # same number of simulated trials as the vectorised run

    print(json.dumps({
        "trials": args.trials,
        "simulated": report.simulated,
        "seconds_vectorised": round(vectorised, 3),
        "seconds_one_trial_at_a_time_extrapolated": round(baseline, 3),
        "speedup": round(baseline / vectorised, 1),
        "trials_per_second": round(args.trials / vectorised, 1),
        "target_seconds": 10.0,
    }))


if __name__ == "__main__":
    main()
