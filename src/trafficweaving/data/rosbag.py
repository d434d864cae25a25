"""Import of the authors' raw human–human recordings (ROS1 bags), sanitised as they did.

A bag is named ``<HH:MM:SS>_<v>_<swap>_<dv>_<tco>_<round>.bag`` and lies in a folder named after
the pair of drivers (``01``: drivers 2 and 3). Topics ``/object_state/1`` (car 1, agent 0) and
``/object_state/2`` (car 2, agent 1) carry ``vtd_interface/rdb_object_state`` messages, read with
the message definitions stored in the bag (no ROS install needed).

Pipeline per bag (the authors' ``extract_from_and_validate_bag`` and
``sanitize_traffic_weaving_dataframe``):

1. the bag readable (a file that is not a ROS1 bag, truncated or corrupt, is rejected as
   ``unreadable``; the other bags still import); both topics present, all values finite; no gap
   above ``DT`` between consecutive ``simTime`` stamps of a topic;
2. every field linearly interpolated onto ``t0, t0 + DT, ... < tf`` (``t0``: the later first stamp,
   ``tf``: the earlier last stamp);
3. time consistency: positions and speeds must agree with integrated speeds and accelerations;
4. kept from the first step where both cars are behind ``RECORD_START_X`` to before the first step
   where both are past ``RECORD_END_X``; every kept value within :data:`.trials.PLAUSIBLE_RANGES`
   (the limits the human-in-the-loop importer applies too);
5. :func:`scenario.check_validity`, then cut before the first car reaches ``CUTOFF_X``.

Each rejected bag is counted under a reason in :data:`REJECT_REASONS`.
"""

from __future__ import annotations

import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader
from tqdm import tqdm

from ..errors import InputError
from ..scenario import (
    DELTA_V_VALUES,
    DT,
    MIN_TRIAL_STEPS,
    RECORD_END_X,
    RECORD_START_X,
    STATE_NAMES,
    VALIDITY_REASONS,
    check_validity,
    lane_of,
)
from .trials import TrialSet, first_implausible

TOPICS = ("/object_state/1", "/object_state/2")
"""Topic of each agent (car 1, car 2)."""
FILENAME = re.compile(r"(\d\d:\d\d:\d\d)_(\d+)_([01])_(-?\d+)_(\d+)_(\d+)\.bag")
"""``<HH:MM:SS>_<v>_<swap>_<dv>_<tco>_<round>.bag``."""
CONSISTENCY_LIMIT = 1.0
"""Largest allowed std of ``x - DT·cumsum(xd)`` and ``xd - DT·cumsum(xdd)`` (authors' check), m and m/s."""
REJECT_REASONS = (
    "bad_filename",
    "unreadable",
    "missing_topic",
    "timestamp_gap",
    "non_finite",
    "too_short",
    "inconsistent",
    "start_not_recorded",
    "implausible",
    *VALIDITY_REASONS[1:],
)
"""Why a bag can be rejected, in pipeline order. ``unreadable``: not a ROS1 bag (random bytes,
empty, truncated, corrupt) or messages of another type; ``missing_topic``: a topic with fewer than 2
messages; ``too_short``: a ``DT`` grid, or a valid trial once cut, of fewer than
``MIN_TRIAL_STEPS`` steps; ``start_not_recorded``: no step with both cars behind
``RECORD_START_X``; ``implausible``: a kept value outside :data:`.trials.PLAUSIBLE_RANGES`; then
the :data:`scenario.VALIDITY_REASONS`."""


@dataclass
class RosbagImport:
    """Result of :func:`read_rosbags`: the accepted ``trials``, the number of bags ``rejected`` per
    reason (only reasons that occurred), and every bag's outcome ``files`` as ``(path relative to
    the directory, "ok" or the reason)``, in the order read."""

    trials: TrialSet
    rejected: dict[str, int]
    files: list[tuple[str, str]]


class BagRejected(Exception):
    """A bag that does not make a trial, for ``reason`` (one of ``REJECT_REASONS``)."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def read_rosbags(directory: str | Path) -> RosbagImport:
    """Import every ``*.bag`` below ``directory`` (recursively, in sorted order).

    All agents get role ``human``. ``ic_dv`` is ``v_left - v_right`` at the first kept step,
    snapped to the nearest of ``DELTA_V_VALUES``; ``ic_tco`` is the file name's crossover time
    (NaN when ``ic_dv`` is 0). Drivers ``2p`` and ``2p + 1`` come from a numeric folder name ``p``
    (-1 otherwise).

    A bag that cannot be read or is not a valid trial is counted under its reason and skipped.
    Raises :class:`InputError` when ``directory`` is not a directory, holds no bags, or none of its
    bags is a valid trial. The result's ``trials.source_path`` is ``directory``.
    """
    root = Path(directory)
    if not root.is_dir():
        raise InputError(f"{root}: no such directory (expected a folder of ROS1 .bag files)")
    paths = sorted(p for p in root.glob("**/*.bag") if p.is_file())
    if not paths:
        raise InputError(f"{root}: no .bag files found (expected ROS1 bags named <HH:MM:SS>_<v>_<swap>_<dv>_<tco>_<round>.bag)")

    files: list[tuple[str, str]] = []
    accepted = []  # (states [2, T, 6], tco, drivers, source)
    for path in tqdm(paths, desc="bags", unit="bag", disable=None):
        source = path.relative_to(root).as_posix()
        try:
            tco, drivers = _parse_name(path)
            states = sanitise(_read_bag(path))
        except BagRejected as rejected:
            files.append((source, rejected.reason))
            continue
        files.append((source, "ok"))
        accepted.append((states, tco, drivers, source))

    counts = Counter(outcome for _, outcome in files if outcome != "ok")
    rejected = {reason: counts[reason] for reason in REJECT_REASONS if counts[reason]}
    if not accepted:
        summary = ", ".join(f"{reason} {count}" for reason, count in rejected.items())
        raise InputError(f"{root}: no valid trials among {len(paths)} bags (rejected: {summary})")
    trials = _trial_set(accepted)
    trials.source_path = root
    return RosbagImport(trials=trials, rejected=rejected, files=files)


def sanitise(states: np.ndarray) -> np.ndarray:
    """Trim and check one recording interpolated on the ``DT`` grid, ``[2, T, 6]`` (car, step,
    ``STATE_NAMES``); returns the kept steps ``[2, cut, 6]`` or raises :class:`BagRejected`."""
    x = states[:, :, 0]
    started = (x < RECORD_START_X).all(axis=0)
    if not started.any():
        raise BagRejected("start_not_recorded")
    states = states[:, int(np.argmax(started)):]
    ended = (states[:, :, 0] > RECORD_END_X).all(axis=0)
    if ended.any():
        states = states[:, : int(np.argmax(ended))]
    if first_implausible(states) is not None:
        raise BagRejected("implausible")
    reason, cut = check_validity(states[None], np.array([states.shape[1]]))
    if reason[0]:
        raise BagRejected(VALIDITY_REASONS[reason[0]])
    if cut[0] < MIN_TRIAL_STEPS:
        raise BagRejected("too_short")
    return states[:, : cut[0]]


def _parse_name(path: Path) -> tuple[float, tuple[int, int]]:
    """The crossover time (s) from the file name and the two drivers' ids from the folder name."""
    match = FILENAME.fullmatch(path.name)
    if not match:
        raise BagRejected("bad_filename")
    pair = path.parent.name
    drivers = (2 * int(pair), 2 * int(pair) + 1) if pair.isdecimal() else (-1, -1)
    return float(match.group(5)), drivers


