"""The ROS1 bag importer on synthetic bags written in the authors' format: one valid weaving trial
checked against its analytic trajectory, and one bag per rejection reason."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbag_writer import TYPESTORE, car_states, sim_times, write_bag
from rosbags.rosbag1 import Writer

from trafficweaving.data.rosbag import REJECT_REASONS, BagRejected, read_rosbags, sanitise
from trafficweaving.data.trials import load_trials
from trafficweaving.errors import InputError
from trafficweaving.scenario import CUTOFF_X, DT, LANE_CENTRE_Y

LEFT, RIGHT = LANE_CENTRE_Y["left"], LANE_CENTRE_Y["right"]
T0 = 1000.0
"""Simulator clock at the start of every synthetic recording, s."""
TOPICS = ("/object_state/1", "/object_state/2")
CHANGE_AT, CHANGE_FOR = 2.6, 2.0
"""Lane changes start this many seconds into the recording and last this long, s."""


def weaving(*, x1=-145.0, x2=-147.0, v2=31.0, y1_end=RIGHT, y2_end=LEFT, change_at=CHANGE_AT, stop=6.5):
    """Per-car ``(x0, v, y0, y1, t_change, duration)`` of car_states: car 1 starts in the left lane
    at 29 m/s, car 2 in the right lane (by default 2 m behind at 31 m/s, i.e. the study's
    Δv = +2 m/s, tco = 1 s, passing in front), both changing lanes at the same time; and ``stop``,
    the recording's duration in s."""
    return [(x1, 29.0, LEFT, y1_end, change_at, CHANGE_FOR), (x2, v2, RIGHT, y2_end, change_at, CHANGE_FOR)], stop


def tracks(spec, seed: int = 0) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Topic -> (simTime, states) at 60 Hz with ±2 ms jitter; car 2's stream starts 13 ms later."""
    cars, stop = spec
    out = {}
    for k, (topic, car) in enumerate(zip(TOPICS, cars)):
        t = sim_times(T0 + 0.013 * k, T0 + stop, jitter=0.002, seed=seed + k)
        out[topic] = (t, car_states(t - T0, *car))
    return out


VALID = weaving()
SAME_SPEED = weaving(x2=-139.0, v2=29.0)  # Δv = 0, car 2 stays 6 m ahead


def _gap(spec):
    out = tracks(spec)
    t, states = out[TOPICS[0]]
    keep = (t < T0 + 2.0) | (t > T0 + 2.3)
    out[TOPICS[0]] = (t[keep], states[keep])
    return out


def _not_finite(spec):
    out = tracks(spec)
    out[TOPICS[1]][1][50, 1] = np.nan
    return out


def _inconsistent(spec):
    out = tracks(spec)
    t, states = out[TOPICS[0]]
    states = states.copy()
    states[:, 2] += 5.0  # reported speed disagrees with the positions
    out[TOPICS[0]] = (t, states)
    return out


def _implausible(spec):
    out = tracks(spec)
    t, states = out[TOPICS[1]]
    states = states.copy()
    states[(t > T0 + 1.0) & (t < T0 + 1.5), 5] = 500.0  # a lateral acceleration of 50 g for 0.5 s
    out[TOPICS[1]] = (t, states)
    return out


def _random_bytes(path: Path) -> None:
    path.write_bytes(np.random.default_rng(7).bytes(20_000))


def _truncated(path: Path) -> None:
    write_bag(path, tracks(VALID))
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _other_type(path: Path) -> None:
    float64 = TYPESTORE.types["std_msgs/msg/Float64"]
    with Writer(path) as writer:
        for topic in TOPICS:
            connection = writer.add_connection(topic, "std_msgs/msg/Float64", typestore=TYPESTORE)
            writer.write(connection, 1, TYPESTORE.serialize_ros1(float64(data=1.0), "std_msgs/msg/Float64"))


