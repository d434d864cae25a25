"""The checkpoint file format: writing model files and reading them back, checked.

A checkpoint is a ``torch.save`` dictionary readable with ``weights_only=True`` (no pickled code):
``format``, ``version`` (6), ``config`` (the :class:`CVAEConfig` fields), ``state_dict`` (parameters
and standardisation buffers), for a :class:`~trafficweaving.model.mixture.Mixture` ``mixture``
(``weights``, a float64 tensor with one weight per component, optionally ``person_weights``, the
weights of a driver facing a person, likewise, and ``components``: the ``config`` and ``state_dict``
of every component after the first, which is the file's own model), ``tensor_sha256`` (a SHA-256
of every tensor in the file, see :func:`tensor_digest`), ``data_fingerprint``, ``step``, ``history`` (validation NLL by step) and, in
training checkpoints, ``train_config``, ``optimizer`` and ``rng`` for resuming.

Loading checks everything a reader later relies on, so that a corrupted or hand-edited file is
refused with one :class:`InputError` naming it instead of loading silently (``torch.load`` does not
check the zip entries' CRCs, and ``load_state_dict`` casts integer tensors into float weights) or
failing later with a traceback: the tensors' digest, the config's types and ranges, each tensor's
dtype, shape and finiteness, positive standard deviations and calibration (docs/model.md,
docs/calibration.md), a mixture's weights (finite, positive, with a finite sum), and the types of
the fields the commands read. Which file a ``--model`` value names, and loading it, is
:mod:`~trafficweaving.model.registry`'s job.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import math
import re
import warnings
from pathlib import Path

import torch

from ..atomic import atomic_write
from ..errors import InputError
from .cvae import CVAE, ROBOT_FUTURES, CVAEConfig
from .gmm import HOLD_MIN_SIGMA, LOG_SIGMA_CLIP
from .mixture import Mixture, normalised
from .train_config import TRAINABLE, TrainConfig

FORMAT = "trafficweaving-cvae"
VERSION = 6
"""2: adds ``tensor_sha256`` (version 1 files, without it, are refused); 3: the output scale no
longer widens the hold modes; 4: one output scale per direction; 5: mixtures; 6: a mixture's
weights are tensors, inside the SHA-256. Older files are read with the same density
(:func:`upgrade_state`), except version 5 mixtures (:data:`MIXTURE_VERSION`)."""
READABLE_VERSIONS = (2, 3, 4, 5, 6)
MIXTURE_VERSION = 6
"""The first version whose mixtures are read: version 5 stored a mixture's weights as numbers,
outside the SHA-256."""
HASH_FIELD = "tensor_sha256"
EXPECTED = "a trafficweaving model checkpoint (.pt written by `trafficweaving train`)"
WRITTEN_BY_US = "expected a checkpoint as written by trafficweaving"

MAX_SIZE = 4096
"""Largest accepted config size (units, components, latent variables or classes): a guard against
hand-edited configs that would allocate absurd models; the paper's largest is 128."""
MAX_LATENT_VALUES = 4096
"""Largest accepted ``latent_classes ** latent_vars`` (the paper's: 5² = 25), enumerated by the model."""
POSITIVE_BUFFERS = {"feature_std": "positive standard deviations", "label_std": "positive standard deviations",
                    "latent_temperature": "a positive temperature", "output_scale": "a positive scale"}
"""Buffers that divide or scale and must be positive (model/cvae.py, model/calibrate.py)."""


# ---------------------------------------------------------------- the tensor digest
def _order(key) -> tuple[str, str]:
    """A total order on dictionary keys of any (mixed) types, deterministic across runs."""
    return type(key).__name__, repr(key)


def _hash_tensors(h, value, where: str) -> None:
    if isinstance(value, torch.Tensor):
        tensor = value.detach().cpu()
        if tensor.layout != torch.strided:
            tensor = tensor.to_dense()
        header = f"{where}\0{str(tensor.dtype).removeprefix('torch.')}\0{list(tensor.shape)}".encode()
        data = tensor.contiguous().reshape(-1).view(torch.uint8).numpy()
        h.update(len(header).to_bytes(8, "little") + header + data.nbytes.to_bytes(8, "little"))
        h.update(data)
    elif isinstance(value, dict):
        for key in sorted(value, key=_order):
            _hash_tensors(h, value[key], f"{where}/{key}")
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            _hash_tensors(h, item, f"{where}/{i}")


