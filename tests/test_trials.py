"""The Parquet data model: round trips, atomic writes, and a clear error for every malformed input."""

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from trafficweaving.data.generate import generate_trials
from trafficweaving.data.trials import SCHEMA, TrialSet, load_trials, trials_from_table
from trafficweaving.errors import InputError


@pytest.fixture(scope="module")
def trials():
    return generate_trials(12, seed=3)[0]


def test_round_trip_is_exact(trials, tmp_path):
    path = tmp_path / "d.parquet"
    trials.write_parquet(path)
    back = load_trials(path)
    np.testing.assert_array_equal(back.lengths, trials.lengths)
    np.testing.assert_array_equal(back.states, trials.states)  # NaN padding included
    for name in ("trial_ids", "roles", "start_lanes", "drivers", "sources"):
        np.testing.assert_array_equal(getattr(back, name), getattr(trials, name))
    np.testing.assert_array_equal(back.ic_dv, trials.ic_dv)
    np.testing.assert_array_equal(np.isnan(back.ic_tco), np.isnan(trials.ic_tco))
    assert back.dt == trials.dt and back.metadata["generator"]["seed"] == 3


def test_file_has_the_documented_schema_one_row_per_agent_per_step(trials, tmp_path):
    path = tmp_path / "d.parquet"
    trials.write_parquet(path)
    table = pq.read_table(path)
    assert table.schema.remove_metadata() == SCHEMA
    assert table.num_rows == 2 * trials.lengths.sum()
    assert set(table.column("role").to_pylist()) == {"human"}


def test_write_is_atomic_and_leaves_no_temporary_files(trials, tmp_path, monkeypatch):
    path = tmp_path / "d.parquet"
    trials.write_parquet(path)
    before = path.read_bytes()

    def broken(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(pq, "write_table", broken)
    with pytest.raises(OSError):
        trials.subset(np.arange(3)).write_parquet(path)
    assert path.read_bytes() == before  # the old file is intact
    assert [p.name for p in tmp_path.iterdir()] == ["d.parquet"]


def test_subset_and_concatenate(trials):
    a, b = trials.subset(np.arange(5)), trials.subset(np.arange(5, 12))
    joined = TrialSet.concatenate([a, b])
    assert len(joined) == 12 and joined.trial_ids.tolist() == list(range(12))
    np.testing.assert_array_equal(joined.lengths, trials.lengths)
    i = 7
    np.testing.assert_array_equal(joined.trajectory(i, 1), trials.trajectory(i, 1))


def table_of(trials):
    return trials.to_table()


def replace(table, name, values):
    return table.set_column(table.schema.get_field_index(name), name, pa.array(values, type=table.schema.field(name).type))


def malformed_cases(table):
    n = table.num_rows
    x = table.column("x").to_numpy().copy()
    step = table.column("step").to_numpy().copy()
    t = table.column("t").to_numpy().copy()
    trial = table.column("trial").to_numpy()
    first_trial = trial == trial[0]
    cases = {
        "missing column": (table.drop(["ydd"]), "missing column(s) ydd"),
        "NaN state": (replace(table, "x", np.where(np.arange(n) == 5, np.nan, x)), "NaN or infinite"),
        "inf state": (replace(table, "x", np.where(np.arange(n) == 5, np.inf, x)), "NaN or infinite"),
        "unknown role": (replace(table, "role", ["pilot"] * n), "unknown role 'pilot'"),
        "unknown lane": (replace(table, "start_lane", ["middle"] * n), "unknown start_lane 'middle'"),
        "non-uniform dt": (replace(table, "t", np.where(step == 10, t + 0.05, t)), "non-uniform time step"),
        "gap in steps": (table.filter(pa.array(~(step == 10))), "not consecutive"),
        "too short": (table.filter(pa.array(~first_trial | (step < 12))), "too short (12 steps"),
        "one agent": (table.filter(pa.array(~(first_trial & (table.column("agent").to_numpy() == 1)))), "expected exactly 2"),
        "empty": (table.slice(0, 0), "no rows"),
    }
    unequal = table.filter(pa.array(~(first_trial & (table.column("agent").to_numpy() == 1) & (step == step[first_trial].max()))))
    cases["unequal agents"] = (unequal, "different lengths")
    return cases


@pytest.mark.parametrize("case", ["missing column", "NaN state", "inf state", "unknown role", "unknown lane",
                                  "non-uniform dt", "gap in steps", "too short", "one agent", "empty",
                                  "unequal agents"])
def test_every_malformed_file_gets_a_one_line_error_naming_it(trials, tmp_path, case):
    table, expected = malformed_cases(table_of(trials))[case]
    path = tmp_path / "bad.parquet"
    pq.write_table(table, path)
    with pytest.raises(InputError) as err:
        load_trials(path)
    message = str(err.value)
    assert message.startswith(str(path)) and expected in message and "\n" not in message


def test_not_a_parquet_file_and_missing_file(tmp_path):
    junk = tmp_path / "junk.parquet"
    junk.write_text("hello")
    with pytest.raises(InputError, match="not a readable Parquet file"):
        load_trials(junk)
    with pytest.raises(InputError, match="no such file"):
        load_trials(tmp_path / "absent.parquet")


def test_rows_in_any_order_load_the_same(trials):
    table = table_of(trials)
    shuffled = table.take(pa.array(np.random.default_rng(0).permutation(table.num_rows)))
    back = trials_from_table(shuffled, "shuffled")
    np.testing.assert_array_equal(back.states, trials.states)
