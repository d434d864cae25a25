"""Device choice: the one place that turns a ``--device`` value into a torch device."""

from __future__ import annotations

import re

import torch

from ..errors import InputError


def choose_device(name: str = "auto") -> torch.device:
    """``auto`` picks CUDA when available, else CPU; otherwise ``cpu``, ``cuda`` or ``cuda:N``.

    Other torch device types (``meta``, ``mps``, ...) are refused here: the model code runs on CPU
    and CUDA only, and a ``meta`` model would only fail later, far from the option.
    """
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    expected = (f"expected auto, cpu, cuda or cuda:N with N < {count}" if count else
                "expected auto or cpu; cuda and cuda:N need CUDA, which is not available here")
    if name == "auto":
        return torch.device("cuda" if count else "cpu")
    if name == "cpu":
        return torch.device("cpu")
    match = re.fullmatch(r"cuda(?::(\d+))?", name) if isinstance(name, str) else None
    if match is None:
        raise InputError(f"--device {name!r}: unknown device ({expected})")
    if not count:
        raise InputError(f"--device {name!r}: CUDA is not available ({expected})")
    if match[1] is not None and int(match[1]) >= count:
        raise InputError(f"--device {name!r}: no such CUDA device, this machine has {count} ({expected})")
    return torch.device(name)