def tensor_digest(payload: dict) -> str:
    """SHA-256 (hex) over every tensor in ``payload`` except the digest field itself: for each, in
    a fixed walk (dicts in sorted-key order, lists in order), its path (``/state_dict/decoder.bias``),
    dtype, shape and raw bytes. Detects flipped bytes in a file's tensor data and edited tensors."""
    h = hashlib.sha256()
    _hash_tensors(h, {k: v for k, v in payload.items() if k != HASH_FIELD}, "")
    return h.hexdigest()


# ---------------------------------------------------------------- writing
def write_payload(path: str | Path, payload: dict) -> None:
    """Write a checkpoint dictionary atomically with its ``tensor_sha256`` (re)computed."""
    payload = {**payload, HASH_FIELD: tensor_digest(payload)}
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    with atomic_write(path) as f:
        f.write(buffer.getvalue())


RESERVED = ("format", "version", "config", "state_dict", "mixture", HASH_FIELD)
"""Fields :func:`save_checkpoint` writes itself (given ones are replaced: they describe the model)."""


def _model_fields(model: CVAE) -> dict:
    return {"config": model.config.to_dict(), "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()}}


def save_checkpoint(path: str | Path, model: CVAE | Mixture, **fields) -> None:
    """Write ``model`` and extra ``fields`` (step, history, data_fingerprint, optimizer, ...) atomically."""
    mixture = {}
    if isinstance(model, Mixture):
        mixture = {"mixture": {"weights": torch.tensor(model.weights, dtype=torch.float64),
                               "components": [_model_fields(c) for c in model.components[1:]]}}
        if model.person_weights is not None:
            mixture["mixture"]["person_weights"] = torch.tensor(model.person_weights, dtype=torch.float64)
        model = model.components[0]
    payload = {"format": FORMAT, "version": VERSION, **_model_fields(model), **mixture,
               **{k: v for k, v in fields.items() if k not in RESERVED}}
    write_payload(path, payload)


TRAINING_ONLY = ("optimizer", "rng")


def export_checkpoint(source: str | Path, destination: str | Path, **provenance) -> None:
    """Copy a training checkpoint without what only resuming needs (optimizer moments, RNG state),
    adding ``provenance`` fields (e.g. how the training data was made)."""
    payload, model = _read(source)
    fields = {k: v for k, v in payload.items() if k not in (*TRAINING_ONLY, *RESERVED)}
    save_checkpoint(destination, model, **fields, **provenance)


# ---------------------------------------------------------------- reading and checking
def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _is_list_of(value, test) -> bool:
    return isinstance(value, (list, tuple)) and all(test(v) for v in value)


def _history_entry(entry) -> bool:
    """``(step, validation NLL, ...)``; an NLL may be None (nothing to validate)."""
    return (_is_list_of(entry, lambda v: v is None or _is_number(v)) and len(entry) >= 2
            and _is_int(entry[0]) and entry[0] >= 0)


FIELD_CHECKS = {  # field: (test, what is expected); fields read by train, crossval, calibrate, demo, scripts
    "step": (lambda v: _is_int(v) and v >= 0, "a non-negative integer"),
    "history": (lambda v: _is_list_of(v, _history_entry), "a list of [step, validation NLL, ...] rows"),
    "data_fingerprint": (lambda v: isinstance(v, str), "a string"),
    "held_out_trials": (lambda v: _is_list_of(v, _is_int), "a list of integer trial ids"),
    "init": (lambda v: isinstance(v, dict), "a dictionary"),
    "calibration": (lambda v: isinstance(v, dict), "a dictionary"),
    "crossval": (lambda v: isinstance(v, dict), "a dictionary"),
    "train_config": (lambda v: isinstance(v, dict) and all(isinstance(k, str) for k in v), "a dictionary"),
    "recipe": (lambda v: isinstance(v, str), "a string"),
    "data_command": (lambda v: isinstance(v, str), "a string"),
    "summary": (lambda v: isinstance(v, str), "a string"),
}


def _check_train_config(config: dict, path) -> None:
    """Types of the known :class:`~trafficweaving.model.train_config.TrainConfig` fields (``--resume``)."""
    for f in dataclasses.fields(TrainConfig):
        if f.name not in config or f.default is None:
            continue
        value, default = config[f.name], f.default
        if _is_int(default):
            ok, expected = _is_int(value), "an integer"
        elif isinstance(default, float):
            ok, expected = _is_number(value) and math.isfinite(value), "a finite number"
        else:
            ok, expected = isinstance(value, type(default)), type(default).__name__
        if not ok:
            raise InputError(f"{path}: train_config field {f.name} is {_short(value)} (expected {expected}; {WRITTEN_BY_US})")


def _check_optimizer(optimizer, path) -> None:
    """Structure and finiteness of the resumable optimizer state (a ``torch.optim`` state dict)."""
    groups = optimizer.get("param_groups") if isinstance(optimizer, dict) else None
    if not (isinstance(optimizer, dict) and isinstance(optimizer.get("state"), dict)
            and _is_list_of(groups, lambda g: isinstance(g, dict) and _is_list_of(g.get("params"), _is_int))):
        raise InputError(f"{path}: checkpoint field optimizer is malformed (expected a torch optimizer state "
                         f"dict with state and param_groups; {WRITTEN_BY_US})")
    for key, state in optimizer["state"].items():
        tensors = [t for t in state.values() if isinstance(t, torch.Tensor)] if isinstance(state, dict) else None
        if tensors is None or not all(t.is_floating_point() and torch.isfinite(t).all() for t in tensors):
            raise InputError(f"{path}: optimizer state {_short(key)} is malformed or not finite "
                             f"(expected finite float tensors; {WRITTEN_BY_US})")


def _check_rng(rng, path) -> None:
    """The saved ``torch.get_rng_state()`` that ``--resume`` restores."""
    expected = torch.get_rng_state()
    if not (isinstance(rng, torch.Tensor) and rng.dtype == torch.uint8 and rng.shape == expected.shape):
        raise InputError(f"{path}: checkpoint field rng is not a torch CPU RNG state (expected a uint8 tensor "
                         f"of {expected.numel()} bytes; {WRITTEN_BY_US})")


def check_fields(payload: dict, path: str | Path) -> None:
    """:class:`InputError` when a field that the commands read has the wrong type or range."""
    for name, (test, expected) in FIELD_CHECKS.items():
        if name in payload and not test(payload[name]):
            raise InputError(f"{path}: checkpoint field {name} is {_short(payload[name])} "
                             f"(expected {expected}; {WRITTEN_BY_US})")
    if "train_config" in payload:
        _check_train_config(payload["train_config"], path)
    if "optimizer" in payload:
        _check_optimizer(payload["optimizer"], path)
    if "rng" in payload:
        _check_rng(payload["rng"], path)


def config_from_checkpoint(payload: dict, path: str | Path) -> CVAEConfig:
    """The checkpoint's :class:`CVAEConfig`, every field checked for type and range."""
    fields = {f.name: f for f in dataclasses.fields(CVAEConfig)}
    config = payload.get("config")
    if not isinstance(config, dict):
        raise InputError(f"{path}: checkpoint has no config dictionary (expected the fields {sorted(fields)})")
    for key, value in config.items():
        if key not in fields:
            raise InputError(f"{path}: config has unknown field {_short(key)} (expected only {sorted(fields)})")
        default = fields[key].default
        if isinstance(default, bool):
            ok, expected = isinstance(value, bool), "true or false"
        elif _is_int(default):
            ok, expected = _is_int(value) and 1 <= value <= MAX_SIZE, f"an integer in 1..{MAX_SIZE}"
        elif isinstance(default, float):
            ok, expected = _is_number(value) and math.isfinite(value), "a finite number"
        elif key == "robot_future":
            ok, expected = value in ROBOT_FUTURES, " or ".join(ROBOT_FUTURES)
        else:
            ok, expected = default is None or isinstance(value, type(default)), type(default).__name__
        if not ok:
            raise InputError(f"{path}: config field {key} is {_short(value)} (expected {expected})")
    result = CVAEConfig(**config)
    latent_values = result.latent_classes ** min(result.latent_vars, 64)
    if latent_values > MAX_LATENT_VALUES:
        raise InputError(f"{path}: config latent_classes ** latent_vars is {result.latent_classes}^{result.latent_vars} "
                         f"(expected at most {MAX_LATENT_VALUES} latent values)")
    return result


def _dtype(dtype: torch.dtype) -> str:
    return str(dtype).removeprefix("torch.")


def check_tensors(state: dict, expected: dict, path: str | Path, label=lambda name: f"tensor {name}") -> None:
    """Each tensor of ``state`` has the dtype and shape of ``expected``'s, finite values and, for the
    standardisation stds and calibration, positive ones. Messages name ``path`` and ``label(name)``."""
    for name, tensor in state.items():
        want, what = expected[name], label(name)
        if not isinstance(tensor, torch.Tensor):
            raise InputError(f"{path}: {what} is {_short(tensor)} (expected a tensor)")
        if tensor.layout != torch.strided:
            raise InputError(f"{path}: {what} is stored as {tensor.layout} (expected a dense tensor)")
        if tensor.dtype != want.dtype:
            raise InputError(f"{path}: {what} has dtype {_dtype(tensor.dtype)} (expected {_dtype(want.dtype)})")
        if tuple(tensor.shape) != tuple(want.shape):
            raise InputError(f"{path}: {what} has shape {list(tensor.shape)} (expected {list(want.shape)})")
        if tensor.is_floating_point() and not torch.isfinite(tensor).all():
            raise InputError(f"{path}: {what} has NaN or infinite values (expected finite weights)")
        if name in POSITIVE_BUFFERS and tensor.numel() and not (tensor > 0).all():
            raise InputError(f"{path}: {what} has a value {tensor.min().item():g} <= 0 "
                             f"(expected {POSITIVE_BUFFERS[name]})")


def model_from_checkpoint(payload: dict, path: str | Path) -> CVAE | Mixture:
    """Build the model a checkpoint describes (a :class:`Mixture` where it has ``mixture``) and load
    its weights, checking every tensor."""
    model = _cvae_from_checkpoint(payload, path)
    if "mixture" not in payload:
        return model
    mixture = payload["mixture"]
    if payload["version"] < MIXTURE_VERSION:
        raise InputError(f"{path}: a version {payload['version']} mixture, whose weights are outside the checkpoint's "
                         f"SHA-256 (expected version {MIXTURE_VERSION} or later: mix it again with `trafficweaving mix`)")
    components = mixture.get("components") if isinstance(mixture, dict) else None
    if not (_is_list_of(components, lambda c: isinstance(c, dict)) and components):
        raise InputError(f"{path}: checkpoint field mixture is not a mixture (expected weights and components, a "
                         f"config and state_dict for each component after the first; {WRITTEN_BY_US})")
    weights = _mixture_weights(mixture, "weights", len(components) + 1, path)
    person = _mixture_weights(mixture, "person_weights", len(components) + 1, path) if "person_weights" in mixture else None
    others = [_cvae_from_checkpoint({**c, "version": payload["version"]}, f"{path} (mixture component {k + 2})")
              for k, c in enumerate(components)]
    try:
        return Mixture([model, *others], weights, person).eval()
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None


def _mixture_weights(mixture: dict, key: str, count: int, path: str | Path) -> list[float]:
    """A mixture's ``weights`` (positive) or ``person_weights`` (non-negative, not all zero), checked:
    a float64 tensor of ``count``, finite, normalisable (:func:`~.mixture.normalised`)."""
    value, positive = mixture.get(key), key == "weights"
    if not (isinstance(value, torch.Tensor) and value.dtype == torch.float64 and value.layout == torch.strided
            and normalised(value, count, positive) is not None):
        shown = value.tolist() if isinstance(value, torch.Tensor) and value.numel() <= 16 else value
        raise InputError(f"{path}: checkpoint field mixture.{key} is {_short(shown)} (expected a float64 tensor of "
                         f"{count} finite {'positive' if positive else 'non-negative'} weights, "
                         f"{'' if positive else 'not all zero, '}with a finite sum; {WRITTEN_BY_US})")
    return value.tolist()


def _cvae_from_checkpoint(payload: dict, path: str | Path) -> CVAE:
    """The CVAE of a checkpoint's (or mixture component's) ``config`` and ``state_dict``."""
    model = CVAE(config_from_checkpoint(payload, path))
    expected = model.state_dict()
    state = payload.get("state_dict")
    if not isinstance(state, dict) or not all(isinstance(k, str) for k in state):
        raise InputError(f"{path}: checkpoint has no state_dict dictionary (expected tensors by parameter name)")
    missing, extra = set(expected) - set(state), set(state) - set(expected)
    if missing or extra:
        name = sorted(missing or extra)[0]
        raise InputError(f"{path}: checkpoint {'lacks' if missing else 'has unexpected'} tensor {name} (expected a {model.config.name} model)")
    state = upgrade_state(state, payload["version"])
    check_tensors(state, expected, path)
    optimizer = payload.get("optimizer")
    if isinstance(optimizer, dict) and isinstance(optimizer.get("param_groups"), list):
        trainable = (payload.get("train_config") or {}).get("trainable", "all")
        parts = TRAINABLE.get(trainable) if isinstance(trainable, str) else None
        count = sum(len(g.get("params", ())) for g in optimizer["param_groups"])
        params = sum(1 for name, _ in model.named_parameters() if parts is None or name.split(".")[0] in parts)
        if count != params:
            raise InputError(f"{path}: optimizer state covers {count} parameters (expected the model's {params} "
                             f"trainable ones)")
    model.load_state_dict(state)
    return model.eval()


def upgrade_state(state: dict, version: int) -> dict:
    """The ``state_dict`` of a ``version`` checkpoint as this version's model reads it, with the
    same density: before version 4 the output scale was one number (both directions); in version 2
    it also multiplied the hold widths, so a version-2 hold model gets ``log s + log output_scale``
    as its hold log-widths (the widths it had)."""
    scale = state.get("output_scale")
    if version >= 4 or not isinstance(scale, torch.Tensor) or scale.dim() != 0:
        return state
    upgraded = state | {"output_scale": scale.expand(2).clone()}
    if version == 2 and "hold.log_sigma" in state and scale.is_floating_point() and scale > 0:  # else refused below
        log_sigma = state["hold.log_sigma"].clamp(math.log(HOLD_MIN_SIGMA), LOG_SIGMA_CLIP)
        upgraded["hold.log_sigma"] = log_sigma + torch.log(scale)
    return upgraded


def _read(path: str | Path) -> tuple[dict, CVAE | Mixture]:
    """The validated checkpoint dictionary and its model (see :func:`read_checkpoint`)."""
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder (expected {EXPECTED})")
    if not path.is_file():
        raise InputError(f"{path}: no such file (expected {EXPECTED})")
    try:
        with warnings.catch_warnings():  # e.g. torch's about another pickle protocol: the error below says it
            warnings.simplefilter("ignore")
            payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # any unreadable file is the user's input error here
        raise InputError(f"{path}: not a readable checkpoint ({type(exc).__name__}; expected {EXPECTED})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise InputError(f"{path}: not a trafficweaving model checkpoint (expected {EXPECTED})")
    version = payload.get("version")
    if version not in READABLE_VERSIONS or isinstance(version, bool):
        raise InputError(f"{path}: checkpoint version {_short(version)} (expected version {', '.join(map(str, READABLE_VERSIONS))}, which carry "
                         f"a SHA-256 of their tensors; version 1 files are no longer read)")
    stored = payload.get(HASH_FIELD)
    if not (isinstance(stored, str) and re.fullmatch(r"[0-9a-f]{64}", stored)):
        raise InputError(f"{path}: checkpoint has no valid {HASH_FIELD} ({WRITTEN_BY_US})")
    try:
        actual = tensor_digest(payload)
    except Exception as exc:  # an exotic tensor that torch.load accepted but cannot be hashed
        raise InputError(f"{path}: tensor data cannot be read ({type(exc).__name__}; {WRITTEN_BY_US})") from None
    if actual != stored:
        raise InputError(f"{path}: tensor data does not match the checkpoint's SHA-256 "
                         f"(the file is corrupted or was edited; {WRITTEN_BY_US})")
    check_fields(payload, path)
    return payload, model_from_checkpoint(payload, path)


def read_checkpoint(path: str | Path) -> dict:
    """The validated checkpoint dictionary; :class:`InputError` naming the file when it is not one,
    is corrupted (tensor digest), or holds a model or field that would fail later."""
    return _read(path)[0]


def load_checkpoint(path: str | Path) -> tuple[CVAE | Mixture, dict]:
    """The model of a checkpoint file (evaluation mode) and the checkpoint dictionary."""
    payload, model = _read(path)
    return model, payload
