"""The trial data model and its Parquet storage.

A *trial* is one interaction of two cars (agents 0 and 1), sampled every ``DT`` seconds. On disk a
dataset is one Parquet file with **one row per agent per step**:

============  ========  ==========================================================================
column        type      meaning
============  ========  ==========================================================================
trial         int32     trial id, unique in the file
agent         int8      0 or 1, the car within the trial
step          int32     0, 1, ... T-1 (consecutive integers)
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
``dt`` (the time step, s; required, a positive finite number) and free-form provenance (e.g. the
generator's seed and parameters). Integer columns may also be stored as floats holding whole
numbers; every value must fit the type above.

In memory a :class:`TrialSet` holds padded arrays ready for learning: ``states[n, 2, T_max, 6]``
(NaN past each trial's length) and ``lengths[n]``.

:data:`PLAUSIBLE_RANGES` is the one statement of which state values a real car can have; both
importers (:mod:`.hitl`, :mod:`.rosbag`) refuse recordings outside it.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..atomic import atomic_write
from ..errors import InputError
from ..scenario import DT, LANES, MIN_TRIAL_STEPS, ROAD_Y_MAX, ROAD_Y_MIN, STATE_NAMES

FORMAT_VERSION = 1
ROLES = ("human", "robot")
"""The valid role labels of an agent: a person driving, or the robot car driven by the planner."""
METADATA_KEY = b"trafficweaving"
INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1

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
NULLABLE = ("ic_dv", "ic_tco")
"""The only columns that may hold nulls (an unknown initial condition)."""

STATE_UNITS = {"x": "m", "y": "m", "xd": "m/s", "yd": "m/s", "xdd": "m/s²", "ydd": "m/s²"}
"""Unit of each of ``STATE_NAMES``."""

PLAUSIBLE_RANGES: dict[str, tuple[float, float]] = {
    "x": (-500.0, 500.0),
    "y": (ROAD_Y_MIN - 10.0, ROAD_Y_MAX + 10.0),
    "xd": (-5.0, 80.0),
    "yd": (-15.0, 15.0),
    "xdd": (-30.0, 30.0),
    "ydd": (-30.0, 30.0),
}
"""Closed interval of every state component a recorded car can plausibly have, in the units of
:data:`STATE_UNITS`; the importers refuse recordings with a value outside it (or non-finite).

