"""Model files: saving and loading checkpoints, and resolving ``--model`` specifications.

A checkpoint is a ``torch.save`` dictionary readable with ``weights_only=True`` (no pickled code):
``format``, ``version``, ``config`` (the :class:`CVAEConfig` fields), ``state_dict`` (parameters
and standardisation buffers), ``data_fingerprint``, ``step``, ``history`` (validation NLL by step)
and, in training checkpoints, ``train_config``, ``optimizer`` and ``rng`` for resuming.
"""

from __future__ import annotations

import dataclasses
import io
from importlib import resources
from pathlib import Path

import torch

from ..atomic import atomic_write
from ..errors import InputError
from .cvae import CVAE, CVAEConfig

FORMAT = "trafficweaving-cvae"
VERSION = 1
DEFAULT_MODEL = "default_cvae.pt"
EXPECTED = "a trafficweaving model checkpoint (.pt written by `trafficweaving train`)"


def choose_device(name: str = "auto") -> torch.device:
    """``auto`` picks CUDA when available, else CPU; otherwise the named device."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise InputError(f"unknown device {name!r} (expected auto, cpu, cuda or cuda:N)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"device {name!r} requested but CUDA is not available (expected auto or cpu)")
    return device


def save_checkpoint(path: str | Path, model: CVAE, **fields) -> None:
    """Write ``model`` and extra ``fields`` (step, history, data_fingerprint, optimizer, ...) atomically."""
    payload = {"format": FORMAT, "version": VERSION, "config": model.config.to_dict(),
               "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()}, **fields}
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    with atomic_write(path) as f:
        f.write(buffer.getvalue())


TRAINING_ONLY = ("optimizer", "rng")
CALIBRATION = ("latent_temperature", "output_scale")
"""Buffers set by calibration (model/calibrate.py); checkpoints written before it lack them (1, 1)."""


def export_checkpoint(source: str | Path, destination: str | Path, **provenance) -> None:
    """Copy a training checkpoint without what only resuming needs (optimizer moments, RNG state),
    adding ``provenance`` fields (e.g. how the training data was made)."""
    payload = read_checkpoint(source)
    model = model_from_checkpoint(payload, source)
    fields = {k: v for k, v in payload.items() if k not in (*TRAINING_ONLY, "format", "version", "config", "state_dict")}
    save_checkpoint(destination, model, **fields, **provenance)


def read_checkpoint(path: str | Path) -> dict:
    """The validated checkpoint dictionary; :class:`InputError` naming the file when it is not one."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file (expected {EXPECTED})")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # any unreadable file is the user's input error here
        raise InputError(f"{path}: not a readable checkpoint ({type(exc).__name__}; expected {EXPECTED})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise InputError(f"{path}: not a trafficweaving model checkpoint (expected {EXPECTED})")
    if payload.get("version") != VERSION:
        raise InputError(f"{path}: checkpoint version {payload.get('version')} (expected {VERSION})")
    return payload


def model_from_checkpoint(payload: dict, path: str | Path) -> CVAE:
    """Build the model a checkpoint describes and load its weights, checking every tensor."""
    fields = {f.name for f in dataclasses.fields(CVAEConfig)}
    config = payload.get("config")
    if not isinstance(config, dict) or set(config) - fields:
        raise InputError(f"{path}: checkpoint has a malformed config (expected the fields {sorted(fields)})")
    model = CVAE(CVAEConfig(**config))
    expected = model.state_dict()
    state = payload.get("state_dict", {})
    state = {**{k: expected[k] for k in CALIBRATION if k not in state}, **state}  # older files: uncalibrated
    missing, extra = set(expected) - set(state), set(state) - set(expected)
    if missing or extra:
        name = sorted(missing or extra)[0]
        raise InputError(f"{path}: checkpoint {'lacks' if missing else 'has unexpected'} tensor {name} (expected a {model.config.name} model)")
    for name, tensor in state.items():
        if tuple(tensor.shape) != tuple(expected[name].shape):
            raise InputError(f"{path}: tensor {name} has shape {list(tensor.shape)} (expected {list(expected[name].shape)})")
        if not torch.isfinite(tensor).all():
            raise InputError(f"{path}: tensor {name} has NaN or infinite values (expected finite weights)")
    model.load_state_dict(state)
    return model.eval()


def load_checkpoint(path: str | Path) -> tuple[CVAE, dict]:
    """The model of a checkpoint file (evaluation mode) and the checkpoint dictionary."""
    payload = read_checkpoint(path)
    return model_from_checkpoint(payload, path), payload


def default_model_path() -> Path:
    """The model shipped inside the package (``cvae`` trained on our synthetic data)."""
    return Path(str(resources.files(__package__).joinpath(DEFAULT_MODEL)))


def load_model(spec: str, device: torch.device | str = "cpu") -> CVAE:
    """Resolve a ``--model`` value: ``default``, ``authors:PATH`` or a checkpoint path."""
    if spec == "default":
        model, _ = load_checkpoint(default_model_path())
    elif spec.startswith("authors:"):
        from .authors import load_authors_model

        model = load_authors_model(spec.removeprefix("authors:"))
    else:
        model, _ = load_checkpoint(spec)
    return model.to(device)