def _read_bag(path: Path) -> np.ndarray:
    """Both cars interpolated on the ``DT`` grid of ``simTime``, ``[2, T, 6]``, time-consistent."""
    columns: dict[str, list[tuple[float, ...]]] = {topic: [] for topic in TOPICS}
    try:
        with AnyReader([path]) as reader:
            connections = [c for c in reader.connections if c.topic in columns]
            for connection, _, raw in reader.messages(connections=connections):
                m = reader.deserialize(raw, connection.msgtype)
                columns[connection.topic].append(
                    (m.simTime, m.base.pos.x, m.base.pos.y, m.ext.speed.x, m.ext.speed.y, m.ext.accel.x, m.ext.accel.y)
                )
    except Exception:  # noqa: BLE001 - a corrupt bag makes the reader fail in any way (UnicodeDecodeError, struct.error, ...)
        raise BagRejected("unreadable") from None
    if any(len(rows) < 2 for rows in columns.values()):
        raise BagRejected("missing_topic")

    tracks = [np.array(sorted(columns[topic])) for topic in TOPICS]  # each [n, 7], sorted by simTime
    if not all(np.isfinite(track).all() for track in tracks):
        raise BagRejected("non_finite")
    if max(np.diff(track[:, 0]).max() for track in tracks) > DT:
        raise BagRejected("timestamp_gap")
    t0 = max(track[0, 0] for track in tracks)
    tf = min(track[-1, 0] for track in tracks)
    grid = np.arange(t0, tf, DT)
    if len(grid) < MIN_TRIAL_STEPS:
        raise BagRejected("too_short")
    states = np.stack(
        [np.stack([np.interp(grid, track[:, 0], track[:, k + 1]) for k in range(len(STATE_NAMES))], axis=1)
         for track in tracks]
    )  # [2, T, 6]

    x, xd, xdd = states[:, :, 0], states[:, :, 2], states[:, :, 4]
    with np.errstate(over="ignore", invalid="ignore"):  # absurd values give inf/NaN: inconsistent
        drift = np.concatenate([x - DT * np.cumsum(xd, axis=1), xd - DT * np.cumsum(xdd, axis=1)])  # [4, T]
        spread = drift.std(axis=1, ddof=1)  # ddof=1: pandas' std, as the authors
    if not (spread < CONSISTENCY_LIMIT).all():
        raise BagRejected("inconsistent")
    return states


def _trial_set(accepted: list[tuple[np.ndarray, float, tuple[int, int], str]]) -> TrialSet:
    """Pack accepted recordings ``(states [2, T, 6], tco s, drivers, source)`` into a TrialSet."""
    n = len(accepted)
    lengths = np.array([a[0].shape[1] for a in accepted], dtype=np.int64)
    states = np.full((n, 2, int(lengths.max()), len(STATE_NAMES)), np.nan)
    for i, (s, *_) in enumerate(accepted):
        states[i, :, : s.shape[1]] = s

    y0, xd0 = states[:, :, 0, 1], states[:, :, 0, 2]  # [n, 2]
    left = np.argmax(y0, axis=1)
    rows = np.arange(n)
    dv = xd0[rows, left] - xd0[rows, 1 - left]
    values = np.array(DELTA_V_VALUES)
    ic_dv = values[np.abs(dv[:, None] - values[None, :]).argmin(axis=1)]
    tco = np.array([a[1] for a in accepted])
    return TrialSet(
        states=states,
        lengths=lengths,
        trial_ids=np.arange(n, dtype=np.int32),
        roles=np.full((n, 2), "human"),
        start_lanes=lane_of(y0),
        drivers=np.array([a[2] for a in accepted], dtype=np.int32),
        ic_dv=ic_dv,
        ic_tco=np.where(ic_dv == 0, np.nan, tco),
        sources=np.array([a[3] for a in accepted]),
        dt=DT,
        metadata={"importer": "rosbag"},
    )