Chosen from physics and the scenario, with wide margins over the authors' 30 human-in-the-loop
recordings (x −142…+40 m, y −8.2…−1.5 m, xd 20.7…42.8 m/s, |yd| ≤ 4.1 m/s, |xdd|, |ydd| ≤ 8.4 m/s²):
``x`` within 500 m of the cutoff (cars start near ``START_X`` ≈ −150 m and recordings stop a few
tens of metres past the cutoff); ``y`` within 10 m (more than two lane widths) of the road
``ROAD_Y_MIN..ROAD_Y_MAX``; forward speed from a slight roll back (−5 m/s) to 80 m/s (288 km/h,
above any car the study's drivers could reach, about 2.8 × the start speed ``BASE_SPEED``);
lateral speed within ±15 m/s; accelerations within ±30 m/s² (about 3 g; tyres give about 1 g).
"""


def first_implausible(states: np.ndarray) -> tuple[tuple[int, ...], str, float] | None:
    """The first value of ``states[..., 6]`` (last axis ``STATE_NAMES``) outside
    :data:`PLAUSIBLE_RANGES` or non-finite, as ``(index of its state row, component name, value)``
    in C order; None when every value is plausible."""
    states = np.asarray(states, dtype=float)
    low = np.array([PLAUSIBLE_RANGES[name][0] for name in STATE_NAMES])
    high = np.array([PLAUSIBLE_RANGES[name][1] for name in STATE_NAMES])
    bad = ~((states >= low) & (states <= high))  # NaN compares False: bad
    if not bad.any():
        return None
    *row, k = np.unravel_index(int(np.argmax(bad)), bad.shape)
    return tuple(int(i) for i in row), STATE_NAMES[k], float(states[(*row, k)])


def implausible_text(name: str, value: float, where: str = "") -> str:
    """``"<name> = <value> <unit><where> (plausible: <low> to <high> <unit>)"`` for messages;
    ``where`` e.g. ``" at step 4"``."""
    low, high = PLAUSIBLE_RANGES[name]
    unit = STATE_UNITS[name]
    return f"{name} = {value:.6g} {unit}{where} (plausible: {low:g} to {high:g} {unit})"


@dataclass
class TrialSet:
    """A batch of two-agent trials as padded arrays.

    ``states``: ``[n, 2, T_max, 6]`` float64 (trial, agent, step, ``STATE_NAMES``), NaN past a
    trial's length. ``lengths``: ``[n]`` steps per trial. Per-trial ``trial_ids[n]``, ``ic_dv[n]``
    (m/s, NaN unknown), ``ic_tco[n]`` (s, NaN for Δv = 0 or unknown), ``sources[n]``; per-agent
    ``roles[n, 2]``, ``start_lanes[n, 2]``, ``drivers[n, 2]`` (-1 unknown). ``dt``: time step, s.
    ``source_path``: the file (or folder) the set was read from, for messages; None when built in
    memory. It is not stored in the Parquet file.
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
    source_path: Path | None = None

    def __len__(self) -> int:
        return len(self.lengths)

    def trajectory(self, i: int, agent: int) -> np.ndarray:
        """The recorded states of one agent, ``[lengths[i], 6]``."""
        return self.states[i, agent, : self.lengths[i]]

    def require_dt(self, expected: float = DT, purpose: str = "the human model") -> None:
        """Raise :class:`InputError` unless this set's time step is ``expected`` (s) — the step
        ``purpose`` (a model, the planner) works at; data at another step would be misread there.
        The one-line message names :attr:`source_path` when known."""
        dt = float(self.dt)
        if math.isfinite(dt) and abs(dt - expected) <= 1e-9 * abs(expected):
            return
        where = str(self.source_path) if self.source_path is not None else "the trial set"
        raise InputError(f"{where}: time step {dt:g} s (expected {expected:g} s, the time step of {purpose})")

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
            source_path=self.source_path,
        )

    @staticmethod
    def concatenate(sets: list["TrialSet"]) -> "TrialSet":
        """Join trial sets (same ``dt``), renumbering trial ids 0..n-1; ``source_path`` is kept
        only when all sets share it."""
        if not sets:
            raise ValueError("no trial sets to concatenate")
        t_max = max(s.states.shape[2] for s in sets)
        states = np.concatenate(
            [np.pad(s.states, ((0, 0), (0, 0), (0, t_max - s.states.shape[2]), (0, 0)), constant_values=np.nan)
             for s in sets]
        )
        cat = lambda name: np.concatenate([getattr(s, name) for s in sets])  # noqa: E731
        paths = {s.source_path for s in sets}
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
            source_path=paths.pop() if len(paths) == 1 else None,
        )

    # ------------------------------------------------------------------ storage
    def to_table(self) -> pa.Table:
        """The long (one row per agent per step) Arrow table of this set; ``format_version`` and
        ``dt`` in the schema metadata take precedence over keys of the same name in ``metadata``.

        Raises ValueError when a trial id or driver id does not fit the file's int32 columns."""
        for what, values in (("trial id", self.trial_ids), ("driver id", self.drivers)):
            values = np.asarray(values)
            if values.size and (values.min() < INT32_MIN or values.max() > INT32_MAX):
                raise ValueError(f"{what} {values.min() if values.min() < INT32_MIN else values.max()} "
                                 f"does not fit the file's int32 column")
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
        meta = {**self.metadata, "format_version": FORMAT_VERSION, "dt": float(self.dt)}
        table = pa.table(columns, schema=SCHEMA)
        return table.replace_schema_metadata({METADATA_KEY: json.dumps(meta).encode()})

    def write_parquet(self, path: str | os.PathLike) -> None:
        """Write the set to ``path`` atomically (temporary file in the same folder, then rename).
        ``source_path`` is not stored; :func:`load_trials` sets it to the path read."""
        table = self.to_table()
        with atomic_write(path) as f:
            pq.write_table(table, f, compression="zstd")


