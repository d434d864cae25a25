"""The Parquet data model: round trips, atomic writes, and a clear error for every malformed input."""

import json
import math

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from trafficweaving.data import trials as trials_module
from trafficweaving.data.behaviour import behaviour_samples, compare_behaviour, summarise
from trafficweaving.sim.generate import generate_trials
from trafficweaving.data.stats import TABLE1_PAPER, TABLE1_PAPER_TRIALS, table1, table1_max_deviation, table1_test
from trafficweaving.data.trials import (
    METADATA_KEY,
    PLAUSIBLE_RANGES,
    ROLES,
    SCHEMA,
    TrialSet,
    first_implausible,
    load_trials,
    trials_from_table,
)
from trafficweaving.errors import InputError
from trafficweaving.scenario import DT, LANE_CENTRE_Y, LANES, STATE_NAMES, lane_of


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
    assert trials.source_path is None and back.source_path == path  # the path is not stored in the file
    assert back.subset(np.arange(2)).source_path == path
    assert TrialSet.concatenate([back, back]).source_path == path
    assert TrialSet.concatenate([back, trials]).source_path is None


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



def test_lanes_and_roles_have_one_definition():
    assert trials_module.LANES is LANES
    assert ROLES == ("human", "robot")


def test_metadata_cannot_override_the_time_step(trials, tmp_path):
    odd = trials.subset(np.arange(2))
    odd.metadata = {"dt": 5.0, "format_version": 99, "note": "x"}
    odd.write_parquet(tmp_path / "d.parquet")
    back = load_trials(tmp_path / "d.parquet")
    assert back.dt == trials.dt and back.metadata == {"note": "x"}


def with_metadata(table, meta):
    """``table`` with the trafficweaving schema metadata replaced by ``meta`` (bytes, or JSON-dumped)."""
    raw = meta if isinstance(meta, bytes) else json.dumps(meta).encode()
    return table.replace_schema_metadata({METADATA_KEY: raw})


@pytest.mark.parametrize(
    "meta, expected",
    [
        ({"format_version": 1, "dt": "0.1"}, "time step dt = '0.1' in the metadata (expected a positive finite number of seconds"),
        ({"format_version": 1, "dt": None}, "time step dt = None in the metadata"),
        ({"format_version": 1, "dt": [0.1]}, "time step dt = [0.1] in the metadata"),
        ({"format_version": 1, "dt": True}, "time step dt = True in the metadata"),
        ({"format_version": 1}, "the metadata has no time step 'dt' (expected dt in seconds, e.g. 0.1)"),
        ({"format_version": 1, "dt": 0}, "time step dt = 0 in the metadata"),
        ({"format_version": 1, "dt": -0.1}, "time step dt = -0.1 in the metadata"),
        (b'{"format_version": 1, "dt": NaN}', "time step dt = nan in the metadata"),
        (b'{"format_version": 1, "dt": Infinity}', "time step dt = inf in the metadata"),
        (b'{"format_version": 1, "dt": 1e999}', "time step dt = inf in the metadata"),
        (b'{"format_version": 1, "dt": 1' + b"0" * 400 + b"}", "time step dt = 1000000"),
        ({"dt": 0.1}, "format_version None in the metadata (expected 1)"),
        ({"format_version": 2, "dt": 0.1}, "format_version 2 in the metadata (expected 1)"),
        ([1, 2], "schema metadata 'trafficweaving' is a JSON list, not an object"),
        (b"\xff\xfe{", "schema metadata 'trafficweaving' is not valid JSON"),
        (b"[" * 100_000, "schema metadata 'trafficweaving' is not valid JSON"),
        (None, "no 'trafficweaving' schema metadata"),
    ],
)
def test_malformed_time_step_metadata_is_one_line_naming_the_file(trials, tmp_path, meta, expected):
    table = table_of(trials.subset(np.arange(2)))
    table = table.replace_schema_metadata(None) if meta is None else with_metadata(table, meta)
    path = tmp_path / "d.parquet"
    pq.write_table(table, path)
    with pytest.raises(InputError) as err:
        load_trials(path)
    message = str(err.value)
    assert message.startswith(f"{path}: ") and expected in message and "\n" not in message
    assert len(message) < 400


