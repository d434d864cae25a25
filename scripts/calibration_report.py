"""Write ``docs/calibration.md`` and its figures: how well the simulated human–human data matches
the paper's Table I and the authors' real human drivers.

    python scripts/calibration_report.py --hitl path/to/hitl [--out docs]

Measures, in one run: Table I of the shipped dataset (1105 trials, seed 0), the spread of Table I
over seeds 0..9 and at large N (20,000 trials), rejected trials by reason, and the marginal
behaviour of the simulated humans against the 30 real human-in-the-loop drivers.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from trafficweaving.viz.figures import write_dataset_figures
from trafficweaving.data.behaviour import behaviour_samples, compare_behaviour, format_comparison
from trafficweaving.sim.generate import generate_trials
from trafficweaving.data.hitl import read_hitl
from trafficweaving.data.stats import TABLE1_PAPER, table1, table1_max_deviation

CELLS = [("-2", "1"), ("-2", "2"), ("-2", "3"), ("0", "all"), ("2", "1"), ("2", "2"), ("2", "3")]


def cell_name(dv: str, k: str) -> str:
    return f"Δv={int(dv):+d}, " + ("all tco" if k == "all" else f"tco={k} s")


def hold_row(direction: str, comparison: dict, sim: dict, real: dict) -> str:
    """A Markdown row of the hold statistics of one direction (``long`` or ``lat``)."""
    held = comparison[f"{direction}_hold"]
    runs = [sim[f"{direction}_hold_run"], real[f"{direction}_hold_run"]]
    cell = lambda f: " / ".join(f"{f(r):.3g}" for r in runs)  # noqa: E731
    return (f"| {direction} | {100 * held['sim']['mean']:.1f} % / {100 * held['real']['mean']:.1f} % | "
            f"{cell(np.median)} | {cell(lambda r: np.percentile(r, 90))} | {cell(np.max)} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hitl", required=True, help="folder of the authors' human-in-the-loop .jld recordings")
    parser.add_argument("--out", default="docs")
    args = parser.parse_args()
    out = Path(args.out)

    start = time.perf_counter()
    trials, report = generate_trials(1105, seed=0)
    seconds = time.perf_counter() - start
    shipped = table1(trials)
    seeds = [table1(generate_trials(1105, seed=s)[0])["table1"] for s in range(10)]
    large = table1(generate_trials(20000, seed=100)[0])["table1"]
    reference = read_hitl(sorted(Path(args.hitl).glob("*.jld")))
    sim_samples, real_samples = behaviour_samples(trials), behaviour_samples(reference)
    comparison = compare_behaviour(sim_samples, real_samples)
    write_dataset_figures(trials, out / "figures", reference)

    pp = lambda v: f"{100 * v:.1f}"  # noqa: E731
    lines = [
        "# Calibration of the simulated human drivers",
        "",
        "Made by `python scripts/calibration_report.py --hitl hitl/` (`hitl/` holding the authors' 30 "
        "human-in-the-loop recordings, `.jld`); the numbers below are from its last run. The simulator follows "
        "the study protocol of the paper's §V-A (Data Collection): 18 initial conditions (Δv ∈ {−2, 0, +2} m/s, "
        "crossover time t_co ∈ {1, 2, 3} s, which car starts in which lane), the car ahead starting at "
        "x = −145 m, 19 pairs of drivers.",
        "",
        "## Table I",
        "",
        "Fraction (%) of human–human trials in which the car that started in the left lane passes in front.",
        f"Shipped dataset: `trafficweaving generate --trials 1105 --seed 0` ({seconds:.2f} s on 2 CPU cores); "
        "seeds 0–9: the same command with other seeds; 20k: 20,000 trials (the model's own probabilities, "
        "sampling noise ≈ ±0.7 pp).",
        "",
        "| cell | paper | seed 0 (n) | seed 0 − paper | seeds 0–9 min / median / max | 20k |",
        "|---|---|---|---|---|---|",
    ]
    for dv, k in CELLS:
        values = np.array([s[dv][k] for s in seeds])
        lines.append(
            f"| {cell_name(dv, k)} | {pp(TABLE1_PAPER[dv][k])} | {pp(shipped['table1'][dv][k])} "
            f"({shipped['counts'][dv][k]}) | {100 * (shipped['table1'][dv][k] - TABLE1_PAPER[dv][k]):+.1f} | "
            f"{pp(values.min())} / {pp(np.median(values))} / {pp(values.max())} | {pp(large[dv][k])} |"
        )
    max_devs = [100 * table1_max_deviation(s) for s in seeds]
    lines += [
        "",
        f"Largest cell deviation from the paper: seed 0 **{100 * table1_max_deviation(shipped['table1']):.1f} pp**; "
        f"seeds 0–9: {', '.join(f'{d:.1f}' for d in max_devs)} pp "
        f"({sum(d <= 5 for d in max_devs)} of 10 within 5 pp); 20k trials: {100 * table1_max_deviation(large):.1f} pp.",
        "",
        "Rejected while generating the shipped dataset (the authors' validity rules, `scenario.check_validity`: "
        "never |Δx| < 4.5 m and |Δy| < 1.8 m at once; both cars on the road, −8 ≤ y ≤ −1 m, and each on the "
        "other side of y = −4 m from where it started before reaching x = 2 m, the cutoff line, which both must "
        f"reach; valid trials are cut where the first car reaches it): {report.simulated - 1105} of "
        f"{report.simulated} simulated ({100 * (report.simulated - 1105) / report.simulated:.1f} %): "
        + ", ".join(f"{k} {v}" for k, v in report.rejected.items()) + ".",
        "",
        "![Table I](figures/table1.png)",
        "",
        "## Marginal behaviour against the real human drivers",
        "",
        f"Simulated humans (both cars of the 1105 trials) against the human car of the {len(reference)} real "
        "human-in-the-loop trials recorded by the authors (a person driving against their planner). "
        "W: 1-D Wasserstein distance; W / std real: the same in units of the real sample's spread.",
        "",
        format_comparison(comparison),
        "",
        "Intermittent control: `long_hold` / `lat_hold` are 1 when the acceleration changes by less than "
        "0.01 m/s² between consecutive steps (their mean is the fraction of held steps), `*_hold_run` the "
        "lengths of the runs of held steps. Lane-change timing comes from `lane_change_events`: "
        "`lane_change_sideways_time` runs from the last step with at most 0.2 m/s of sideways speed towards "
        "the target lane to the divider crossing, `lane_change_duration` from there to arriving within 0.4 m "
        "of the target lane's centre (recorded lane changes only); `long_accel_abs_near_crossing` is each "
        "driver's mean |ẍ| from 2.5 s before to 0.5 s after its crossing.",
        "",
        "| direction | held steps sim / real | run p50 sim / real | run p90 sim / real | run max sim / real |",
        "|---|---|---|---|---|",
        *[hold_row(direction, comparison, sim_samples, real_samples) for direction in ("long", "lat")],
        "",
        "![behaviour](figures/behaviour_vs_reference.png)",
        "",
        "![trajectories](figures/trajectories.png)",
        "",
        "![profiles](figures/profiles.png)",
        "",
    ]
    (out / "calibration.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
