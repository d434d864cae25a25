"""Checks of values handed to the library's entry points (model sampling, planner, MPC, benchmarks).

One home for the rules and their wording: a failed check raises
:class:`~trafficweaving.errors.InputError` with one line naming the argument and what was expected.
"""

from __future__ import annotations

import math
import numbers
import os

import numpy as np
import torch

from .errors import InputError
from .scenario import MIN_HISTORY, STATE_NAMES

_STATE_DIM = len(STATE_NAMES)


def finite_array(name: str, value, shape: tuple[int | None, ...], expected: str) -> np.ndarray:
    """``value`` (array-like or tensor) as a float64 array of ``shape`` (``None``: any length) with
    only finite numbers; ``expected`` is the shape as messages print it, e.g. ``"[B, 15, 6]"``."""
    try:
        array = np.asarray(value.detach().cpu().double() if isinstance(value, torch.Tensor) else value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} is not an array of numbers (expected a finite float array {expected})") from None
    if array.ndim != len(shape) or any(s is not None and a != s for a, s in zip(array.shape, shape)):
        raise InputError(f"{name} has shape {list(array.shape)} (expected {expected})")
    if not np.isfinite(array).all():
        raise InputError(f"{name} has NaN or infinite values (expected finite numbers)")
    return array


def history(value, min_steps: int = MIN_HISTORY, name: str = "history") -> np.ndarray:
    """An interaction history ``[t+1, 2, 6]``: robot (index 0) and human states ``[x, y, xd, yd,
    xdd, ydd]`` (m, m/s, m/s²) at steps 0..t, finite, at least ``min_steps`` steps."""
    array = finite_array(name, value, (None, 2, _STATE_DIM), f"[t+1 >= {min_steps}, 2, {_STATE_DIM}]")
    if len(array) < min_steps:
        raise InputError(f"{name} has {len(array)} steps (expected at least {min_steps})")
    return array


def integer(name: str, value, low: int, high: int | None = None) -> int:
    """``value`` as an ``int`` in ``low..high`` (``high`` None: no upper bound); bools, floats and
    other non-integers are refused (NumPy integers are accepted)."""
    if high is not None:
        expected = f"an integer in {low}..{high}"
    else:
        expected = {0: "a non-negative integer", 1: "a positive integer"}.get(low, f"an integer >= {low}")
    if (isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral)
            or value < low or (high is not None and value > high)):
        raise InputError(f"{name} must be {expected}, got {value!r}")
    return int(value)


def indices(name: str, value, count: int) -> np.ndarray:
    """``value`` (array-like or tensor) as a non-empty 1-D int64 array of indices in ``0..count-1``."""
    array = np.asarray(value.detach().cpu() if isinstance(value, torch.Tensor) else value)
    valid = array.ndim == 1 and array.size > 0 and array.dtype.kind in "iu"
    if not valid or array.min() < 0 or array.max() >= count:
        got = f"values {array.min()}..{array.max()}" if valid else f"an array of {array.dtype}, shape {list(array.shape)}"
        raise InputError(f"{name} must be a non-empty 1-D array of integers in 0..{count - 1}, got {got}")
    return array.astype(np.int64)


def positive_seconds(name: str, value) -> float:
    """``value`` as a finite duration in seconds > 0."""
    if (isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real)
            or not math.isfinite(value) or value <= 0):
        raise InputError(f"{name} must be a finite number of seconds > 0, got {value!r}")
    return float(value)


def thread_count(name: str, value) -> int:
    """A CPU thread count for ``torch.set_num_threads``: an integer in ``1..os.cpu_count()``
    (PyTorch refuses 0 or fewer with a traceback and crashes on huge counts)."""
    return integer(name, value, 1, os.cpu_count() or 1)