def test_another_time_step_loads_and_require_dt_names_the_file(trials, tmp_path):
    coarse = trials.subset(np.arange(2))
    coarse.dt = 0.2
    path = tmp_path / "d.parquet"
    coarse.write_parquet(path)
    back = load_trials(path)
    assert back.dt == 0.2
    with pytest.raises(InputError) as err:
        back.require_dt()
    assert str(err.value) == f"{path}: time step 0.2 s (expected 0.1 s, the time step of the human model)"
    with pytest.raises(InputError) as err:
        back.require_dt(DT, purpose="the planner")
    assert str(err.value).endswith("(expected 0.1 s, the time step of the planner)")
    back.require_dt(0.2)  # matches
    load_trials(_written(trials, tmp_path)).require_dt()  # the usual 0.1 s passes

    coarse.require_dt(0.2)
    with pytest.raises(InputError) as err:
        coarse.require_dt()  # built in memory: no file to name
    assert str(err.value) == "the trial set: time step 0.2 s (expected 0.1 s, the time step of the human model)"
    coarse.dt = float("nan")
    with pytest.raises(InputError, match="time step nan s"):
        coarse.require_dt()


def _written(trials, tmp_path):
    path = tmp_path / "ok.parquet"
    trials.write_parquet(path)
    return path


def _set(table, name, values, type_=None):
    return table.set_column(table.schema.get_field_index(name), name, pa.array(values, type=type_))


def column_cases(table):
    """Malformed column contents: name -> (table, expected text in the message)."""
    n = table.num_rows
    step = table.column("step").to_numpy()
    trial = table.column("trial").to_numpy()
    agent = table.column("agent").to_numpy()
    row0 = np.arange(n) == 0
    return {
        "fractional step": (_set(table, "step", np.where(step == 3, 3.5, step).astype(float)),
                            "column step has the non-integer value 3.5 at row 3 (expected int32 integers)"),
        "NaN step": (_set(table, "step", np.where(step == 3, np.nan, step).astype(float)), "column step has the non-integer value nan"),
        "whole float steps load": (_set(table, "step", step.astype(float)), None),
        "trial id above int32": (_set(table, "trial", trial.astype(np.int64) + 2**31, pa.int64()),
                                 "column trial has the value 2147483648 at row 0, outside -2147483648..2147483647 (expected int32)"),
        "trial id as huge uint64": (_set(table, "trial", trial.astype(np.uint64) + np.uint64(2**63), pa.uint64()),
                                    "column trial has the value 9223372036854775808 at row 0"),
        "trial id as huge float": (_set(table, "trial", trial.astype(float) * 1e300), "outside -2147483648..2147483647"),
        "driver above int32": (_set(table, "driver", np.full(n, 2**40), pa.int64()), "column driver has the value 1099511627776"),
        "agent 2": (_set(table, "agent", np.where(row0, 2, agent), pa.int8()), "column agent has the value 2 at row 0, outside 0..1"),
        "negative step": (_set(table, "step", np.where(row0, -1, step), pa.int32()), "column step has the value -1 at row 0"),
        "string step": (_set(table, "step", step.astype(str)), "column step has type string (expected int32"),
        "bool state": (_set(table, "x", np.zeros(n, bool)), "column x has type bool (expected double"),
        "numeric role": (_set(table, "role", np.zeros(n)), "column role has type double (expected string"),
        "list state": (_set(table, "y", [[1.0]] * n), "column y has type list<"),
        "null role": (_set(table, "role", [None] + ["human"] * (n - 1), pa.string()),
                      "column role has 1 null value(s) (expected none; only ic_dv and ic_tco may be null)"),
        "null trial": (_set(table, "trial", [None] + trial[1:].tolist(), pa.int32()), "column trial has 1 null value(s)"),
        "null x": (_set(table, "x", [None] + table.column("x").to_pylist()[1:], pa.float64()), "column x has 1 null value(s)"),
        "duplicate column": (table.append_column("x", table.column("x")), "column x appears 2 times (expected once)"),
        "infinite ic_dv": (_set(table, "ic_dv", np.where(row0, np.inf, 0.0)), "column ic_dv is infinite in trial 0"),
        "role changes": (_set(table, "role", np.where((agent == 0) & (step == 7) & (trial == trial[0]), "robot", "human")),
                         "trial 0 agent 0 changes role at step 7 ('human' then 'robot'; expected one value per agent)"),
        "ic_dv changes": (_set(table, "ic_dv", np.where((agent == 1) & (step == 4) & (trial == trial[0]), 1.0, np.nan)),
                          "trial 0 agent 1 changes ic_dv at step 4 (nan then 1.0; expected one value per trial)"),
        "source changes": (_set(table, "source", np.where((agent == 1) & (trial == trial[0]), "b", "a")),
                           "trial 0 agent 1 changes source at step 0 ('a' then 'b'; expected one value per trial)"),
        "duplicated row": (pa.concat_tables([table, table.slice(5, 1)]), "different lengths"),
        "dictionary strings load": (_set(table, "role", pa.array(table.column("role").to_pylist()).dictionary_encode()), None),
        "large strings load": (_set(table, "source", table.column("source").to_pylist(), pa.large_string()), None),
    }


