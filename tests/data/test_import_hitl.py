"""The human-in-the-loop importer: the authors' 30 JLD files and every malformed input."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from trafficweaving.data.hitl import AGENT_ROLES, read_hitl
from trafficweaving.data.trials import PLAUSIBLE_RANGES, ROLES, load_trials
from trafficweaving.errors import InputError
from trafficweaving.scenario import LANE_CENTRE_Y, MIN_TRIAL_STEPS, STATE_NAMES, lane_of


def write_jld(path: Path, car1: np.ndarray | None, car2: np.ndarray | None) -> Path:
    """Write an HDF5 file with datasets ``car1``/``car2`` stored as given (``None``: left out)."""
    with h5py.File(path, "w") as f:
        for name, data in (("car1", car1), ("car2", car2)):
            if data is not None:
                f.create_dataset(name, data=data)
    return path


def straight_cars(steps: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Two cars at constant speed in ``[6, steps, 1]`` float32 layout: car1 in the right lane at
    30 m/s, car2 in the left lane at 28 m/s and 4 m ahead."""
    t = np.arange(steps) * 0.1
    zeros = np.zeros(steps)
    car1 = np.stack([-140 + 30 * t, np.full(steps, LANE_CENTRE_Y["right"]), np.full(steps, 30.0), zeros, zeros, zeros])
    car2 = np.stack([-136 + 28 * t, np.full(steps, LANE_CENTRE_Y["left"]), np.full(steps, 28.0), zeros, zeros, zeros])
    return car1[:, :, None].astype(np.float32), car2[:, :, None].astype(np.float32)


def test_reads_the_authors_files(hitl_dir, hitl_files, hitl_trials):
    paths = hitl_files
    assert len(paths) == 30
    trials = hitl_trials

    assert len(trials) == 30
    assert (trials.roles == ["robot", "human"]).all()
    assert (trials.drivers == -1).all()
    assert trials.trial_ids.tolist() == list(range(30))
    assert trials.sources.tolist() == [p.name for p in paths]
    assert trials.metadata == {"importer": "hitl"}
    assert trials.source_path == hitl_dir
    trials.require_dt()  # the models' time step
    assert set(trials.start_lanes[:, 0]) == {"left", "right"}  # the robot started in both lanes
    assert (trials.start_lanes[:, 0] != trials.start_lanes[:, 1]).all()
    assert np.isfinite(trials.ic_dv).all()
    for i, path in enumerate(paths):
        with h5py.File(path, "r") as f:
            car1, car2 = f["car1"][()], f["car2"][()]
        assert trials.lengths[i] == car1.shape[1]
        np.testing.assert_array_equal(trials.trajectory(i, 0), car1[:, :, 0].T.astype(np.float64))
        np.testing.assert_array_equal(trials.trajectory(i, 1), car2[:, :, 0].T.astype(np.float64))
        assert trials.start_lanes[i].tolist() == lane_of([car1[1, 0, 0], car2[1, 0, 0]]).tolist()
        assert np.isnan(trials.states[i, :, trials.lengths[i]:]).all()


def test_initial_condition_and_storage_round_trip(tmp_path):
    car1, car2 = straight_cars()
    a = write_jld(tmp_path / "a.jld", car1, car2)
    b = write_jld(tmp_path / "b.jld", car1[:, :25], car2[:, :25])
    trials = read_hitl([b, a])  # kept in the order given

    assert trials.sources.tolist() == ["b.jld", "a.jld"]
    assert trials.lengths.tolist() == [25, 30]
    assert trials.start_lanes.tolist() == [["right", "left"]] * 2
    np.testing.assert_allclose(trials.ic_dv, 28 - 30)  # v_left - v_right
    np.testing.assert_allclose(trials.ic_tco, -4.0 / (28 - 30), rtol=1e-5)  # -(x_left - x_right) / Δv

    trials.write_parquet(tmp_path / "d.parquet")
    back = load_trials(tmp_path / "d.parquet")
    np.testing.assert_array_equal(back.states, trials.states)
    assert back.roles.tolist() == trials.roles.tolist()
    assert back.metadata == {"importer": "hitl"}


def test_equal_speeds_give_no_crossover_time(tmp_path):
    car1, car2 = straight_cars()
    car2[2] = car1[2]
    trials = read_hitl([write_jld(tmp_path / "same.jld", car1, car2)])
    assert trials.ic_dv[0] == 0 and np.isnan(trials.ic_tco[0])


