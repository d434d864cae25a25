"""The trial data model and its Parquet storage.

A *trial* is one interaction of two cars (agents 0 and 1), sampled every ``DT`` seconds. On disk a
dataset is one Parquet file with **one row per agent per step**:

============  ========  ==========================================================================
column        type      meaning
============  ========  ==========================================================================
trial         int32     trial id, unique in the file
agent         int8      0 or 1, the car within the trial
step          int32     0, 1, ... T-1 (consecutive)
t             float64   time since the trial's first step, s (``step * DT``)
role          string    ``human`` or ``robot``
start_lane    string    ``left`` or ``right``: the lane the agent started in
ic_dv         float64   initial condition: ``Δv = v_left - v_right`` at the start, m/s (null: unknown)
ic_tco        float64   initial condition: crossover time, s (null: Δv = 0 or unknown)
driver        int32     id of the person (or simulated driver) driving; -1 for the robot/unknown
source        string    where the trial came from (``synthetic``, a file name, ...)
x, y          float64   position, m (``x`` 0 at the cutoff, ``y`` 0 at the left road edge)
xd, yd        float64   velocity, m/s
xdd, ydd      float64   acceleration, m/s²
============  ========  ==========================================================================

The file's schema metadata key ``trafficweaving`` holds a JSON object with ``format_version``,
``dt`` and free-form provenance (e.g. the generator's seed and parameters).

In memory a :class:`TrialSet` holds padded arrays ready for learning: ``states[n, 2, T_max, 6]``
(NaN past each trial's length) and ``lengths[n]``.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..atomic import atomic_write
from ..errors import InputError
from ..scenario import DT, MIN_TRIAL_STEPS, STATE_NAMES

FORMAT_VERSION = 1
ROLES = ("human", "robot")
LANES = ("left", "right")
METADATA_KEY = b"trafficweaving"

SCHEMA = pa.schema(
    [
        ("trial", pa.int32()),
        ("agent", pa.int8()),
        ("step", pa.int32()),
        ("t", pa.float64()),
        ("role", pa.string()),
        ("start_lane", pa.string()),
        ("ic_dv", pa.float64()),
        ("ic_tco", pa.float64()),
        ("driver", pa.int32()),
        ("source", pa.string()),
        *[(name, pa.float64()) for name in STATE_NAMES],
    ]
)


@dataclass
class TrialSet:
    """A batch of two-agent trials as padded arrays.

    ``states``: ``[n, 2, T_max, 6]`` float64 (trial, agent, step, ``STATE_NAMES``), NaN past a
    trial's length. ``lengths``: ``[n]`` steps per trial. Per-trial ``trial_ids[n]``, ``ic_dv[n]``
    (m/s, NaN unknown), ``ic_tco[n]`` (s, NaN for Δv = 0 or unknown), ``sources[n]``; per-agent
    ``roles[n, 2]``, ``start_lanes[n, 2]``, ``drivers[n, 2]`` (-1 unknown).
    """

    states: np.ndarray
    lengths: np.ndarray
    trial_ids: np.ndarray
    roles: np.ndarray
    start_lanes: np.ndarray
    drivers: np.ndarray
    ic_dv: np.ndarray
    ic_tco: np.ndarray
    sources: np.ndarray
    dt: float = DT
    metadata: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.lengths)

    def trajectory(self, i: int, agent: int) -> np.ndarray:
        """The recorded states of one agent, ``[lengths[i], 6]``."""
        return self.states[i, agent, : self.lengths[i]]

    def subset(self, index) -> "TrialSet":
        """The trials selected by ``index`` (boolean mask or integer indices), arrays trimmed to
        the longest selected trial."""
        lengths = self.lengths[index]
        t_max = int(lengths.max()) if len(lengths) else 0
        return TrialSet(
            states=self.states[index][:, :, :t_max],
            lengths=lengths,
            trial_ids=self.trial_ids[index],
            roles=self.roles[index],
            start_lanes=self.start_lanes[index],
            drivers=self.drivers[index],
            ic_dv=self.ic_dv[index],
            ic_tco=self.ic_tco[index],
            sources=self.sources[index],
            dt=self.dt,
            metadata=dict(self.metadata),
        )

    @staticmethod
    def concatenate(sets: list["TrialSet"]) -> "TrialSet":
        """Join trial sets (same ``dt``), renumbering trial ids 0..n-1."""
        if not sets:
            raise ValueError("no trial sets to concatenate")
        t_max = max(s.states.shape[2] for s in sets)
        states = np.concatenate(
            [np.pad(s.states, ((0, 0), (0, 0), (0, t_max - s.states.shape[2]), (0, 0)), constant_values=np.nan)
             for s in sets]
        )
        cat = lambda name: np.concatenate([getattr(s, name) for s in sets])  # noqa: E731
        return TrialSet(
            states=states,
            lengths=cat("lengths"),
            trial_ids=np.arange(sum(len(s) for s in sets), dtype=np.int32),
            roles=cat("roles"),
            start_lanes=cat("start_lanes"),
            drivers=cat("drivers"),
            ic_dv=cat("ic_dv"),
            ic_tco=cat("ic_tco"),
            sources=cat("sources"),
            dt=sets[0].dt,
            metadata=dict(sets[0].metadata),
        )

    # ------------------------------------------------------------------ storage
    def to_table(self) -> pa.Table:
        """The long (one row per agent per step) Arrow table of this set."""
        n = len(self)
        counts = np.repeat(self.lengths, 2)  # rows per (trial, agent)
        trial_of_row = np.repeat(np.repeat(np.arange(n), 2), counts)
        agent_of_row = np.repeat(np.tile(np.arange(2), n), counts)
        step_of_row = np.concatenate([np.arange(c) for c in counts]) if n else np.zeros(0, int)
        state_rows = self.states[trial_of_row, agent_of_row, step_of_row]  # [rows, 6]
        columns = {
            "trial": self.trial_ids[trial_of_row].astype(np.int32),
            "agent": agent_of_row.astype(np.int8),
            "step": step_of_row.astype(np.int32),
            "t": step_of_row * self.dt,
            "role": self.roles[trial_of_row, agent_of_row].astype(str),
            "start_lane": self.start_lanes[trial_of_row, agent_of_row].astype(str),
            "ic_dv": pa.array(self.ic_dv[trial_of_row], from_pandas=True),
            "ic_tco": pa.array(self.ic_tco[trial_of_row], from_pandas=True),
            "driver": self.drivers[trial_of_row, agent_of_row].astype(np.int32),
            "source": self.sources[trial_of_row].astype(str),
        }
        for k, name in enumerate(STATE_NAMES):
            columns[name] = state_rows[:, k]
        meta = {"format_version": FORMAT_VERSION, "dt": self.dt, **self.metadata}
        table = pa.table(columns, schema=SCHEMA)
        return table.replace_schema_metadata({METADATA_KEY: json.dumps(meta).encode()})

    def write_parquet(self, path: str | os.PathLike) -> None:
        """Write the set to ``path`` atomically (temporary file in the same folder, then rename)."""
        with atomic_write(path) as f:
            pq.write_table(self.to_table(), f, compression="zstd")


def load_trials(path: str | os.PathLike) -> TrialSet:
    """Read and validate a Parquet dataset written by :meth:`TrialSet.write_parquet`.

    Raises :class:`InputError` with a one-line message naming the file on a missing file, a file
    that is not Parquet, missing columns, NaN/inf states, unknown roles or lanes, steps that are not
    consecutive, a time step other than the file's ``dt``, a trial without exactly two agents of
    equal length, or a trial shorter than ``MIN_TRIAL_STEPS``.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file (expected a trafficweaving Parquet dataset)")
    try:
        table = pq.read_table(path)
    except (pa.ArrowInvalid, OSError) as exc:
        raise InputError(f"{path}: not a readable Parquet file ({str(exc).splitlines()[0]})") from None
    return trials_from_table(table, str(path))


