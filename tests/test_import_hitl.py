"""The human-in-the-loop importer: the authors' 30 JLD files and every malformed input."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from trafficweaving.data.hitl import read_hitl
from trafficweaving.data.trials import load_trials
from trafficweaving.errors import InputError
from trafficweaving.scenario import LANE_CENTRE_Y, MIN_TRIAL_STEPS, lane_of

REPO = Path(__file__).resolve().parents[1]
HITL_DIR = next(
    (d for d in (REPO / "shared/reference/hitl", REPO.parent / "shared/reference/hitl") if d.is_dir()),
    None,
)


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


@pytest.mark.skipif(HITL_DIR is None, reason="the authors' reference data (shared/reference/hitl) is absent")
def test_reads_the_authors_files():
    paths = sorted(HITL_DIR.glob("*.jld"))
    assert len(paths) == 30
    trials = read_hitl(paths)

    assert len(trials) == 30
    assert (trials.roles == ["robot", "human"]).all()
    assert (trials.drivers == -1).all()
    assert trials.trial_ids.tolist() == list(range(30))
    assert trials.sources.tolist() == [p.name for p in paths]
    assert trials.metadata == {"importer": "hitl"}
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
