"""The shipped models' files, and loading the model a spec names (:mod:`~trafficweaving.model.spec`):
a shipped model, a checkpoint or the authors' weights."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import torch

from ..errors import InputError
from .authors import load_authors_model
from .checkpoint import load_checkpoint
from .cvae import CVAE
from .mixture import Mixture, companion_for
from .spec import SHIPPED_MODELS, ModelSpec, check_model_spec, parse_model_spec


def shipped_model_path(name: str = "default") -> Path:
    """The file of the model shipped inside the package as ``name`` (:data:`~.spec.SHIPPED_MODELS`)."""
    return Path(str(resources.files(__package__).joinpath(SHIPPED_MODELS[name])))


def default_model_path() -> Path:
    """The model ``--model default`` loads."""
    return shipped_model_path("default")


def model_path(spec: str) -> Path:
    """The checkpoint file of a ``--model`` value that names one: a shipped model's name or a path."""
    return shipped_model_path(spec) if spec in SHIPPED_MODELS else Path(spec)


def load_model(spec: str | ModelSpec, device: torch.device | str = "cpu") -> CVAE | Mixture:
    """The model (evaluation mode, on ``device``) of a model spec (:func:`~.spec.parse_model_spec`):
    a shipped model's name, ``authors:PATH`` or a checkpoint path."""
    if not isinstance(spec, ModelSpec):
        spec = parse_model_spec(spec)
    if spec.kind == "shipped":
        model, _ = load_checkpoint(shipped_model_path(spec.path))
    elif spec.kind == "authors":
        model = load_authors_model(spec.path)
    else:
        model, _ = load_checkpoint(spec.path)
    return model.to(device)


def load_companion(spec: str, models: list[tuple[str, CVAE]]) -> CVAE:
    """The ``--companion`` of ``mix`` and ``calibrate``: the model of ``spec``
    (:func:`~.spec.check_model_spec`, :func:`load_model`), checked before any work against every
    model it will be mixed with, ``models`` ``[(name in messages, model)]``, by
    :func:`~.mixture.companion_for`; InputError naming ``--companion`` otherwise."""
    companion = load_model(check_model_spec(spec, "--companion"))
    for name, model in models:
        try:
            companion = companion_for(model, companion)
        except ValueError as exc:
            raise InputError(f"--companion {spec}: {exc}, for {name}") from None
    return companion