def trials_from_table(table: pa.Table, name: str) -> TrialSet:
    """Validate a long table (see module docstring) and pack it into a :class:`TrialSet`;
    ``name`` is used in error messages."""
    missing = [f.name for f in SCHEMA if f.name not in table.column_names]
    if missing:
        raise InputError(f"{name}: missing column(s) {', '.join(missing)} (expected {', '.join(SCHEMA.names)})")
    raw_meta = (table.schema.metadata or {}).get(METADATA_KEY)
    try:
        meta = json.loads(raw_meta) if raw_meta else {}
    except json.JSONDecodeError:
        raise InputError(f"{name}: schema metadata '{METADATA_KEY.decode()}' is not valid JSON") from None
    dt = float(meta.pop("dt", DT))
    meta.pop("format_version", None)
    if table.num_rows == 0:
        raise InputError(f"{name}: the dataset has no rows (expected at least one trial)")

    col = lambda c: table.column(c).to_numpy(zero_copy_only=False)  # noqa: E731
    try:
        trial, agent, step = col("trial").astype(np.int64), col("agent").astype(np.int64), col("step").astype(np.int64)
        t = col("t").astype(float)
        states = np.stack([col(c).astype(float) for c in STATE_NAMES], axis=1)
        ic_dv = np.asarray(table.column("ic_dv").to_numpy(zero_copy_only=False), dtype=float)
        ic_tco = np.asarray(table.column("ic_tco").to_numpy(zero_copy_only=False), dtype=float)
        driver = col("driver").astype(np.int64)
    except (TypeError, ValueError, pa.ArrowInvalid) as exc:
        raise InputError(f"{name}: a column has the wrong type ({exc}); see the schema in the README") from None
    role, lane, source = (np.asarray(col(c)).astype(str) for c in ("role", "start_lane", "source"))

    bad = ~np.isfinite(states).all(axis=1)
    if bad.any():
        r = int(np.argmax(bad))
        raise InputError(f"{name}: NaN or infinite state in trial {trial[r]}, agent {agent[r]}, step {step[r]} (expected finite numbers)")
    for values, allowed, what in ((role, ROLES, "role"), (lane, LANES, "start_lane")):
        unknown = sorted(set(map(str, np.unique(values))) - set(allowed))
        if unknown:
            raise InputError(f"{name}: unknown {what} {unknown[0]!r} (expected one of {', '.join(allowed)})")
    if not set(np.unique(agent)) <= {0, 1}:
        raise InputError(f"{name}: agent ids must be 0 or 1, found {sorted(set(np.unique(agent)) - {0, 1})[0]}")

    order = np.lexsort((step, agent, trial))
    trial, agent, step, t = trial[order], agent[order], step[order], t[order]
    states, role, lane, driver, source = states[order], role[order], lane[order], driver[order], source[order]
    ic_dv, ic_tco = ic_dv[order], ic_tco[order]

    trial_ids = np.unique(trial)
    n = len(trial_ids)
    key_start = np.r_[True, (trial[1:] != trial[:-1]) | (agent[1:] != agent[:-1])]
    starts = np.flatnonzero(key_start)
    seg_len = np.diff(np.r_[starts, len(trial)])
    agents_per_trial = np.bincount(np.searchsorted(trial_ids, trial[starts]), minlength=n)
    if (agents_per_trial != 2).any():
        k = int(np.argmax(agents_per_trial != 2))
        raise InputError(f"{name}: trial {trial_ids[k]} has {agents_per_trial[k]} agent(s) (expected exactly 2)")
    seg_len2 = seg_len.reshape(n, 2)
    if (seg_len2[:, 0] != seg_len2[:, 1]).any():
        k = int(np.argmax(seg_len2[:, 0] != seg_len2[:, 1]))
        raise InputError(f"{name}: trial {trial_ids[k]} has agents of different lengths {seg_len2[k].tolist()} (expected equal)")
    lengths = seg_len2[:, 0]
    expected_step = np.arange(len(trial)) - np.repeat(starts, seg_len)
    if (step != expected_step).any():
        r = int(np.argmax(step != expected_step))
        raise InputError(f"{name}: trial {trial[r]} agent {agent[r]} has steps that are not consecutive from 0 (found step {step[r]}, expected {expected_step[r]})")
    short = lengths < MIN_TRIAL_STEPS
    if short.any():
        k = int(np.argmax(short))
        raise InputError(f"{name}: trial {trial_ids[k]} is too short ({lengths[k]} steps, expected at least {MIN_TRIAL_STEPS})")
    off_grid = ~np.isclose(t, step * dt, atol=1e-3 * dt, rtol=0)
    if off_grid.any():
        r = int(np.argmax(off_grid))
        raise InputError(f"{name}: non-uniform time step in trial {trial[r]} at step {step[r]} "
                         f"(t = {t[r]:.4f} s, expected {step[r] * dt:.4f} s for dt = {dt} s)")

    t_max = int(lengths.max())
    packed = np.full((n, 2, t_max, 6), np.nan)
    trial_index = np.searchsorted(trial_ids, trial)
    packed[trial_index, agent, step] = states
    seg_first = starts.reshape(n, 2)
    first = seg_first[:, 0]
    return TrialSet(
        states=packed,
        lengths=lengths.astype(np.int64),
        trial_ids=trial_ids.astype(np.int32),
        roles=role[seg_first],
        start_lanes=lane[seg_first],
        drivers=driver[seg_first].astype(np.int32),
        ic_dv=ic_dv[first],
        ic_tco=ic_tco[first],
        sources=source[first],
        dt=dt,
        metadata=meta,
    )
