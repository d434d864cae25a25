"""Put a trained checkpoint into the package as the model ``--model NAME`` loads (``--name``:
``default`` or ``simulated-real``).

    python scripts/ship_model.py runs/shipped.pt [--name default] --data-command "trafficweaving import hitl ..." \\
        --summary "pre-trained on simulated drivers, fine-tuned on 30 real trials" \\
        --recipe "$(cat recipe.txt)" --crossval runs/crossval.json

Drops the optimizer and RNG state (only resuming needs them) and records how the training data was
made, the whole recipe, a one-line summary and the cross-validation that chose the recipe (the
JSON of ``trafficweaving crossval --json``). A fine-tuned checkpoint already carries its initial
model's provenance (``init``: path, variant, step, data fingerprint), so the shipped file holds both
data fingerprints.
"""

from __future__ import annotations

import argparse
import json

from trafficweaving.model.checkpoint import export_checkpoint
from trafficweaving.model.registry import shipped_model_path
from trafficweaving.model.spec import SHIPPED_MODELS


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", help="a checkpoint written by `trafficweaving train`")
    parser.add_argument("--name", choices=tuple(SHIPPED_MODELS), default="default", help="the --model name it ships as")
    parser.add_argument("--data-command", required=True, help="the command that made the (last) training data")
    parser.add_argument("--recipe", help="every command of the recipe, from data to this checkpoint")
    parser.add_argument("--summary", help="one line: what the model was trained on")
    parser.add_argument("--crossval", help="the JSON printed by `trafficweaving crossval --json` for this recipe")
    args = parser.parse_args()
    provenance = {"data_command": args.data_command}
    for key in ("recipe", "summary"):
        if getattr(args, key):
            provenance[key] = getattr(args, key)
    if args.crossval:
        with open(args.crossval) as f:
            provenance["crossval"] = json.load(f)
    export_checkpoint(args.checkpoint, shipped_model_path(args.name), **provenance)
    print(f"wrote {shipped_model_path(args.name)}")


if __name__ == "__main__":
    main()
