"""The nested estimates of docs/real_humans.md as Markdown, from the JSON of the commands that made them.

    python scripts/nested_table.py --crossval "authors, lr 1e-4=crossval_authors.json" ... \\
        --calibration "default=calibration_default.json" --calibration "simulated-real=calibration_simulated.json"

``--crossval NAME=FILE``: the JSON of ``trafficweaving crossval --nested --json`` (one candidate
recipe: its non-nested and nested per-fold NLL, the reference model's per fold). ``--calibration
NAME=FILE``: the JSON of ``trafficweaving calibrate --nested --json`` (the whole search: each outer
fold's candidate, calibration and scores); when it chose among as many candidates as there are
``--crossval`` files, they are taken to be its candidates in the same order, and the same choice is
also shown uncalibrated. Prints four tables: the candidates' step choice, the nested estimates per
fold and direction against the reference, each fold's choice, and how far each non-nested figure
was from its nested one.
"""

from __future__ import annotations

import argparse
import json

import numpy as np


def _named(text: str) -> tuple[str, dict]:
    name, _, path = text.partition("=")
    with open(path) as f:
        return name, json.load(f)


def _scale(scale) -> str:
    """An output scale as JSON holds it: one number (older files) or ``{"x", "y"}``."""
    return f"{scale:g}" if isinstance(scale, (int, float)) else f"{scale['x']:g} / {scale['y']:g}"


def _row(cells) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--crossval", action="append", default=[], help="NAME=crossval.json (crossval --nested --json)")
    parser.add_argument("--calibration", action="append", default=[], help="NAME=calibration.json (calibrate --nested --json)")
    args = parser.parse_args()
    crossvals = [_named(t) for t in args.crossval]
    calibrations = [_named(t) for t in args.calibration]
    reference = next(cv["reference"] for _, cv in crossvals if cv.get("reference"))
    k = len(reference["folds"])
    folds = " | ".join(f"fold {i + 1}" for i in range(k))

    print("**Candidates: steps chosen by cross-validation** (uncalibrated exact NLL per fold; *non-nested*: every "
          "fold at the steps the five folds choose together; *nested*: each fold at the steps its inner folds choose)\n")
    print(f"| candidate | steps | {folds} | mean | nested steps | nested mean |")
    print("|---|---|" + "---|" * k + "---|---|---|")
    for name, cv in crossvals:
        n = cv["nested"]
        print(_row([name, cv["steps"], *(f"{v:.2f}" for v in cv["folds"]), f"{cv['nll_exact']:.2f}",
                    "/".join(str(s) for s in n["steps"]), f"**{n['nll_exact']:.2f}**"]))
    print(_row([f"{reference['model'].split(':')[0]} (reference)", "—", *(f"{v:.2f}" for v in reference["folds"]),
                f"{reference['nll_exact']:.2f}", "—", "—"]))

    print("\n**Nested estimates of the whole search** (each fold's candidate, steps and calibration chosen on its inner "
          "folds alone; exact NLL per fold, joint / x / y)\n")
    print(f"| model | {folds} | mean | 90 % coverage at 1.5 s, x / y |")
    print("|---|" + "---|" * k + "---|---|")
    ref_dir = reference.get("folds_by_direction", {})
    for name, cal in calibrations:
        n = cal["nested"]
        cells = [f"{f['nll_exact']:.2f} / {f['nll_exact_by_direction']['x']:.2f} / {f['nll_exact_by_direction']['y']:.2f}"
                 for f in n["folds"]]
        dirs = {d: np.mean([f["nll_exact_by_direction"][d] for f in n["folds"]]) for d in ("x", "y")}
        cov = n["coverage_90"]
        print(_row([name, *cells, f"**{n['fold_mean_nll_exact']:.2f}** / {dirs['x']:.2f} / {dirs['y']:.2f}",
                    f"{100 * cov['x']:.0f} % / {100 * cov['y']:.0f} %"]))
        if len(cal.get("candidates") or []) == len(crossvals) > 1:  # the same choice of candidate and steps, uncalibrated
            picked = [crossvals[f["candidate"]][1]["nested"] for f in n["folds"]]
            joint = [p["folds"][i] for i, p in enumerate(picked)]
            x = [p["folds_by_direction"]["x"][i] for i, p in enumerate(picked)]
            y = [p["folds_by_direction"]["y"][i] for i, p in enumerate(picked)]
            print(_row([f"{name}, uncalibrated", *(f"{a:.2f} / {b:.2f} / {c:.2f}" for a, b, c in zip(joint, x, y)),
                        f"**{np.mean(joint):.2f}** / {np.mean(x):.2f} / {np.mean(y):.2f}", "see below"]))
    if ref_dir:
        cells = [f"{reference['folds'][i]:.2f} / {ref_dir['x'][i]:.2f} / {ref_dir['y'][i]:.2f}" for i in range(k)]
        print(_row([f"{reference['model'].split(':')[0]} (reference)", *cells,
                    f"{reference['nll_exact']:.2f} / {np.mean(ref_dir['x']):.2f} / {np.mean(ref_dir['y']):.2f}", "—"]))
    print("\n**Each fold's choice** (candidate, latent temperature, output scale x / y, and the weight of the mixture "
          "with the companion model where one was given; made on its inner folds)\n")
    print(f"| model | {folds} |")
    print("|---|" + "---|" * k)
    for name, cal in calibrations:
        candidates = cal.get("candidates") or []
        names = [n for n, _ in crossvals] if len(candidates) == len(crossvals) else candidates
        label = lambda c: names[c] if c < len(names) else f"candidate {c + 1}"  # noqa: E731
        mixed = lambda f: f", mixture {f['mixture_weight']:g}" if "companion" in cal else ""  # noqa: E731
        print(_row([name, *(f"{label(f['candidate'])}, {f['latent_temperature']:g}, {_scale(f['output_scale'])}{mixed(f)}"
                            for f in cal["nested"]["folds"])]))

    print("\n**Non-nested against nested** (exact NLL, mean over folds)\n")
    print("| model | non-nested (choices made on the folds it scores) | nested | optimism (nats) |")
    print("|---|---|---|---|")
    for name, cal in calibrations:
        grid_pick = cal["nll_exact"]  # pooled over instances, as the nested `nll_exact`
        nested = cal["nested"]["nll_exact"]
        print(_row([f"{name} (per instance)", f"{grid_pick:.2f}", f"{nested:.2f}", f"{nested - grid_pick:+.2f}"]))
    for name, cv in crossvals:
        print(_row([f"{name}, steps only (per fold)", f"{cv['nll_exact']:.2f}", f"{cv['nested']['nll_exact']:.2f}",
                    f"{cv['nested']['nll_exact'] - cv['nll_exact']:+.2f}"]))


if __name__ == "__main__":
    main()
