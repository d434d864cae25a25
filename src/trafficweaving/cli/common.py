"""What every command group shares: argument types, the one-line error convention, output
(``--json`` or text), the early ``--model`` check, and the signal handling of :func:`main`."""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
from pathlib import Path

from ..errors import InputError

SEED_MAX = 2**32 - 1
"""Largest ``--seed`` (NumPy and PyTorch accept every seed in 0..2³²-1 on every platform)."""


class _Terminated(BaseException):
    """Raised in the main thread when SIGTERM arrives, so that open outputs are cleaned up."""


class _Parser(argparse.ArgumentParser):
    """argparse with the project's error convention: one line on stderr and exit status 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


# ---------------------------------------------------------------- option types
def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None


def _int_at_least(low: int, high: int | None = None):
    """An argparse type: an integer in ``low..high``."""
    def parse(text: str) -> int:
        value = _integer(text)
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"expected an integer in {low}..{high if high is not None else ''}, got {value}"
                                             if high is not None else f"expected an integer >= {low}, got {value}")
        return value
    return parse


def _float_in(low: float, high: float, include_low: bool = False, include_high: bool = False):
    """An argparse type: a finite float in the interval from ``low`` to ``high``."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        above = value >= low if include_low else value > low
        below = value <= high if include_high else value < high
        if not (math.isfinite(value) and above and below):
            interval = f"{'[' if include_low else '('}{low:g}, {high:g}{']' if include_high else ')'}"
            raise argparse.ArgumentTypeError(f"expected a finite number in {interval}, got {text}")
        return value
    return parse


def _floats_in(low: float, high: float):
    """An argparse type: a comma-separated list of finite floats in ``(low, high)``."""
    one = _float_in(low, high)

    def parse(text: str) -> tuple[float, ...]:
        try:
            return tuple(one(part) for part in text.split(","))
        except argparse.ArgumentTypeError as exc:
            raise argparse.ArgumentTypeError(f"{exc} in the list {text!r}") from None
    return parse


POSITIVE = _int_at_least(1)
NON_NEGATIVE = _int_at_least(0)
SEED = _int_at_least(0, SEED_MAX)


# ---------------------------------------------------------------- output
def _json_safe(value):
    """``value`` with every non-finite float replaced by None (JSON has no NaN or Infinity) and
    NumPy scalars as Python numbers."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if hasattr(value, "item") and getattr(value, "ndim", None) == 0:
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _emit(args, payload: dict, text: str) -> None:
    print(json.dumps(_json_safe(payload), allow_nan=False) if args.json else text)


def _log(args):
    """Progress lines: stderr under ``--json`` (stdout holds the one JSON object), else stdout."""
    return (lambda line: print(line, file=sys.stderr)) if args.json else print


def _fmt(value) -> str:
    return "n/a" if value is None else f"{value:.3f}"



# ---------------------------------------------------------------- signals
def _raise_terminated(signum, frame):
    raise _Terminated


def _die_by_signal(signum: int) -> None:
    """Exit as killed by ``signum`` (the shell convention: status 128 + signum), after cleanup."""
    sys.stdout.flush()
    signal.signal(signum, signal.SIG_DFL)
    os.kill(os.getpid(), signum)
    sys.exit(128 + signum)  # if the signal could not end the process
