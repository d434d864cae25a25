"""The model spec grammar: which model a ``--model`` value, or the ``SPEC`` of a ``model:SPEC``
human, names, without loading it (no torch here, so a command checks its options fast).

    SPEC := NAME | authors:PATH | PATH

``NAME`` is a shipped model (:data:`SHIPPED_MODELS`), ``authors:PATH`` the authors' published
weights (``weights.npz``, :mod:`~trafficweaving.model.authors`), anything else a checkpoint file
(:mod:`~trafficweaving.model.checkpoint`). :func:`~trafficweaving.model.registry.load_model` loads
what a spec names.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError

SHIPPED_MODELS = {  # --model name: file in the package (docs/model.md, "The shipped models")
    "default": "default_cvae.pt",  # the authors' real-data model with hold modes, fine-tuned on the 30 real trials
    "simulated-real": "simulated_real_cvae.pt",  # no authors' weights: simulated drivers, then the 30 real trials
    "driver": "driver_cvae.pt",  # a driver: the default's recipe conditioned on a guess of the other car (docs/realism.md)
    "fast": "fast_cvae.pt",  # the default distilled into a 16-unit, 8-component decoder: the full budget on a CPU (docs/fast_model.md)
}
AUTHORS = "authors:"
"""The prefix of a spec naming the authors' weights."""
EXPECTED = f"expected a checkpoint path, {', '.join(SHIPPED_MODELS)}, or authors:PATH to the authors' weights.npz"
"""What a model spec may be, as messages say it."""


@dataclass(frozen=True)
class ModelSpec:
    """A parsed model spec: ``text`` as given; ``kind`` ``shipped``, ``authors`` or ``checkpoint``;
    ``path``: the shipped model's name, the authors' ``weights.npz`` or the checkpoint file."""

    text: str
    kind: str
    path: str


def parse_model_spec(text: str, what: str | None = None) -> ModelSpec:
    """``text`` as a :class:`ModelSpec`; InputError when it has no path. ``what`` names the option
    in the message (``--companion``); None: a spec given to a function (``model spec ...``)."""
    if text in SHIPPED_MODELS:
        return ModelSpec(text, "shipped", text)
    kind = "authors" if text.startswith(AUTHORS) else "checkpoint"
    path = text.removeprefix(AUTHORS) if kind == "authors" else text
    if path:
        return ModelSpec(text, kind, path)
    if what is not None:
        raise InputError(f"{what} {text!r}: empty path ({EXPECTED})")
    if not text:
        raise InputError(f"model spec is empty ({EXPECTED})")
    raise InputError(f"model spec {text!r} has no path after {AUTHORS} ({EXPECTED})")


def check_model_spec(text: str, what: str) -> str:
    """``text``, the value of option ``what``, checked before any long work: a spec whose file
    exists (the file's contents are checked when it is loaded); InputError naming ``what`` otherwise."""
    spec = parse_model_spec(text, what)
    if spec.kind != "shipped" and not Path(spec.path).is_file():
        raise InputError(f"{what} {text}: no such file ({EXPECTED})")
    return text
