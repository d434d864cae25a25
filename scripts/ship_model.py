"""Put a trained checkpoint into the package as the model ``--model default`` loads.

    python scripts/ship_model.py out/train/cvae_default.pt --data-command "trafficweaving generate --trials 4000 --seed 0"

Drops the optimizer and RNG state (only resuming needs them) and records how the training data
was made.
"""

from __future__ import annotations

import argparse

from trafficweaving.model.checkpoint import default_model_path, export_checkpoint


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", help="a checkpoint written by `trafficweaving train`")
    parser.add_argument("--data-command", required=True, help="the command that made the training data")
    args = parser.parse_args()
    export_checkpoint(args.checkpoint, default_model_path(), data_command=args.data_command)
    print(f"wrote {default_model_path()}")


if __name__ == "__main__":
    main()
