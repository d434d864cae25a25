"""Benchmark: CVAE training steps per second on this machine, batched vs one exemplar at a time.

Both measure the full training step of model/train.py (batch 32, 3 latent samples, dropout,
scheduled sampling, Adam, value clipping) on the same data in the same process. The batched step
runs the 32 exemplars together; the baseline runs the same network computation one exemplar at a
time and accumulates the gradients (what a per-sample Python loop costs; its KL floor then applies
per exemplar, which does not change the cost). Prints one JSON object, including the
projected time of the paper's 50,000-step run.

    python benchmarks/bench_train.py [--steps 200] [--baseline-steps 10] [--threads N]
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from trafficweaving.sim.generate import generate_trials
from trafficweaving.model.cvae import CVAE
from trafficweaving.model.train import _MinibatchOrder, _noisy, loss_terms, prepare_data
from trafficweaving.model.train_config import TrainConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--baseline-steps", type=int, default=10)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    trials, _ = generate_trials(400, seed=0, progress=False)
    tc = TrainConfig()
    train_ex, _, statistics = prepare_data(trials, tc)
    torch.manual_seed(0)
    model = CVAE().set_standardisation(*statistics).train()
    data = train_ex.standardised(model)
    minibatch = _MinibatchOrder(len(data), tc.batch_size, tc.seed)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)

    def step(s: int, one_at_a_time: bool) -> None:
        batch = _noisy(data.batch(minibatch(s)), tc.input_noise, tc.input_noise)
        optimizer.zero_grad(set_to_none=True)
        if one_at_a_time:
            for k in range(len(batch)):
                row = type(batch)(**{n: (None if v is None else v[k:k + 1]) for n, v in vars(batch).items()})
                loss, _ = loss_terms(model, row, tc, s)
                (loss / len(batch)).backward()
        else:
            loss, _ = loss_terms(model, batch, tc, s)
            loss.backward()
        torch.nn.utils.clip_grad_value_(model.parameters(), tc.clip_value)
        optimizer.step()

    def rate(n: int, one_at_a_time: bool) -> float:
        step(0, one_at_a_time)  # warm-up
        start = time.perf_counter()
        for s in range(1, n + 1):
            step(s, one_at_a_time)
        return n / (time.perf_counter() - start)

    batched = rate(args.steps, False)
    baseline = rate(args.baseline_steps, True)
    print(json.dumps({
        "threads": args.threads,
        "steps_per_second": round(batched, 2),
        "baseline_steps_per_second": round(baseline, 3),
        "speedup": round(batched / baseline, 1),
        "projected_minutes_50k_steps": round(50_000 / batched / 60, 1),
        "baseline_projected_hours_50k_steps": round(50_000 / baseline / 3600, 1),
    }))


if __name__ == "__main__":
    main()