BAGS = {
    # relative path: tracks, or a function writing the file, and the expected outcome
    "01/15:48:04_29_0_2_1_3.bag": (tracks(VALID), "ok"),
    "pair/15:44:04_29_1_0_2_1.bag": (tracks(SAME_SPEED), "ok"),
    "01/15:50:00_29_0_2_1_4.bag": (tracks(weaving(change_at=0.5)), "collision"),
    "01/15:51:00_29_0_2_1_5.bag": (tracks(weaving(y1_end=LEFT, y2_end=RIGHT)), "no_lane_swap"),
    "01/15:52:00_29_0_2_1_6.bag": (tracks(weaving(y1_end=-0.5, y2_end=RIGHT)), "off_road"),
    "01/15:53:00_29_0_2_1_7.bag": (tracks(weaving(stop=4.0)), "cutoff_not_reached"),
    "01/15:54:00_29_0_2_1_8.bag": (tracks(weaving(stop=1.5)), "too_short"),
    "01/15:55:00_29_0_2_1_9.bag": (tracks(weaving(x1=-90.0, x2=-92.0)), "start_not_recorded"),
    "02/15:56:00_29_0_2_1_1.bag": (_gap(VALID), "timestamp_gap"),
    "02/15:57:00_29_0_2_1_2.bag": ({TOPICS[0]: tracks(VALID)[TOPICS[0]]}, "missing_topic"),
    "02/15:58:00_29_0_2_1_3.bag": (_inconsistent(VALID), "inconsistent"),
    "02/15:58:30_29_0_2_1_4.bag": (_not_finite(VALID), "non_finite"),
    "02/trial.bag": (tracks(VALID), "bad_filename"),
    "02/15:59:00_29_0_2_1_4.bag": (lambda path: path.write_bytes(b"not a bag\n"), "unreadable"),
    "02/15:59:30_29_0_2_1_5.bag": (_other_type, "unreadable"),
    "03/16:00:00_29_0_2_1_1.bag": (_random_bytes, "unreadable"),
    "03/16:00:30_29_0_2_1_2.bag": (lambda path: path.write_bytes(b""), "unreadable"),
    "03/16:01:00_29_0_2_1_3.bag": (_truncated, "unreadable"),
    "03/16:01:30_29_0_2_1_4.bag": (_implausible(VALID), "implausible"),
}


@pytest.fixture(scope="module")
def bag_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("bags")
    for name, (content, _) in BAGS.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if callable(content):
            content(path)
        else:
            write_bag(path, content)
    (root / "01" / "notes.txt").write_text("not a bag, ignored\n")
    return root


@pytest.fixture(scope="module")
def imported(bag_dir):
    return read_rosbags(bag_dir)


@pytest.mark.slow
def test_every_bag_has_its_outcome(imported):
    assert imported.files == sorted((name, outcome) for name, (_, outcome) in BAGS.items())
    assert imported.rejected == {
        "bad_filename": 1,
        "unreadable": 5,
        "missing_topic": 1,
        "timestamp_gap": 1,
        "non_finite": 1,
        "too_short": 1,
        "inconsistent": 1,
        "start_not_recorded": 1,
        "implausible": 1,
        "collision": 1,
        "off_road": 1,
        "no_lane_swap": 1,
        "cutoff_not_reached": 1,
    }


def test_valid_trial_matches_its_analytic_trajectory(imported, bag_dir):
    trials = imported.trials
    assert len(trials) == 2
    assert trials.source_path == bag_dir
    trials.require_dt()
    i = trials.sources.tolist().index("01/15:48:04_29_0_2_1_3.bag")
    assert trials.roles[i].tolist() == ["human", "human"]
    assert trials.drivers[i].tolist() == [2, 3]
    assert trials.start_lanes[i].tolist() == ["left", "right"]
    assert trials.ic_dv[i] == -2.0  # v_left - v_right = 29 - 31
    assert trials.ic_tco[i] == 1.0  # from the file name

    recorded = tracks(VALID)
    t0 = max(t[0] for t, _ in recorded.values())  # the later first stamp
    grid = t0 + DT * np.arange(100) - T0
    expected = np.stack([car_states(grid, *car) for car in VALID[0]])  # [2, 100, 6]
    cut = int(np.argmax((expected[:, :, 0] >= CUTOFF_X).any(axis=0)))  # before the first car reaches x = 2
    assert trials.lengths[i] == cut
    states = trials.states[i, :, :cut]
    np.testing.assert_allclose(states[..., :4], expected[:, :cut, :4], atol=0.01)  # positions, speeds
    np.testing.assert_allclose(states[..., 4:], expected[:, :cut, 4:], atol=0.05)  # ydd has kinks


def test_equal_speeds_have_no_crossover_time_and_unknown_drivers(imported):
    trials = imported.trials
    i = trials.sources.tolist().index("pair/15:44:04_29_1_0_2_1.bag")
    assert trials.ic_dv[i] == 0.0
    assert np.isnan(trials.ic_tco[i])
    assert trials.drivers[i].tolist() == [-1, -1]


def test_import_round_trips_through_parquet(imported, tmp_path):
    imported.trials.write_parquet(tmp_path / "bags.parquet")
    back = load_trials(tmp_path / "bags.parquet")
    np.testing.assert_array_equal(back.lengths, imported.trials.lengths)
    np.testing.assert_allclose(back.states, imported.trials.states)
    assert back.metadata == {"importer": "rosbag"}


