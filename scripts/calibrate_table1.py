"""Fit the simulated drivers' decision weights so the generator reproduces the paper's Table I.

Minimises the squared logit error of the 7 Table I cells (weighted by their trial counts) over
``w_gap``, ``lookahead``, ``lane_bias_right`` and ``trial_noise_sd`` with Nelder–Mead, using common
random numbers (one seed) so the objective is smooth. Prints the fitted values to paste into
``DriverModel``; the marginal-behaviour parameters are not touched.

    python scripts/calibrate_table1.py --trials 20000 --iterations 60
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
from scipy.optimize import minimize

from trafficweaving.sim.drivers import DriverModel
from trafficweaving.sim.generate import generate_trials
from trafficweaving.data.stats import TABLE1_PAPER, table1

FITTED = ("w_gap", "lookahead", "lane_bias_right", "trial_noise_sd")


def logit(p):
    p = np.clip(p, 1e-3, 1 - 1e-3)
    return np.log(p / (1 - p))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=20000)
    parser.add_argument("--iterations", type=int, default=60)
    parser.add_argument("--seed", type=int, default=12345)
    args = parser.parse_args()
    base = DriverModel()

    def objective(theta):
        model = dataclasses.replace(base, **dict(zip(FITTED, theta)))
        trials, _ = generate_trials(args.trials, seed=args.seed, model=model)
        result = table1(trials)
        err = sum(
            result["counts"][dv][k] * (logit(result["table1"][dv][k]) - logit(TABLE1_PAPER[dv][k])) ** 2
            for dv in TABLE1_PAPER for k in TABLE1_PAPER[dv]
        ) / args.trials
        print(" ".join(f"{n}={v:.3f}" for n, v in zip(FITTED, theta)), f"loss={err:.4f}", flush=True)
        return err

    x0 = np.array([getattr(base, n) for n in FITTED])
    fit = minimize(objective, x0, method="Nelder-Mead",
                   options={"maxfev": args.iterations})
    print("fitted:", {n: round(float(v), 3) for n, v in zip(FITTED, fit.x)})


if __name__ == "__main__":
    main()
