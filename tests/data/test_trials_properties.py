"""Property-based tests of the Parquet data model: every valid trial set survives a round trip
exactly, and every corruption of a file gives either a valid trial set or a one-line
:class:`InputError` naming the file — never another exception."""

from __future__ import annotations

import json
import math

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from trafficweaving.data.trials import INT32_MAX, INT32_MIN, METADATA_KEY, ROLES, SCHEMA, TrialSet, load_trials
from trafficweaving.errors import InputError
from trafficweaving.scenario import LANES, MIN_TRIAL_STEPS

SETTINGS = settings(max_examples=50, deadline=None, database=None, derandomize=True,  # the same examples in every CI run
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

FINITE = st.floats(allow_nan=False, allow_infinity=False)
TEXT = st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), max_size=12)
"""Any text Arrow (UTF-8) and numpy (no trailing NUL) both keep exactly."""
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**53), 2**53) | FINITE | TEXT,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(TEXT, inner, max_size=3),
    max_leaves=8,
)


@st.composite
def trial_sets(draw, max_trials: int = 4) -> TrialSet:
    """A valid TrialSet: 1..max_trials trials of MIN_TRIAL_STEPS..+12 steps, any finite states,
    unique int32 ids in any order, any roles, lanes, drivers, sources, initial conditions (NaN:
    unknown), time step and JSON provenance."""
    n = draw(st.integers(1, max_trials))
    lengths = np.array(draw(st.lists(st.integers(MIN_TRIAL_STEPS, MIN_TRIAL_STEPS + 12), min_size=n, max_size=n)))
    states = draw(arrays(np.float64, (n, 2, int(lengths.max()), 6), elements=FINITE))
    states.transpose(0, 2, 1, 3)[np.arange(states.shape[2])[None, :] >= lengths[:, None]] = np.nan  # past each length
    per_trial = lambda strategy: draw(st.lists(strategy, min_size=n, max_size=n))  # noqa: E731
    per_agent = lambda strategy: np.array(draw(st.lists(st.lists(strategy, min_size=2, max_size=2), min_size=n, max_size=n)))  # noqa: E731
    initial = st.one_of(st.just(math.nan), FINITE)
    return TrialSet(
        states=states,
        lengths=lengths.astype(np.int64),
        trial_ids=np.array(draw(st.lists(st.integers(INT32_MIN, INT32_MAX), min_size=n, max_size=n, unique=True)), dtype=np.int32),
        roles=per_agent(st.sampled_from(ROLES)),
        start_lanes=per_agent(st.sampled_from(LANES)),
        drivers=per_agent(st.integers(INT32_MIN, INT32_MAX)).astype(np.int32),
        ic_dv=np.array(per_trial(initial), dtype=float),
        ic_tco=np.array(per_trial(initial), dtype=float),
        sources=np.array(per_trial(TEXT), dtype=str),
        dt=draw(st.sampled_from([0.1, 0.05, 0.2]) | st.floats(1e-3, 10.0)),
        metadata=draw(st.dictionaries(TEXT.filter(lambda k: k not in ("dt", "format_version")), JSON_VALUES, max_size=3)),
    )