def test_sanitise_trims_the_neighbouring_trials():
    grid = np.arange(0, 7, DT)
    states = np.stack([car_states(grid, *car) for car in VALID[0]])  # [2, T, 6]
    kept = sanitise(states)
    previous = np.repeat(states[:, -1:], 3, axis=1)  # the last trial's end, both cars past x = 20
    crash = states[:, -1:].copy()
    crash[1] = crash[0]  # both cars in one place after the end of the recording
    padded = np.concatenate([previous, states, np.repeat(crash, 3, axis=1)], axis=1)
    np.testing.assert_array_equal(sanitise(padded), kept)
    with pytest.raises(BagRejected) as rejected:
        sanitise(states[:, 40:])
    assert rejected.value.reason == "start_not_recorded"


def test_sanitise_rejects_a_valid_but_short_trial():
    grid = np.arange(0, 3, DT)
    fast = [(-101.0, 60.0, LEFT, RIGHT, 0.3, 1.2), (-108.0, 60.0, RIGHT, LEFT, 0.3, 1.2)]  # at x = 2 after 18 steps
    with pytest.raises(BagRejected) as rejected:
        sanitise(np.stack([car_states(grid, *car) for car in fast]))
    assert rejected.value.reason == "too_short"


def test_directory_errors(tmp_path, bag_dir):
    with pytest.raises(InputError, match="no such directory"):
        read_rosbags(tmp_path / "nope")
    with pytest.raises(InputError, match="no .bag files"):
        read_rosbags(tmp_path)
    with pytest.raises(InputError) as error:
        read_rosbags(bag_dir / "02")
    message = str(error.value)
    assert "\n" not in message
    assert "no valid trials among 7 bags" in message
    assert "unreadable 2" in message


@pytest.mark.parametrize("seed", range(6))
def test_corrupt_bags_are_rejected_one_by_one_while_the_others_import(tmp_path, seed):
    """Random bytes, random truncations and random overwritten spans of a valid bag: each corrupt
    bag gets a rejection reason (never an exception) and the intact bag still imports."""
    rng = np.random.default_rng(seed)
    write_bag(tmp_path / "01" / "15:48:04_29_0_2_1_3.bag", tracks(VALID))
    whole = (tmp_path / "01" / "15:48:04_29_0_2_1_3.bag").read_bytes()
    corrupt = {
        "16:00:00_29_0_2_1_1.bag": rng.bytes(int(rng.integers(1, 50_000))),
        "16:00:01_29_0_2_1_1.bag": whole[: int(rng.integers(0, len(whole)))],
        "16:00:02_29_0_2_1_1.bag": whole[:13] + rng.bytes(int(rng.integers(1, 5_000))),
    }
    spliced = bytearray(whole)
    at = int(rng.integers(13, len(whole) - 64))
    spliced[at : at + 64] = rng.bytes(64)
    corrupt["16:00:03_29_0_2_1_1.bag"] = bytes(spliced)
    for name, data in corrupt.items():
        (tmp_path / "02" / name).parent.mkdir(exist_ok=True)
        (tmp_path / "02" / name).write_bytes(data)

    result = read_rosbags(tmp_path)
    outcomes = dict(result.files)
    assert outcomes["01/15:48:04_29_0_2_1_3.bag"] == "ok"
    assert outcomes["02/16:00:00_29_0_2_1_1.bag"] == "unreadable"
    assert outcomes["02/16:00:02_29_0_2_1_1.bag"] == "unreadable"
    assert all(outcome == "ok" or outcome in REJECT_REASONS for outcome in outcomes.values())
    assert len(result.trials) == sum(outcome == "ok" for outcome in outcomes.values()) >= 1


def test_a_folder_of_only_unreadable_bags_is_one_input_error(tmp_path):
    (tmp_path / "16:00:00_29_0_2_1_1.bag").write_bytes(b"")
    (tmp_path / "16:00:01_29_0_2_1_1.bag").write_bytes(np.random.default_rng(0).bytes(1000))
    with pytest.raises(InputError) as error:
        read_rosbags(tmp_path)
    assert str(error.value) == f"{tmp_path}: no valid trials among 2 bags (rejected: unreadable 2)"


def test_not_a_folder_is_an_input_error(tmp_path):
    bag = tmp_path / "15:48:04_29_0_2_1_3.bag"
    write_bag(bag, tracks(VALID))
    with pytest.raises(InputError, match="no such directory"):
        read_rosbags(bag)


def test_sanitise_rejects_implausible_values_before_the_validity_rules():
    grid = np.arange(0, 7, DT)
    states = np.stack([car_states(grid, *car) for car in VALID[0]])  # [2, T, 6]
    states[0, 10, 1] = -60.0  # 60 m to the right of the road: implausible rather than off_road
    with pytest.raises(BagRejected) as rejected:
        sanitise(states)
    assert rejected.value.reason == "implausible"
