"""Evaluate human models on the held-out split of a synthetic dataset and on the authors' 30 real
human-in-the-loop trials, and write the table (``docs/<--table>``); with ``--figures`` also the
paper's Fig. 3 for the first and last model and the validation curves (``docs/figures``).

    python scripts/model_report.py --data synthetic_4000.parquet --real hitl.parquet --table model_table.md \
        --model "cvae (shipped)=src/trafficweaving/model/default_cvae.pt" ... \
        --model "authors=authors:path/to/weights.npz" --figures

The held-out split is the validation split ``trafficweaving train`` makes of ``--data`` (80/20 by
trial, seed 0). Every number is measured in this run.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from trafficweaving.demo import DEMO_REAL_PICKS
from trafficweaving.data.trials import load_trials
from trafficweaving.model.checkpoint import read_checkpoint
from trafficweaving.model.evaluate import evaluate
from trafficweaving.model.exemplars import build_exemplars, split_by_trial
from trafficweaving.model.registry import load_model, model_path
from trafficweaving.model.spec import parse_model_spec
from trafficweaving.model.train_config import TrainConfig
from trafficweaving.viz.model_figures import plot_predictions, plot_validation_curves


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="the synthetic training dataset")
    parser.add_argument("--real", required=True, help="imported real trials (trafficweaving import hitl)")
    parser.add_argument("--model", action="append", required=True, metavar="NAME=SPEC")
    parser.add_argument("--out", default="variants")
    parser.add_argument("--table", default="model_table.md", help="file name of the table, in --out")
    parser.add_argument("--figures", action="store_true", help="also draw Fig. 3 and the validation curves")
    args = parser.parse_args()
    out = Path(args.out)

    synthetic, real = load_trials(args.data), load_trials(args.real)
    tc = TrainConfig()
    held_trials = synthetic.subset(split_by_trial(len(synthetic), tc.validation_fraction, tc.seed)[1])
    held_out = build_exemplars(held_trials)
    real_ex = build_exemplars(real)
    rows, curves = [], {}
    fmt = lambda v: "n/a" if v is None else f"{v:.2f}"  # noqa: E731
    for item in args.model:
        name, spec = item.split("=", 1)
        model = load_model(spec)
        start = time.perf_counter()
        on_synthetic, on_real = evaluate(model, held_out).summary(), evaluate(model, real_ex).summary()
        print(f"{name}: synthetic {on_synthetic}, real {on_real} ({time.perf_counter() - start:.0f} s)", flush=True)
        steps = "—"
        if parse_model_spec(spec).kind != "authors":
            payload = read_checkpoint(model_path(spec))
            steps, curves[name] = f"{payload['step']:,}", payload.get("history", [])
        rows.append(f"| {name} | {model.config.latent_vars} × {model.config.latent_classes} | {model.config.components} | {steps} | "
                    + " | ".join(fmt(r[k]) for r in (on_synthetic, on_real) for k in ("nll_exact", "nll_is", "nll_naive")) + " |")

    if args.figures:
        figures = out / "figures"
        default_name, default_spec = args.model[0].split("=", 1)
        plot_validation_curves(curves, figures / "validation_curves.png")
        for name, spec in (args.model[0].split("=", 1), args.model[-1].split("=", 1)):
            slug = "authors" if parse_model_spec(spec).kind == "authors" else "default"
            plot_predictions(load_model(spec), real, DEMO_REAL_PICKS, figures / f"fig3_real_{slug}.png", title=f"{name} on real trials")
        syn_picks = [(i, 0, min(t, int(held_trials.lengths[i]) - 16)) for i, t in ((0, 12), (1, 22))]
        plot_predictions(load_model(default_spec), held_trials, syn_picks, figures / "fig3_synthetic_default.png",
                         title=f"{default_name} on held-out synthetic trials")

    lines = [
        f"# Human models evaluated: held-out trials of `{Path(args.data).name}` and the real trials",
        "",
        f"Made by `python scripts/model_report.py --data {args.data} ...` (the full command is in docs/model.md); numbers from its last run.",
        "",
        "NLL: nats per prediction instance for the human's next 15 accelerations `[xdd, ydd]` in m/s² "
        "(lower is better): exact (all latent values), importance-sampled with q (50 samples), naive with p (50 samples). "
        f"Held-out synthetic: the {len(held_out)} instances of the validation trials (20 %, split by trial) of `{Path(args.data).name}`. "
        f"Real: the {len(real_ex)} instances of the 30 human-in-the-loop trials (human = car2, robot future = recorded).",
        "",
        "| model | latent N_z × K_z | GMM M | steps | synthetic exact | synthetic IS | synthetic naive | real exact | real IS | real naive |",
        "|---|---|---|---|---|---|---|---|---|---|",
        *rows,
        "",
    ]
    (out / args.table).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()