def assert_same(a: TrialSet, b: TrialSet) -> None:
    """Every field of two trial sets equal (NaN equal to NaN); ``source_path`` not compared."""
    for name in ("states", "lengths", "trial_ids", "drivers", "ic_dv", "ic_tco"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for name in ("roles", "start_lanes", "sources"):
        assert getattr(a, name).tolist() == getattr(b, name).tolist(), name
    assert a.dt == b.dt and a.metadata == b.metadata


def assert_valid(trials: TrialSet) -> None:
    """The invariants every loaded trial set keeps."""
    n = len(trials)
    assert n >= 1 and trials.states.shape == (n, 2, int(trials.lengths.max()), 6)
    assert (trials.lengths >= MIN_TRIAL_STEPS).all()
    recorded = np.arange(trials.states.shape[2])[None, :] < trials.lengths[:, None]  # [n, T]
    assert np.isfinite(trials.states.transpose(0, 2, 1, 3)[recorded]).all()
    assert np.isnan(trials.states.transpose(0, 2, 1, 3)[~recorded]).all()
    assert set(trials.roles.ravel()) <= set(ROLES) and set(trials.start_lanes.ravel()) <= set(LANES)
    assert len(np.unique(trials.trial_ids)) == n and trials.trial_ids.dtype == np.int32
    assert math.isfinite(trials.dt) and trials.dt > 0
    assert not np.isinf(trials.ic_dv).any() and not np.isinf(trials.ic_tco).any()


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("properties")


@pytest.mark.slow
@SETTINGS
@given(trials=trial_sets())
def test_round_trip_of_any_valid_trial_set_is_exact(workdir, trials):
    path = workdir / "round trip.parquet"
    trials.write_parquet(path)
    back = load_trials(path)
    assert_same(back, trials.subset(np.argsort(trials.trial_ids)))  # loaded in trial-id order
    assert back.source_path == path
    assert_valid(back)
    assert [p.name for p in workdir.iterdir() if p.name.startswith(".")] == []  # no temporary file left


# ---------------------------------------------------------------- corruption
FLOAT_COLUMNS = ["t", "ic_dv", "ic_tco", "x", "y", "xd", "yd", "xdd", "ydd"]
TABLE_MUTATIONS = ["drop_column", "retype_column", "non_finite", "fractional_step", "duplicate_row", "drop_row",
                   "huge_id", "bad_dt", "bad_metadata", "null", "other_text", "shuffle_step", "extra_column"]
BYTE_MUTATIONS = ["random_bytes", "truncate", "overwrite_bytes", "empty_file"]


def _set(table: pa.Table, name: str, values: list, type_: pa.DataType | None = None) -> pa.Table:
    return table.set_column(table.schema.get_field_index(name), name, pa.array(values, type=type_))


def _retyped(values: list, kind: str) -> tuple[list, pa.DataType]:
    """``values`` converted to another Arrow type ``kind`` (nulls kept)."""
    def number(v):
        return float(len(v)) if isinstance(v, str) else float(v)

    convert = {
        "string": (lambda v: str(v), pa.string()),
        "large_string": (lambda v: str(v), pa.large_string()),
        "float64": (lambda v: number(v) + 0.25, pa.float64()),
        "float32": (lambda v: number(v), pa.float32()),
        "int64": (lambda v: int(number(v)) if abs(number(v)) < 2**62 else 0, pa.int64()),  # NaN, inf, huge: 0
        "uint8": (lambda v: int(abs(number(v))) % 256 if math.isfinite(number(v)) else 0, pa.uint8()),
        "bool": (lambda v: bool(v), pa.bool_()),
        "list": (lambda v: [v], None),
    }[kind]
    return [None if v is None else convert[0](v) for v in values], convert[1]


def mutate(table: pa.Table, kind: str, draw) -> pa.Table:
    """One corruption of a valid long table, drawn with ``draw``."""
    n = table.num_rows
    row = draw(st.integers(0, n - 1))
    column = draw(st.sampled_from(SCHEMA.names))
    values = table.column(column).to_pylist()
    if kind == "drop_column":
        return table.drop_columns([column])
    if kind == "retype_column":
        new, type_ = _retyped(values, draw(st.sampled_from(["string", "large_string", "float64", "float32", "int64",
                                                             "uint8", "bool", "list"])))
        return _set(table, column, new, type_)
    if kind == "non_finite":
        column = draw(st.sampled_from(FLOAT_COLUMNS))
        values = table.column(column).to_pylist()
        values[row] = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
        return _set(table, column, values, pa.float64())
    if kind == "fractional_step":
        steps = [float(s) for s in table.column("step").to_pylist()]
        steps[row] += draw(st.floats(0.001, 0.999))
        return _set(table, "step", steps, pa.float64())
    if kind == "duplicate_row":
        return pa.concat_tables([table, table.slice(row, 1)])
    if kind == "drop_row":
        return table.filter(pa.array(np.arange(n) != row))
    if kind == "huge_id":
        column = draw(st.sampled_from(["trial", "driver", "step", "agent"]))
        values = table.column(column).to_pylist()
        huge = st.integers(INT32_MAX + 1, 2**63 - 1) | st.integers(-(2**63), INT32_MIN - 1)
        if draw(st.booleans()):
            values[row] = draw(huge)
        else:
            offset = draw(huge)
            values = [v + offset if -(2**63) <= v + offset < 2**63 else offset for v in values]
        return _set(table, column, values, pa.int64())
    meta = json.loads(table.schema.metadata[METADATA_KEY])
    if kind == "bad_dt":
        if draw(st.booleans()):
            del meta["dt"]
        else:
            meta["dt"] = draw(st.none() | st.booleans() | TEXT | st.floats() | st.integers(-(2**70), 2**70)
                              | st.lists(st.floats(), max_size=2))
        return table.replace_schema_metadata({METADATA_KEY: json.dumps(meta).encode()})
    if kind == "bad_metadata":
        choice = draw(st.sampled_from(["bytes", "json", "none", "version"]))
        if choice == "none":
            return table.replace_schema_metadata(None)
        if choice == "version":
            meta["format_version"] = draw(JSON_VALUES)
            raw = json.dumps(meta).encode()
        else:
            raw = draw(st.binary(max_size=40)) if choice == "bytes" else json.dumps(draw(JSON_VALUES)).encode()
        return table.replace_schema_metadata({METADATA_KEY: raw})
    if kind == "null":
        values[row] = None
        return _set(table, column, values, table.schema.field(column).type)
    if kind == "other_text":
        column = draw(st.sampled_from(["role", "start_lane", "source"]))
        values = table.column(column).to_pylist()
        values[row] = draw(TEXT | st.sampled_from(list(ROLES + LANES)))
        return _set(table, column, values, pa.string())
    if kind == "shuffle_step":
        steps = table.column("step").to_pylist()
        steps[row] = draw(st.integers(INT32_MIN, INT32_MAX))
        return _set(table, "step", steps, pa.int32())
    if kind == "extra_column":
        return table.append_column(draw(st.sampled_from([column, "extra"])), table.column(column))
    raise AssertionError(kind)


def corrupt_bytes(data: bytes, kind: str, draw) -> bytes:
    """One corruption of a valid file's bytes."""
    if kind == "random_bytes":
        return draw(st.binary(min_size=1, max_size=2000))
    if kind == "truncate":
        return data[: draw(st.integers(0, len(data) - 1))]
    if kind == "overwrite_bytes":
        at = draw(st.integers(0, len(data) - 1))
        span = draw(st.binary(min_size=1, max_size=16))
        return data[:at] + span + data[at + len(span):]
    return b""


@pytest.mark.slow
@pytest.mark.parametrize("kind", TABLE_MUTATIONS + BYTE_MUTATIONS)
@settings(SETTINGS, max_examples=8)
@given(data=st.data())
def test_any_corruption_gives_a_valid_set_or_one_input_error_naming_the_file(workdir, kind, data):
    trials = data.draw(trial_sets(max_trials=3), label="trials")
    path = workdir / f"corrupt {kind}.parquet"
    if kind in BYTE_MUTATIONS:
        trials.write_parquet(path)
        path.write_bytes(corrupt_bytes(path.read_bytes(), kind, data.draw))
    else:
        pq.write_table(mutate(trials.to_table(), kind, data.draw), path)
    try:
        back = load_trials(path)
    except InputError as error:
        message = str(error)
        assert message.startswith(f"{path}: ") and "\n" not in message, message
    else:
        assert_valid(back)
