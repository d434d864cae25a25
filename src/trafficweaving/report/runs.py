"""The inputs of ``trafficweaving report``: a ``simulate`` run folder, an ``evaluate --json`` or a
``realism --json`` file, recognised by what it holds and read with every field it uses checked, so
that a wrong or damaged input is refused in one line naming its file before anything is written."""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

from ..data.trials import _short
from ..errors import InputError

EXPECTED = "expected a simulate run folder holding summary.json, an evaluate --json or a realism --json file"
SIMULATE_KEYS = ("episodes", "robot", "human", "seed", "score", "success_rate")
"""Keys that mark a simulate summary (``summary.json``, or ``simulate --json`` saved to a file)."""
EVALUATE_KEYS = ("instances", "nll_exact", "nll_is", "nll_naive", "model")
"""Keys that mark an ``evaluate --json`` output (``train --json`` has the first four, not ``model``)."""
REALISM_KEYS = ("realism", "groups", "human", "rollouts", "swap_rate", "off_road_rate", "collision_rate")
"""Keys that mark a ``realism --json`` output."""
WRITTEN_BY = {"simulate": "simulate's summary.json", "evaluate": "evaluate --json", "realism": "realism --json"}
MAX_JSON_BYTES = 16 * 2**20
"""Largest JSON file read (the outputs read are a few kB)."""

_MISSING = object()


def _is_number(value) -> bool:
    return type(value) in (int, float) and math.isfinite(value)


CHECKS = {
    "number": (_is_number, "a finite number"),
    "number or null": (lambda v: v is None or _is_number(v), "a finite number or null"),
    "count": (lambda v: type(v) is int and v >= 0, "an integer >= 0"),
    "count or null": (lambda v: v is None or type(v) is int and v >= 0, "an integer >= 0 or null"),
    "text": (lambda v: isinstance(v, str), "a string"),
    "object": (lambda v: isinstance(v, dict), "an object"),
    "object or null": (lambda v: v is None or isinstance(v, dict), "an object or null"),
    "interval or null": (lambda v: v is None or isinstance(v, list) and len(v) == 2 and all(map(_is_number, v)),
                         "[low, high] or null"),
    "budget or null": (lambda v: v is None or isinstance(v, list) and len(v) == 3
                       and all(type(n) is int and n > 0 for n in v), "[first_stage_samples, finalists, "
                       "second_stage_samples] or null"),
}
"""What a field read may hold: its test and how a message names it."""


@dataclass(frozen=True)
class Run:
    """One input: its ``path`` as given, ``kind`` (simulate, evaluate or realism), ``label``, the
    JSON object read (``data``) and the file it came from (``source``, for messages)."""

    path: str
    kind: str
    label: str
    data: dict
    source: str

    def get(self, *keys: str, check: str, default=_MISSING):
        """The value at ``keys`` (nested objects), checked by :data:`CHECKS`; ``default`` when a
        key is missing and a default is given, else InputError naming the file and the key."""
        value, name = self.data, ".".join(keys)
        for depth, key in enumerate(keys):
            if not isinstance(value, dict):
                raise InputError(f"{self.source}: {'.'.join(keys[:depth])} is {_short(value)} (expected an object)")
            value = value.get(key, _MISSING)
            if value is _MISSING:
                break
        if value is _MISSING:
            if default is not _MISSING:
                return default
            rebuild = "; simulate into the folder again to rebuild it" if self.kind == "simulate" else ""
            raise InputError(f"{self.source}: no {name} (expected {WRITTEN_BY[self.kind]} of this release{rebuild})")
        test, expected = CHECKS[check]
        if not test(value):
            raise InputError(f"{self.source}: {name} is {_short(value)} (expected {expected})")
        return value


def _load_json(path: Path) -> dict:
    """The JSON object in ``path`` (strict: no NaN or infinities); InputError naming the file."""
    def refuse(name: str):
        raise InputError(f"{path}: {name} is not a number JSON allows ({EXPECTED})")

    try:
        if path.stat().st_size > MAX_JSON_BYTES:
            raise InputError(f"{path}: over {MAX_JSON_BYTES // 2**20} MiB ({EXPECTED})")
        data = json.loads(path.read_bytes().decode(), parse_constant=refuse)
    except OSError as exc:
        raise InputError(f"{path}: cannot be read ({exc.strerror or exc}; {EXPECTED})") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not UTF-8 text ({EXPECTED})") from None
    except json.JSONDecodeError as exc:
        where = f"line {exc.lineno} column {exc.colno}"
        raise InputError(f"{path}: not valid JSON ({where}: {exc.msg}; {EXPECTED})") from None
    except RecursionError:
        raise InputError(f"{path}: JSON nested too deeply ({EXPECTED})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: a JSON {type(data).__name__}, not an object ({EXPECTED})")
    return data


def read_run(path: str | os.PathLike) -> Run:
    """The run at ``path`` (module docstring), its label taken from what it records: robot,
    human, seed and episodes of a simulate run, the model of an evaluate file, the agent of a
    realism file (else the file's stem). InputError naming the path for anything else."""
    if not isinstance(path, (str, os.PathLike)) or not os.fspath(path).strip():
        raise InputError(f"run {_short(path)} is not a path ({EXPECTED})")
    shown = os.fspath(path)
    source = Path(shown) / "summary.json" if Path(shown).is_dir() else Path(shown)
    if not source.is_file():
        what = ("a folder without summary.json" if Path(shown).is_dir() else
                "not a regular file" if Path(shown).exists() else "no such file or folder")
        raise InputError(f"{shown}: {what} ({EXPECTED})")
    data = _load_json(source)
    kind = next((k for k, keys in (("simulate", SIMULATE_KEYS), ("realism", REALISM_KEYS), ("evaluate", EVALUATE_KEYS))
                 if all(key in data for key in keys)), None)
    if kind is None:
        raise InputError(f"{source}: a JSON object without the keys of simulate, evaluate or realism ({EXPECTED})")
    run = Run(shown, kind, "", data, str(source))
    if kind == "simulate":
        label = (f"{run.get('robot', check='text')} vs {run.get('human', check='text')}, seed "
                 f"{run.get('seed', check='count')}, {run.get('episodes', check='count')} episodes")
    else:
        named = data.get("model" if kind == "evaluate" else "human")
        label = named if isinstance(named, str) and named else Path(shown).stem
    return Run(shown, kind, label, data, str(source))
