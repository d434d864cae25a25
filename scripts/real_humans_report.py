"""Evaluate human models on real human drivers beyond the mean NLL and write a Markdown report
(NLL overall, by lane-change phase and by direction, position coverage against nominal,
minADE/minFDE) with figures in ``<report folder>/figures``.

    python scripts/real_humans_report.py --data hitl.parquet --out docs/real_humans.md \\
        --model shipped=default --model authors=authors:path/to/weights.npz

``--data`` is any dataset with human agents (e.g. ``trafficweaving import hitl`` of the authors'
30 human-in-the-loop trials); ``--model NAME=SPEC`` takes what ``trafficweaving evaluate --model``
takes, or ``crossval:DIR``, the fold models of ``trafficweaving crossval --out DIR`` on the same
data: each trial is then predicted by the model that did not train on it (out-of-fold), the honest
way to analyse a model trained on these trials. Every number is measured in this run (all
instances, fixed seed). ``--nested FILE`` inserts a Markdown fragment (the output of
``scripts/nested_table.py``) as the section "Nested estimates".
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch

from trafficweaving.atomic import atomic_write
from trafficweaving.data.behaviour import LANE_BAND, SIDEWAYS_SPEED
from trafficweaving.data.trials import load_trials
from trafficweaving.model.registry import load_model
from trafficweaving.model.crossval import out_of_fold_models
from trafficweaving.model.exemplars import build_exemplars
from trafficweaving.model.metrics import (DIRECTIONS, DURING_WITHOUT_END, HORIZON_STEPS, PHASES, InstanceMetrics,
                                          evaluate_instances, horizon_key, level_key)
from trafficweaving.viz.evaluation_figures import plot_coverage_calibration, plot_nll_by_phase, plot_nll_per_trial

CURVE_LEVELS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95)
"""Central-interval levels of the calibration curve (the tables show 50 % and 90 %)."""
FIGURES = {"calibration": "real_humans_coverage_calibration.png", "phase": "real_humans_nll_by_phase.png",
           "trial": "real_humans_nll_per_trial.png"}


def fmt(value, digits: int = 2) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def tables(results: dict[str, InstanceMetrics], variants: dict[str, str]) -> list[str]:
    """The report's Markdown tables, from each model's summary."""
    s = {name: m.summary() for name, m in results.items()}
    lines = ["## NLL", "",
             "Nats per instance for the human's next 15 accelerations `[xdd, ydd]` in m/s² (lower is better): "
             "exact (all latent values), importance-sampled with q and naive with p (50 latent samples each).", "",
             "| model | variant | instances | exact | importance-sampled | naive |", "|---|---|---|---|---|---|"]
    lines += [f"| {n} | {variants[n]} | {r['instances']} | {fmt(r['nll_exact'])} | {fmt(r['nll_is'])} | {fmt(r['nll_naive'])} |"
              for n, r in s.items()]
    lines += ["", "## Exact NLL by phase of the human's lane change", "",
              f"An instance at present step t is *before* the lane change if t < start (the last step before the divider "
              f"crossing with lateral speed towards the target lane ≤ {SIDEWAYS_SPEED} m/s), *during* it if start ≤ t < end "
              f"(the first step within {LANE_BAND} m of the target lane's centre; the crossing + {DURING_WITHOUT_END} steps where that is not "
              f"recorded), *after* otherwise; *none*: a human who never crosses the divider. "
              f"An instance needs 15 recorded future steps, so recordings that stop soon after the lane change have few "
              f"*after* instances.", "",
              "| model | " + " | ".join(PHASES) + " |", "|---|" + "---|" * len(PHASES)]
    lines += [f"| {n} | " + " | ".join(f"{fmt(r['nll_exact_by_phase'][p]['nll_exact'])} (n = {r['nll_exact_by_phase'][p]['instances']})"
                                       for p in PHASES) + " |" for n, r in s.items()]
    lines += ["", "## Exact NLL by direction", "",
              "`-log Σ_z p(z|x) Π_k p_k(y_k | z, recorded past)` with the per-step marginal density of one direction "
              "(15 accelerations). The two do not add up to the joint NLL, which also scores how the directions go together.", "",
              "| model | longitudinal x | lateral y | joint (both) |", "|---|---|---|---|"]
    lines += [f"| {n} | {fmt(r['nll_exact_by_direction']['x'])} | {fmt(r['nll_exact_by_direction']['y'])} | {fmt(r['nll_exact'])} |"
              for n, r in s.items()]
    first = next(iter(results.values()))
    lines += ["", "## Coverage of the human's position", "",
              f"Per direction and horizon, the percentage of instances whose true position lies within the central "
              f"50 % / 90 % interval of {first.samples} sampled futures (percentiles of the samples, linearly interpolated). "
              f"Nominal: 50 / 90. Below nominal: the model is overconfident; above: too cautious. True positions are the "
              f"trapezoid integration of the recorded accelerations from the recorded present state, as for the samples.", "",
              "| model | direction | " + " | ".join(f"{horizon_key(h)} s" for h in HORIZON_STEPS) + " |",
              "|---|---|" + "---|" * len(HORIZON_STEPS)]
    pct = lambda v: "n/a" if v is None else f"{100 * v:.0f}"  # noqa: E731
    for n, r in s.items():
        for d in DIRECTIONS:
            cells = [f"{pct(r['coverage'][d][horizon_key(h)][level_key(0.5)])} / {pct(r['coverage'][d][horizon_key(h)][level_key(0.9)])}"
                     for h in HORIZON_STEPS]
            lines.append(f"| {n} | {d} | " + " | ".join(cells) + " |")
    lines += ["", "## Displacement errors", "",
              f"Over {first.ade_samples} sampled futures per instance: minADE, the smallest mean Euclidean position error "
              f"over the 1.5 s horizon, and minFDE, the smallest error at 1.5 s (m, means over instances).", "",
              "| model | minADE (m) | minFDE (m) |", "|---|---|---|"]
    lines += [f"| {n} | {fmt(r['min_ade_m'])} | {fmt(r['min_fde_m'])} |" for n, r in s.items()]
    lines += ["", "## Held controls", "",
              "Percentage of the 15 predicted steps whose acceleration changes by less than 0.01 m/s² from the step "
              "before (a *held* pedal or steering wheel), in the sampled futures (mean over samples) and in the real "
              "drivers' futures. Sampled behaviour, so a narrow density component cannot inflate it: a model that "
              "learned intermittent control holds as often as the drivers do.", "",
              "| model | x sampled | x real | y sampled | y real |", "|---|---|---|---|---|"]
    pct1 = lambda v: "n/a" if v is None else f"{100 * v:.1f}"  # noqa: E731
    lines += [f"| {n} | " + " | ".join(f"{pct1(r['held_fraction'][d]['sampled'])} | {pct1(r['held_fraction'][d]['true'])}"
                                       for d in DIRECTIONS) + " |" for n, r in s.items()]
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="dataset of real trials (trafficweaving import hitl)")
    parser.add_argument("--model", action="append", required=True, metavar="NAME=SPEC")
    parser.add_argument("--out", default="docs/real_humans.md", help="the Markdown report; figures go to its folder's figures/")
    parser.add_argument("--samples", type=int, default=100, help="sampled futures per instance for the coverage")
    parser.add_argument("--ade-samples", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--nested", help="Markdown of scripts/nested_table.py, shown as the section 'Nested estimates'")
    args = parser.parse_args()
    torch.set_num_threads(1)
    out = Path(args.out)
    figures = out.parent / "figures"

    trials = load_trials(args.data)
    exemplars = build_exemplars(trials)
    results, variants = {}, {}
    for item in args.model:
        name, spec = item.split("=", 1)
        start = time.perf_counter()
        options = {"samples": args.samples, "ade_samples": args.ade_samples, "levels": CURVE_LEVELS, "seed": args.seed}
        if spec.startswith("crossval:"):
            parts = []
            for model, held in out_of_fold_models(spec.removeprefix("crossval:")):
                fold = trials.subset(np.flatnonzero(np.isin(trials.trial_ids, held)))
                parts.append(evaluate_instances(model, fold, build_exemplars(fold), **options))
            results[name] = InstanceMetrics.concatenate(parts)
            variants[name] = f"{model.config.name}, out-of-fold ({len(parts)} folds)"
        else:
            model = load_model(spec)
            results[name] = evaluate_instances(model, trials, exemplars, **options)
            variants[name] = model.config.name
        print(f"{name}: {time.perf_counter() - start:.0f} s", flush=True)

    plot_coverage_calibration(results, figures / FIGURES["calibration"])
    plot_nll_by_phase(results, figures / FIGURES["phase"])
    plot_nll_per_trial(results, figures / FIGURES["trial"])

    command = shlex.join(["python", "scripts/real_humans_report.py", *sys.argv[1:]])
    lines = [f"# Human models on real drivers: `{Path(args.data).name}`", "",
             f"Made by `{command}`; every number is from its last run. "
             f"{len(trials)} trials, {len(exemplars)} prediction instances (every human agent at every present step "
             f"4 ≤ t ≤ T−16, conditioned on the other car's recorded future). Models: "
             + ", ".join(f"**{n}** (`{spec.split('=', 1)[1]}`)" for n, spec in zip(results, args.model)) + ".", ""]
    if args.nested:
        lines += ["## Nested estimates", "",
                  "What a model trained by each recipe scores on trials it never saw, when every choice of the recipe "
                  "(candidate, steps, calibration, and the weight of the mixture with the authors' model) is made without "
                  "the fold it is scored on (model/crossval.py, "
                  "model/calibrate.py; [model.md](model.md#the-shipped-models)). Made by "
                  "`python scripts/nested_table.py` from the JSON of the commands in [model.md](model.md#reproduce).", "",
                  Path(args.nested).read_text().strip(), "",
                  "The sections below are out-of-fold analyses of each recipe at the choices made on all five folds.", ""]
    lines += [*tables(results, variants), "",
             "## Figures", "",
             f"Calibration of the sampled positions 1.5 s ahead at levels {', '.join(level_key(v) for v in CURVE_LEVELS)} %; "
             "a calibrated model lies on the diagonal.", "",
             f"![coverage calibration](figures/{FIGURES['calibration']})", "",
             f"![NLL by phase](figures/{FIGURES['phase']})", "",
             "Mean exact NLL of each trial's instances:", "",
             f"![NLL per trial](figures/{FIGURES['trial']})", ""]
    with atomic_write(out) as f:
        f.write("\n".join(lines).encode())
    print(f"wrote {out} and {len(FIGURES)} figures in {figures}")


if __name__ == "__main__":
    main()