def load_trials(path: str | os.PathLike) -> TrialSet:
    """Read and validate a Parquet dataset written by :meth:`TrialSet.write_parquet`; the result's
    ``source_path`` is ``path``.

    Raises :class:`InputError` with a one-line message naming the file on a missing file, a file
    that is not Parquet, a missing, duplicated or wrongly typed column, nulls outside ``ic_dv`` and
    ``ic_tco``, integers that are fractional or outside their type, missing or malformed metadata
    (``format_version``, ``dt``), NaN/inf states, unknown roles or lanes, per-trial or per-agent
    values that change within a trial, steps that are not ``0..T-1``, a time column off the grid of
    the file's ``dt``, a trial without exactly two agents of equal length, or a trial shorter than
    ``MIN_TRIAL_STEPS``.
    """
    path = Path(path)
    if not path.is_file():
        what = "is a folder" if path.is_dir() else "not a regular file" if path.exists() else "no such file"
        raise InputError(f"{path}: {what} (expected a trafficweaving Parquet dataset)")
    try:
        with pq.ParquetFile(path) as parquet:  # a plain file reader: keeps duplicated column names for the check
            table = parquet.read()
    except (pa.ArrowException, OSError) as exc:
        reason = (str(exc).splitlines() or [type(exc).__name__])[0]
        raise InputError(f"{path}: not a readable Parquet file ({reason})") from None
    trials = trials_from_table(table, str(path))
    trials.source_path = path
    return trials


def _metadata(table: pa.Table, name: str) -> tuple[dict, float]:
    """The provenance dict and the time step (s) of the table's schema metadata, validated."""
    key = METADATA_KEY.decode()
    raw = (table.schema.metadata or {}).get(METADATA_KEY)
    expected = f"expected a JSON object with format_version {FORMAT_VERSION} and dt, as TrialSet.write_parquet writes"
    if raw is None:
        raise InputError(f"{name}: no '{key}' schema metadata ({expected})")
    try:
        meta = json.loads(raw)
    except (ValueError, RecursionError):
        raise InputError(f"{name}: schema metadata '{key}' is not valid JSON ({expected})") from None
    if not isinstance(meta, dict):
        raise InputError(f"{name}: schema metadata '{key}' is a JSON {type(meta).__name__}, not an object ({expected})")
    version = meta.pop("format_version", None)
    if type(version) is not int or version != FORMAT_VERSION:
        raise InputError(f"{name}: format_version {_short(version)} in the metadata (expected {FORMAT_VERSION})")
    if "dt" not in meta:
        raise InputError(f"{name}: the metadata has no time step 'dt' (expected dt in seconds, e.g. {DT})")
    dt = meta.pop("dt")
    try:
        ok = type(dt) in (int, float) and math.isfinite(dt) and float(dt) > 0
    except OverflowError:
        ok = False
    if not ok:
        raise InputError(f"{name}: time step dt = {_short(dt)} in the metadata (expected a positive finite number of seconds, e.g. {DT})")
    return meta, float(dt)


def _short(value) -> str:
    """``repr`` of a metadata value for a one-line message, at most 40 characters."""
    text = " ".join(repr(value).split())
    return text if len(text) <= 40 else text[:37] + "..."


def _check_columns(table: pa.Table, name: str) -> None:
    """Every schema column present once, of a usable type, without nulls outside ``NULLABLE``."""
    names = table.column_names
    missing = [f.name for f in SCHEMA if f.name not in names]
    if missing:
        raise InputError(f"{name}: missing column(s) {', '.join(missing)} (expected {', '.join(SCHEMA.names)})")
    repeated = [c for c in SCHEMA.names if names.count(c) > 1]
    if repeated:
        raise InputError(f"{name}: column {repeated[0]} appears {names.count(repeated[0])} times (expected once)")
    for spec in SCHEMA:
        typ = table.schema.field(spec.name).type
        if pa.types.is_string(spec.type):
            usable = _is_text(typ) or (pa.types.is_dictionary(typ) and _is_text(typ.value_type))
        else:  # numbers; integer columns may hold whole floats (checked on reading)
            usable = pa.types.is_integer(typ) or pa.types.is_floating(typ)
        if not usable:
            raise InputError(f"{name}: column {spec.name} has type {typ} (expected {spec.type}; see the data format in the README)")
        nulls = table.column(spec.name).null_count
        if nulls and spec.name not in NULLABLE:
            raise InputError(f"{name}: column {spec.name} has {nulls} null value(s) (expected none; only {' and '.join(NULLABLE)} may be null)")