@pytest.mark.parametrize("case", [
    "fractional step", "NaN step", "whole float steps load", "trial id above int32", "trial id as huge uint64",
    "trial id as huge float", "driver above int32", "agent 2", "negative step", "string step", "bool state",
    "numeric role", "list state", "null role", "null trial", "null x", "duplicate column", "infinite ic_dv",
    "role changes", "ic_dv changes", "source changes", "duplicated row", "dictionary strings load",
    "large strings load"])
def test_column_types_and_values_are_checked(trials, tmp_path, case):
    table, expected = column_cases(table_of(trials.subset(np.arange(3))))[case]
    path = tmp_path / "bad.parquet"
    pq.write_table(table, path)
    if expected is None:
        back = load_trials(path)
        np.testing.assert_array_equal(back.states, trials.subset(np.arange(3)).states)
        assert back.roles.tolist() == trials.roles[:3].tolist()
        return
    with pytest.raises(InputError) as err:
        load_trials(path)
    message = str(err.value)
    assert message.startswith(f"{path}: ") and expected in message and "\n" not in message


@pytest.mark.parametrize("content", [b"", b"PAR1", b"PAR1" + bytes(100) + b"PAR1"])
def test_empty_and_tiny_files_are_not_parquet(tmp_path, content):
    path = tmp_path / "tiny.parquet"
    path.write_bytes(content)
    with pytest.raises(InputError, match=f"^{path}: not a readable Parquet file"):
        load_trials(path)


