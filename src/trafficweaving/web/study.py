"""The study's data-collection protocol for a pair of people in a human–human room (paper §V-A),
and the progress of a folder of recordings.

A pair plays rounds of the 18 initial conditions (:func:`~trafficweaving.scenario.study_initial_conditions`),
each round in its own random order (drawn from the room's seed), and the two people swap cars
every round: in even rounds the room's first page (seat 0) drives car A, in odd rounds car B. A
trial advances the schedule only when it completed (ended by the scenario's rules,
:data:`~.trial.COMPLETED`) and was recorded; an aborted or too short trial is played again.

Every recording of a room carries ``room`` in its ``drive`` record (:meth:`StudySchedule.record`
and :class:`~.room.Room`): the ``session`` id (one per room, the pair's session), the
``participants`` per seat, the seat driving each car, and the trial's ``round`` and ``position``
in the round (null when the page chose the initial condition itself).
"""

from __future__ import annotations

import os
from collections import defaultdict

import numpy as np

from ..data.stats import format_table1, format_table1_test, table1, table1_test
from ..data.trials import TrialSet
from ..scenario import study_initial_conditions
from .recording import load_recordings
from .trial import COMPLETED

ROUND = len(study_initial_conditions())
"""Trials per round: every initial condition once."""


class StudySchedule:
    """Where a pair is in the protocol: ``done`` completed trials of the schedule so far; the
    order of round ``r`` is a permutation drawn from ``seed`` and ``r``."""

    def __init__(self, seed: int):
        self.seed = seed
        self.done = 0

    @property
    def round(self) -> int:
        """The present round, 0 first."""
        return self.done // ROUND

    @property
    def position(self) -> int:
        """The next trial's place in the present round, 0..17."""
        return self.done % ROUND

    def order(self, round_: int) -> np.ndarray:
        """Round ``round_``'s initial conditions, ``[18]`` indices in play order."""
        return np.random.default_rng([self.seed, round_]).permutation(ROUND)

    def next_initial_condition(self) -> int:
        """The initial condition the protocol plays next."""
        return int(self.order(self.round)[self.position])

    def seats(self) -> tuple[int, int]:
        """The seat driving car A and the one driving car B in the present round (swapped every round)."""
        return (0, 1) if self.round % 2 == 0 else (1, 0)

    def advance(self) -> None:
        """A trial of the schedule completed: move to the next."""
        self.done += 1

    def progress(self) -> dict:
        """``round``, ``position``, ``done``, ``next_initial_condition``, ``seats`` (JSON-ready)."""
        return {"round": self.round, "position": self.position, "done": self.done,
                "next_initial_condition": self.next_initial_condition(), "seats": list(self.seats())}


def is_completed(record: dict) -> bool:
    """Whether a recording's ``drive`` record ended by the scenario's rules (not aborted)."""
    return record.get("reason") in COMPLETED


def folder_progress(recordings: list[TrialSet]) -> dict:
    """The progress of a study from its recordings (one trial each, with a ``drive`` record):
    ``files``, ``completed``, ``aborted`` (stopped by a person, a page gone away or a server
    error), ``pairs`` (one row per room session: ``session``, ``mode``, ``participants``,
    ``trials``, ``completed``, ``aborted``, ``rounds`` (completed protocol rounds), ``first`` and
    ``last`` start times), and Table I so far (``table1``, ``table1_counts``: the completed
    human–human trials, :func:`~trafficweaving.data.stats.table1`). Recordings without a room
    (made before rooms) form the session ``null``."""
    sessions: dict = defaultdict(list)
    for trials in recordings:
        record = trials.metadata.get("drive", {})
        sessions[(record.get("room") or {}).get("session")].append(record)
    pairs = []
    for session, records in sessions.items():
        completed = [r for r in records if is_completed(r)]
        on_schedule = [r for r in completed if (r.get("room") or {}).get("round") is not None]
        participants = (records[-1].get("room") or {}).get("participants")
        starts = [r.get("started_at") or "" for r in records]
        pairs.append({"session": session, "mode": records[-1].get("mode"), "participants": participants,
                      "trials": len(records), "completed": len(completed), "aborted": len(records) - len(completed),
                      "rounds": len(on_schedule) // ROUND, "first": min(starts), "last": max(starts)})
    pairs.sort(key=lambda row: row["first"])
    everything = TrialSet.concatenate(recordings)
    human_human = np.array([is_completed(t.metadata.get("drive", {})) and all(role == "human" for role in t.roles[0])
                            for t in recordings])
    t1 = table1(everything.subset(human_human))
    completed = sum(row["completed"] for row in pairs)
    return {"files": len(recordings), "completed": completed, "aborted": len(recordings) - completed,
            "human_human_completed": int(human_human.sum()), "pairs": pairs,
            "table1": t1["table1"], "table1_counts": t1["counts"]}


def format_progress(progress: dict) -> str:
    """The pairs' rows as a text table."""
    lines = [f"{'session':<14} {'mode':<12} {'participants':<14} {'trials':>6} {'completed':>9} {'aborted':>7} "
             f"{'rounds':>6}  last trial"]
    for row in progress["pairs"]:
        people = "—" if not row["participants"] else ",".join("?" if p is None else str(p)
                                                               for p in row["participants"])
        lines.append(f"{row['session'] or '(no room)':<14} {row['mode'] or '—':<12} {people:<14} {row['trials']:>6} "
                     f"{row['completed']:>9} {row['aborted']:>7} {row['rounds']:>6}  {row['last'] or '—'}")
    return "\n".join(lines)


def study_stats(folder: str | os.PathLike) -> tuple[dict, str]:
    """``stats DIR``: the progress of the study recorded in ``folder`` (``trafficweaving drive``
    recordings): :func:`folder_progress` with Table I's test against the paper
    (``table1_vs_paper``, :func:`~trafficweaving.data.stats.table1_test`). Returns the ``--json``
    payload (``folder``, then the progress) and the text."""
    progress = folder_progress(load_recordings(folder))
    progress["table1_vs_paper"] = table1_test(progress["table1"], progress["table1_counts"])
    text = [f"{folder}: trials recorded {progress['files']}, completed {progress['completed']}, aborted "
            f"{progress['aborted']} (stopped, a page gone, a server error)", format_progress(progress),
            f"Table I so far (completed human-human trials: {progress['human_human_completed']}):",
            format_table1(progress["table1"], progress["table1_counts"]), format_table1_test(progress["table1_vs_paper"])]
    return {"folder": str(folder), **progress}, "\n".join(text)