def _is_text(typ: pa.DataType) -> bool:
    return pa.types.is_string(typ) or pa.types.is_large_string(typ) or pa.types.is_string_view(typ)


def _integers(table: pa.Table, column: str, name: str, low: int, high: int) -> np.ndarray:
    """Column ``column`` as int64, refusing fractional or non-finite floats and values outside
    ``low..high`` (the range of the column's documented type)."""
    data = table.column(column)
    values = data.to_numpy()
    if pa.types.is_floating(data.type):
        bad = ~np.isfinite(values) | (values != np.round(values))
        if bad.any():
            r = int(np.argmax(bad))
            raise InputError(f"{name}: column {column} has the non-integer value {float(values[r]):.10g} at row {r} (expected {SCHEMA.field(column).type} integers)")
    out_of_range = (values < low) | (values > high)
    if out_of_range.any():
        r = int(np.argmax(out_of_range))
        value = int(values[r])
        raise InputError(f"{name}: column {column} has the value {value} at row {r}, outside {low}..{high} "
                         f"(expected {SCHEMA.field(column).type})")
    return values.astype(np.int64)


def _floats(table: pa.Table, column: str) -> np.ndarray:
    """Column ``column`` as float64 (nulls as NaN)."""
    return np.asarray(table.column(column).to_numpy(zero_copy_only=False), dtype=float)


def _texts(table: pa.Table, column: str) -> np.ndarray:
    """Column ``column`` as a numpy string array."""
    data = table.column(column)
    if pa.types.is_dictionary(data.type):
        data = data.cast(data.type.value_type)
    return np.asarray(data.to_numpy(zero_copy_only=False), dtype=object).astype(str)


def trials_from_table(table: pa.Table, name: str) -> TrialSet:
    """Validate a long table (see module docstring) and pack it into a :class:`TrialSet`;
    ``name`` (the file) starts every error message."""
    _check_columns(table, name)
    meta, dt = _metadata(table, name)
    if table.num_rows == 0:
        raise InputError(f"{name}: the dataset has no rows (expected at least one trial)")
    rows = _read_rows(table, name)
    order = np.lexsort((rows["step"], rows["agent"], rows["trial"]))
    rows = {column: values[order] for column, values in rows.items()}
    trial_ids, starts, lengths = _segments(rows, name)
    _check_constant(rows, starts, lengths, name)
    _check_lengths_and_times(rows, trial_ids, lengths, dt, name)

    n, t_max = len(trial_ids), int(lengths.max())
    packed = np.full((n, 2, t_max, 6), np.nan)
    trial_index = np.searchsorted(trial_ids, rows["trial"])
    packed[trial_index, rows["agent"], rows["step"]] = rows["states"]
    seg_first = starts.reshape(n, 2)
    first = seg_first[:, 0]
    return TrialSet(
        states=packed,
        lengths=lengths.astype(np.int64),
        trial_ids=trial_ids.astype(np.int32),
        roles=rows["role"][seg_first],
        start_lanes=rows["lane"][seg_first],
        drivers=rows["driver"][seg_first].astype(np.int32),
        ic_dv=rows["ic_dv"][first],
        ic_tco=rows["ic_tco"][first],
        sources=rows["source"][first],
        dt=dt,
        metadata=meta,
    )