def test_truncated_file_is_not_parquet(trials, tmp_path):
    path = _written(trials, tmp_path)
    data = path.read_bytes()
    for cut in (len(data) // 3, len(data) - 10):
        path.write_bytes(data[:cut])
        with pytest.raises(InputError, match="not a readable Parquet file"):
            load_trials(path)


def test_to_table_refuses_ids_beyond_int32(trials):
    big = trials.subset(np.arange(2))
    big.trial_ids = np.array([0, 2**31], dtype=np.int64)
    with pytest.raises(ValueError, match="trial id 2147483648 does not fit"):
        big.to_table()


def test_first_implausible_finds_the_first_bad_value():
    states = np.zeros((2, 5, 6))
    states[..., 1] = LANE_CENTRE_Y["left"]
    states[..., 2] = 30.0
    assert first_implausible(states) is None
    states[1, 3, 4] = 200.0
    states[1, 4, 0] = np.nan
    assert first_implausible(states) == ((1, 3), "xdd", 200.0)
    states[1, 3, 4] = 0.0
    assert first_implausible(states)[:2] == ((1, 4), "x")
    assert set(PLAUSIBLE_RANGES) == set(STATE_NAMES)


# ---------------------------------------------------------------- statistics are strict JSON
def _tiny(y_paths, x0=(-60.0, -64.0), speed=(30.0, 30.0), ic_dv=0.0, ic_tco=np.nan, steps=40) -> TrialSet:
    """One trial of two cars at constant speeds with lateral paths ``y_paths`` (functions of the
    step index, m)."""
    k = np.arange(steps)
    states = np.zeros((1, 2, steps, 6))
    for a in (0, 1):
        states[0, a, :, 0] = x0[a] + speed[a] * DT * k
        states[0, a, :, 1] = y_paths[a](k)
        states[0, a, :, 2] = speed[a]
        states[0, a, :, 3] = np.gradient(states[0, a, :, 1], DT)
    y0 = states[0, :, 0, 1]
    return TrialSet(states=states, lengths=np.array([steps]), trial_ids=np.array([0], np.int32),
                    roles=np.array([["human", "human"]]), start_lanes=lane_of(y0)[None],
                    drivers=np.full((1, 2), -1, np.int32), ic_dv=np.array([ic_dv]), ic_tco=np.array([ic_tco]),
                    sources=np.array(["tiny"]))


def _strict_json(value) -> str:
    return json.dumps(value, allow_nan=False)


def test_statistics_of_a_trial_where_nobody_changes_lanes_are_strict_json():
    left, right = LANE_CENTRE_Y["left"], LANE_CENTRE_Y["right"]
    trials = _tiny([lambda k: np.full(k.shape, left), lambda k: np.full(k.shape, right)])
    t1 = table1(trials)
    _strict_json(t1)
    assert t1["table1"]["0"]["all"] in (0.0, 1.0) and t1["table1"]["2"] == {"1": None, "2": None, "3": None}
    samples = behaviour_samples(trials)
    summaries = {name: summarise(values) for name, values in samples.items()}
    _strict_json(summaries)
    assert summaries["lane_change_x"] == {"count": 0, "mean": None, "std": None, "p5": None, "p50": None, "p95": None}
    comparison = compare_behaviour(samples, samples)
    _strict_json(comparison)
    assert comparison["lane_change_x"]["wasserstein"] is None
    assert comparison["speed"]["wasserstein"] == 0.0 and comparison["speed"]["wasserstein_over_std"] is None  # std 0


def test_statistics_of_one_weaving_trial_and_of_an_empty_set_are_strict_json():
    left, right = LANE_CENTRE_Y["left"], LANE_CENTRE_Y["right"]
    ramp = lambda a, b: (lambda k: a + (b - a) * np.clip((k - 10) / 15, 0, 1))  # noqa: E731
    trials = _tiny([ramp(left, right), ramp(right, left)], ic_dv=2.0, ic_tco=1.0)
    t1 = table1(trials)
    _strict_json(t1)
    assert t1["counts"]["2"]["1"] == 1 and t1["table1"]["2"]["1"] in (0.0, 1.0)
    samples = behaviour_samples(trials)
    assert samples["lane_change_x"].size == 2
    _strict_json({name: summarise(v) for name, v in samples.items()})
    _strict_json(compare_behaviour(samples, behaviour_samples(trials.subset(np.zeros(1, bool)))))

    empty = trials.subset(np.zeros(1, bool))
    t1 = table1(empty)
    _strict_json(t1)
    assert table1_max_deviation(t1["table1"]) is None
    assert all(v is None for row in t1["table1"].values() for v in row.values())
    assert table1_max_deviation({"2": {"1": 0.9}}) == pytest.approx(abs(0.9 - 0.857))


def test_summaries_never_hold_nan_or_infinity():
    assert summarise(np.array([1.0, np.nan]))["mean"] is None
    assert summarise(np.array([np.inf, 1.0]))["std"] is None
    assert summarise(np.array([2.0]))["std"] == 0.0
    row = compare_behaviour({"speed": np.array([1.0, np.nan])}, {"speed": np.array([1.0, 2.0])})["speed"]
    _strict_json(row)
    assert row["wasserstein"] is None and row["wasserstein_over_std"] is None
    assert math.isclose(compare_behaviour({"speed": np.array([3.0])}, {"speed": np.array([1.0, 2.0])})["speed"]["wasserstein_over_std"], 1.5 / 0.5)


@pytest.mark.slow
def test_table1_test_is_calibrated_on_tables_drawn_at_the_papers_rates():
    """Tables played at the study's true rates (each cell's rate drawn from what its published
    percentage and size leave possible, a Beta posterior) are judged consistent about 95 % of the
    time, and fall within 5 pp of the paper in every cell only about one time in nine."""
    rng = np.random.default_rng(0)
    cells = [(dv, k) for dv, row in TABLE1_PAPER.items() for k in row]
    sizes = {cell: round(TABLE1_PAPER_TRIALS[cell[0]][cell[1]]) for cell in cells}
    rejected = within_5pp = 0
    runs = 2000
    for _ in range(runs):
        table, counts = {}, {}
        for dv, k in cells:
            n, q = sizes[dv, k], TABLE1_PAPER[dv][k]
            table.setdefault(dv, {})[k] = rng.binomial(n, rng.beta(q * n + 0.5, (1 - q) * n + 0.5)) / n
            counts.setdefault(dv, {})[k] = n
        rejected += table1_test(table, counts)["p_value"] < 0.05
        within_5pp += table1_max_deviation(table) <= 0.05 + 1e-12
    assert 0.03 < rejected / runs < 0.08
    assert 0.04 < within_5pp / runs < 0.25  # the paper's own sampling error makes 5 pp a rare outcome


def test_table1_test_scores_differences_against_both_samples_errors():
    same = table1_test(TABLE1_PAPER, {dv: {k: 123 for k in row} for dv, row in TABLE1_PAPER.items()})
    assert same["chi2"] == pytest.approx(0.0) and same["p_value"] == pytest.approx(1.0) and same["dof"] == 7
    off = {dv: dict(row) for dv, row in TABLE1_PAPER.items()}
    off["2"]["2"] = 0.64  # 12 pp low in one cell
    small, large = (table1_test(off, {"2": {"2": n}}) for n in (120, 12000))
    assert small["dof"] == large["dof"] == 1 and small["cells"]["2"]["2"]["difference"] == pytest.approx(0.64 - 0.762)
    assert large["cells"]["2"]["2"]["z"] < small["cells"]["2"]["2"]["z"] < 0  # more trials: only the paper's error left
    assert large["p_value"] < small["p_value"] < 0.05
    assert table1_test({"2": {"1": None}}, {"2": {"1": 0}}) is None