def _bad_files(tmp_path: Path) -> dict[str, Path]:
    """One malformed file per error the importer must report."""
    car1, car2 = straight_cars()
    nan, inf = car2.copy(), car1.copy()
    nan[3, 7, 0] = np.nan
    inf[0, 2, 0] = np.inf
    text = tmp_path / "text.jld"
    text.write_text("not HDF5\n")
    group = tmp_path / "group.jld"
    with h5py.File(group, "w") as f:
        f.create_group("car1")
        f.create_dataset("car2", data=car2)
    truncated = tmp_path / "truncated.jld"
    truncated.write_bytes(write_jld(tmp_path / "whole.jld", car1, car2).read_bytes()[:1000])
    return {
        "missing": tmp_path / "nope.jld",
        "not_hdf5": text,
        "truncated": truncated,
        "no_car2": write_jld(tmp_path / "no_car2.jld", car1, None),
        "car1_group": group,
        "rank": write_jld(tmp_path / "rank.jld", car1[:, :, 0], car2[:, :, 0]),
        "rows": write_jld(tmp_path / "rows.jld", car1[:5], car2[:5]),
        "strings": write_jld(tmp_path / "strings.jld", np.array([b"x"] * 3), car2),
        "lengths": write_jld(tmp_path / "lengths.jld", car1, car2[:, :29]),
        "nan": write_jld(tmp_path / "nan.jld", car1, nan),
        "inf": write_jld(tmp_path / "inf.jld", inf, car2),
        "short": write_jld(tmp_path / "short.jld", car1[:, : MIN_TRIAL_STEPS - 1], car2[:, : MIN_TRIAL_STEPS - 1]),
    }


@pytest.mark.parametrize(
    "case, expected",
    [
        ("missing", "no such file"),
        ("not_hdf5", "not an HDF5 file"),
        ("truncated", "unreadable HDF5 file"),
        ("no_car2", "missing dataset car2"),
        ("car1_group", "missing dataset car1"),
        ("rank", "expected [6, T, 1]"),
        ("rows", "shape [5, 30, 1]"),
        ("strings", "expected float"),
        ("lengths", "car1 has 30 steps but car2 has 29"),
        ("nan", "NaN or infinite yd at step 7"),
        ("inf", "NaN or infinite x at step 2"),
        ("short", f"expected at least {MIN_TRIAL_STEPS}"),
    ],
)
def test_malformed_input_is_one_line_naming_the_file(tmp_path, case, expected):
    bad = _bad_files(tmp_path)[case]
    good = write_jld(tmp_path / "good.jld", *straight_cars())
    with pytest.raises(InputError) as error:
        read_hitl([good, bad])
    message = str(error.value)
    assert "\n" not in message
    assert message.startswith(str(bad))
    assert expected in message


def test_no_files_is_an_error():
    with pytest.raises(InputError, match="no files given"):
        read_hitl([])


def test_plausible_ranges_leave_a_wide_margin_around_the_real_recordings(hitl_trials):
    """Every real value lies inside PLAUSIBLE_RANGES with at least half the real spread to spare."""
    for k, name in enumerate(STATE_NAMES):
        values = hitl_trials.states[..., k][np.isfinite(hitl_trials.states[..., k])]
        low, high = PLAUSIBLE_RANGES[name]
        margin = 0.5 * (values.max() - values.min())
        assert low + margin <= values.min() and values.max() <= high - margin, name


def test_agent_roles_are_valid_role_labels():
    assert set(AGENT_ROLES) <= set(ROLES) and len(AGENT_ROLES) == 2


def _with(car: np.ndarray, row: str, step: int, value: float) -> np.ndarray:
    car = car.copy()
    car[STATE_NAMES.index(row), step, 0] = value
    return car


@pytest.mark.parametrize(
    "car, quantity, value, expected",
    [
        ("car1", "x", -9e6, "car1 (robot) has x = -9e+06 m at step 4 (plausible: -500 to 500 m)"),
        ("car2", "xd", 250.0, "car2 (human) has xd = 250 m/s at step 4 (plausible: -5 to 80 m/s)"),
        ("car2", "y", 40.0, "car2 (human) has y = 40 m at step 4 (plausible: -18 to 9 m)"),
        ("car1", "xdd", -300.0, "car1 (robot) has xdd = -300 m/s² at step 4 (plausible: -30 to 30 m/s²)"),
        ("car2", "ydd", 120.0, "car2 (human) has ydd = 120 m/s² at step 4 (plausible: -30 to 30 m/s²)"),
        ("car1", "yd", -20.0, "car1 (robot) has yd = -20 m/s at step 4 (plausible: -15 to 15 m/s)"),
    ],
)
def test_implausible_values_are_refused_naming_file_car_quantity_value_and_range(tmp_path, car, quantity, value, expected):
    car1, car2 = straight_cars()
    if car == "car1":
        car1 = _with(car1, quantity, 4, value)
    else:
        car2 = _with(car2, quantity, 4, value)
    bad = write_jld(tmp_path / "bad.jld", car1, car2)
    good = write_jld(tmp_path / "good.jld", *straight_cars())
    with pytest.raises(InputError) as error:
        read_hitl([good, bad])
    message = str(error.value)
    assert message == f"{bad}: {expected}"


def test_values_at_the_edge_of_the_plausible_ranges_import(tmp_path):
    car1, car2 = straight_cars()
    car1 = _with(_with(car1, "xdd", 3, PLAUSIBLE_RANGES["xdd"][1]), "ydd", 5, PLAUSIBLE_RANGES["ydd"][0])
    trials = read_hitl([write_jld(tmp_path / "edge.jld", car1, car2)])
    assert trials.states[0, 0, 3, 4] == PLAUSIBLE_RANGES["xdd"][1]
    assert trials.source_path == tmp_path / "edge.jld"