def _read_rows(table: pa.Table, name: str) -> dict[str, np.ndarray]:
    """The table's columns as arrays, one entry per row (``states [rows, 6]``), their values
    checked: integers in their types' ranges, finite states, known roles and lanes."""
    trial = _integers(table, "trial", name, INT32_MIN, INT32_MAX)
    agent = _integers(table, "agent", name, 0, 1)
    step = _integers(table, "step", name, 0, INT32_MAX)
    driver = _integers(table, "driver", name, INT32_MIN, INT32_MAX)
    t = _floats(table, "t")
    states = np.stack([_floats(table, c) for c in STATE_NAMES], axis=1)
    ic_dv, ic_tco = _floats(table, "ic_dv"), _floats(table, "ic_tco")
    role, lane, source = (_texts(table, c) for c in ("role", "start_lane", "source"))

    bad = ~np.isfinite(states).all(axis=1)
    if bad.any():
        r = int(np.argmax(bad))
        raise InputError(f"{name}: NaN or infinite state in trial {trial[r]}, agent {agent[r]}, step {step[r]} (expected finite numbers)")
    for values, column in ((ic_dv, "ic_dv"), (ic_tco, "ic_tco")):
        if np.isinf(values).any():
            r = int(np.argmax(np.isinf(values)))
            raise InputError(f"{name}: column {column} is infinite in trial {trial[r]} (expected a finite number, or null when unknown)")
    for values, allowed, what in ((role, ROLES, "role"), (lane, LANES, "start_lane")):
        unknown = sorted(set(map(str, np.unique(values))) - set(allowed))
        if unknown:
            raise InputError(f"{name}: unknown {what} {_short(unknown[0])} (expected one of {', '.join(allowed)})")
    return {"trial": trial, "agent": agent, "step": step, "t": t, "states": states, "role": role, "lane": lane,
            "driver": driver, "source": source, "ic_dv": ic_dv, "ic_tco": ic_tco}


def _segments(rows: dict[str, np.ndarray], name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sorted trial ids ``[n]``, the first row of each (trial, agent) segment ``[2n]`` and the
    trials' lengths ``[n]`` of ``rows`` sorted by trial, agent and step; refuses trials without
    exactly two agents of equal length, or whose steps are not 0, 1, ... in order."""
    trial, agent, step = rows["trial"], rows["agent"], rows["step"]
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
    expected_step = np.arange(len(trial)) - np.repeat(starts, seg_len)
    if (step != expected_step).any():
        r = int(np.argmax(step != expected_step))
        raise InputError(f"{name}: trial {trial[r]} agent {agent[r]} has steps that are not consecutive from 0 (found step {step[r]}, expected {expected_step[r]})")
    return trial_ids, starts, seg_len2[:, 0]


def _check_constant(rows: dict[str, np.ndarray], starts: np.ndarray, lengths: np.ndarray, name: str) -> None:
    """Refuses a role, start lane or driver that changes within an agent's rows, or a source or
    initial condition that changes within a trial's (``starts``, ``lengths``: :func:`_segments`)."""
    trial, agent, step = rows["trial"], rows["agent"], rows["step"]
    segment_first = np.repeat(starts, np.repeat(lengths, 2))  # row of each row's (trial, agent) first step
    trial_first = np.repeat(starts[::2], 2 * lengths)  # row of each row's trial's first row
    for column, first, what, per in (("role", segment_first, "role", "agent"),
                                     ("lane", segment_first, "start_lane", "agent"),
                                     ("driver", segment_first, "driver", "agent"),
                                     ("source", trial_first, "source", "trial"),
                                     ("ic_dv", trial_first, "ic_dv", "trial"), ("ic_tco", trial_first, "ic_tco", "trial")):
        values = rows[column]
        same = values == values[first]
        if values.dtype.kind == "f":
            same |= np.isnan(values) & np.isnan(values[first])
        if not same.all():
            r = int(np.argmax(~same))
            raise InputError(f"{name}: trial {trial[r]} agent {agent[r]} changes {what} at step {step[r]} "
                             f"({_short(values[first[r]].item())} then {_short(values[r].item())}; expected one value per {per})")


def _check_lengths_and_times(rows: dict[str, np.ndarray], trial_ids: np.ndarray, lengths: np.ndarray, dt: float,
                             name: str) -> None:
    """Refuses a trial shorter than ``MIN_TRIAL_STEPS`` or a time ``t`` off the grid ``step * dt``."""
    short = lengths < MIN_TRIAL_STEPS
    if short.any():
        k = int(np.argmax(short))
        raise InputError(f"{name}: trial {trial_ids[k]} is too short ({lengths[k]} steps, expected at least {MIN_TRIAL_STEPS})")
    trial, step, t = rows["trial"], rows["step"], rows["t"]
    off_grid = ~np.isclose(t, step * dt, atol=1e-3 * dt, rtol=0)
    if off_grid.any():
        r = int(np.argmax(off_grid))
        raise InputError(f"{name}: non-uniform time step in trial {trial[r]} at step {step[r]} "
                         f"(t = {t[r]:.4f} s, expected {step[r] * dt:.4f} s for dt = {dt:g} s)")
