"""Where browser trials are written: one Parquet file per trial, in the dataset format.

Trial ``n`` of a folder is ``drive_00000n.parquet`` (numbers continue after the highest one in
the folder, so a folder collects the drives of many sessions, and the rooms driving at once never
share one); the file is written atomically
(:meth:`~trafficweaving.data.trials.TrialSet.write_parquet`), so a reader never sees half a trial.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from ..atomic import check_output_folder
from ..data.trials import TrialSet, _short, load_trials
from ..errors import InputError
from ..scenario import DT

FILE_PATTERN = re.compile(r"drive_(\d{6,})\.parquet")
"""Names of recorded trials: ``drive_`` and the trial number."""


class Recorder:
    """Writes the trials of ``folder`` (created on the first write); InputError if it is a file."""

    def __init__(self, folder: str | os.PathLike):
        self.folder = check_output_folder(folder, "--out")
        self.last_reserved = 0

    def next_number(self) -> int:
        """The number of the next trial: one more than the highest recorded in the folder (1 first)."""
        numbers = [int(m.group(1)) for p in (self.folder.iterdir() if self.folder.is_dir() else [])
                   if (m := FILE_PATTERN.fullmatch(p.name))]
        return max(numbers, default=0) + 1

    def reserve(self) -> int:
        """The number of a new trial, never one this recorder handed out before (rooms that start
        trials at once get different numbers before either is written)."""
        self.last_reserved = max(self.next_number(), self.last_reserved + 1)
        return self.last_reserved

    def path(self, number: int) -> Path:
        """The file of trial ``number``."""
        return self.folder / f"drive_{number:06d}.parquet"

    def write(self, trials: TrialSet, number: int) -> Path:
        """Write trial ``number``'s record atomically; returns its path."""
        path = self.path(number)
        trials.write_parquet(path)
        return path


def recorded_files(folder: str | os.PathLike) -> list[Path]:
    """The recorded trials of ``folder`` in trial order; InputError when it holds none."""
    folder = Path(folder)
    files = sorted((p for p in folder.iterdir() if FILE_PATTERN.fullmatch(p.name)),
                   key=lambda p: int(FILE_PATTERN.fullmatch(p.name).group(1))) if folder.is_dir() else []
    if not files:
        raise InputError(f"{folder}: no recorded trials (expected drive_NNNNNN.parquet files written by "
                         f"trafficweaving drive)")
    return files


def check_recording(trials: TrialSet) -> TrialSet:
    """``trials`` (one file of a ``trafficweaving drive`` folder, read with its ``source_path``) if
    it holds what the study's progress reads: one trial at the scenario's ``DT``, and a ``drive``
    record (absent from recordings made before it) whose ``mode``, ``started_at`` and ``reason``
    are strings or null and whose ``room`` is null or an object with ``session`` (a string or
    null), ``participants`` (a list or null) and ``round`` (an integer ≥ 0 or null). InputError
    naming the file otherwise."""
    def refuse(name, key: str, value, expected: str):
        raise InputError(f"{name}: {key} {_short(value)} in the drive record (expected {expected})")

    name = trials.source_path or "a recording"
    if len(trials) != 1:
        raise InputError(f"{name}: {len(trials)} trials (expected the one trial trafficweaving drive records per file)")
    if trials.dt != DT:
        raise InputError(f"{name}: time step {trials.dt:g} s (expected {DT:g} s, as trafficweaving drive records)")
    record = trials.metadata.get("drive", {})
    if not isinstance(record, dict):
        refuse(name, "drive", record, "an object")
    for key in ("mode", "started_at", "reason"):
        if not isinstance(record.get(key), (str, type(None))):
            refuse(name, key, record[key], "a string or null")
    room = record.get("room")
    if not isinstance(room, (dict, type(None))):
        refuse(name, "room", room, "an object or null")
    room = room or {}
    if not isinstance(room.get("session"), (str, type(None))):
        refuse(name, "room.session", room["session"], "a string or null")
    if not isinstance(room.get("participants"), (list, type(None))):
        refuse(name, "room.participants", room["participants"], "a list or null")
    if not (room.get("round") is None or type(room["round"]) is int and room["round"] >= 0):
        refuse(name, "room.round", room["round"], "an integer >= 0 or null")
    return trials


def load_recordings(folder: str | os.PathLike) -> list[TrialSet]:
    """Every recorded trial of ``folder`` (:func:`recorded_files`), each checked by
    :func:`~trafficweaving.data.trials.load_trials` and :func:`check_recording`."""
    return [check_recording(load_trials(path)) for path in recorded_files(folder)]
