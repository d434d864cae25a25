"""Closed-loop evaluation: episode metrics on hand-built records, aggregates and their intervals,
episodes from (seed, index), batches (determinism across workers and engines, resume, a failing
episode) and the ``simulate`` command."""

from __future__ import annotations

import json
import os
import sys

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from helpers_model import small_checkpoint, synthetic_trials
from trafficweaving.cli import main
from trafficweaving.data.trials import TrialSet, load_trials
from trafficweaving.errors import InputError
from trafficweaving.planning.planner import Budget
from trafficweaving.scenario import (CAR_LENGTH, COLLISION_DX, CUTOFF_X, DT, LANE_CENTRE_Y, REPLAN_PERIOD_S,
                                    START_X, SWAP_THRESHOLD_Y, lane_of, study_initial_conditions, time_to_collision)
from trafficweaving.sim.batch import EpisodeFailed, episode_path, simulate
from trafficweaving.sim.episodes import EpisodeSpec, run_episode
from trafficweaving.sim.metrics import (Z95, aggregate, episode_metrics, lane_reversals, latency_summary, mean_interval,
                                        wilson_interval)
from trafficweaving.sim.score import COMFORT_LIMITS, SCORE_WEIGHTS, comfort_violations, comfort_violations_by_limit

LEFT, RIGHT = LANE_CENTRE_Y["left"], LANE_CENTRE_Y["right"]
T = 80  # steps of a hand-built record: 8 s at 30 m/s from START_X ends 95 m past the cutoff


# ---------------------------------------------------------------- hand-built records
def car(x0: float, speed: float, y_from: float, y_to: float | None = None, change: tuple[int, int] = (20, 50),
        accel: float = 0.0) -> np.ndarray:
    """One car's states ``[T, 6]``: longitudinal ``x0 + speed·t + accel·t²/2``, a lane change
    from ``y_from`` to ``y_to`` between the steps ``change`` (smoothstep), velocities and
    accelerations by differences."""
    t = np.arange(T) * DT
    x = x0 + speed * t + 0.5 * accel * t**2
    s = np.clip((np.arange(T) - change[0]) / (change[1] - change[0]), 0, 1)
    y = np.full(T, y_from) if y_to is None else y_from + (y_to - y_from) * s * s * (3 - 2 * s)
    xd, yd = np.gradient(x, DT), np.gradient(y, DT)
    return np.stack([x, y, xd, yd, np.full(T, accel), np.gradient(yd, DT)], axis=1)


def metrics(robot: np.ndarray, human: np.ndarray, robot_index: int = 0) -> dict:
    states = np.stack([robot, human] if robot_index == 0 else [human, robot])
    return episode_metrics(states, T, robot_index)


def test_clean_weave_robot_first():
    """The robot (left, 10 m ahead) and the human swap lanes: success, the robot passed first."""
    m = metrics(car(START_X + 10, 30, LEFT, RIGHT), car(START_X, 30, RIGHT, LEFT))
    assert m["outcome"] == "valid" and m["success"] and m["robot_swapped"] and m["human_swapped"]
    assert not m["collision"] and not m["near_collision"] and m["robot_first"]
    assert m["min_gap_m"] == pytest.approx(10.0)  # |Δx| while the cars overlap laterally
    assert m["min_distance_m"] == pytest.approx(10.0)
    assert m["time_to_swap_s"] == pytest.approx(3.5, abs=0.1 + 1e-9)  # steps 20..50: across the divider mid-way
    assert m["accel_rms"]["longitudinal"] == pytest.approx(0.0) and m["accel_rms"]["lateral"] > 0


def test_who_passed_first_and_robot_index():
    """The human ahead at the cutoff passed first, whichever car index the robot has."""
    for robot_index in (0, 1):
        m = metrics(car(START_X, 30, LEFT, RIGHT), car(START_X + 12, 30, RIGHT, LEFT), robot_index)
        assert m["success"] and not m["robot_first"]


def test_collision():
    """The robot runs into the human from behind in the same lane: a collision, also a near one."""
    m = metrics(car(START_X - 30, 34, LEFT, RIGHT, change=(60, 75)), car(START_X, 28, LEFT))
    assert m["outcome"] == "collision" and m["collision"] and m["near_collision"] and m["robot_at_fault"]
    assert not m["success"] and m["min_gap_m"] < COLLISION_DX
    # the same, the human running into the robot: a collision the robot is not at fault for
    hit = metrics(car(START_X, 28, LEFT), car(START_X - 30, 34, LEFT, RIGHT, change=(60, 75)))
    assert hit["collision"] and not hit["robot_at_fault"]


def test_near_collision_without_collision():
    """The robot cuts in 6 m ahead: inside J_c's |Δs| < 8 m, |Δτ| < 2 m, outside the collision box."""
    m = metrics(car(START_X + 6, 30, LEFT, RIGHT, change=(10, 30)), car(START_X, 30, RIGHT, LEFT, change=(32, 45)))
    assert m["near_collision"] and not m["collision"] and m["success"] and m["outcome"] == "valid"
    assert COLLISION_DX < m["min_gap_m"] < 8.0


def test_off_road():
    """The robot leaves the road while changing lane: no success, its own part failed too; the
    human leaves it: no success, but the robot did its part."""
    m = metrics(car(START_X + 10, 30, LEFT, -9.0, change=(15, 40)), car(START_X, 30, RIGHT, LEFT))
    assert m["outcome"] == "off_road" and not m["success"] and m["robot_swapped"] and not m["robot_success"]
    m = metrics(car(START_X + 10, 30, LEFT, RIGHT), car(START_X, 30, RIGHT, -0.5))
    assert m["outcome"] == "off_road" and not m["success"] and m["robot_swapped"] and m["robot_success"]


def test_late_swap():
    """The robot crosses SWAP_THRESHOLD_Y only after passing the cutoff: no success; the time it
    crossed the divider is still reported."""
    robot = car(START_X + 10, 30, LEFT, RIGHT, change=(62, 75))
    assert robot[55, 0] >= CUTOFF_X and robot[55, 1] > SWAP_THRESHOLD_Y  # at the cutoff still in its lane
    m = metrics(robot, car(START_X, 30, RIGHT, LEFT))
    assert m["outcome"] == "no_lane_swap" and not m["robot_swapped"] and m["human_swapped"] and not m["success"]
    assert m["time_to_swap_s"] > 6.2


def test_human_stays_robot_succeeds():
    """Only the human fails to swap: the record breaks the lane-swap rule, the robot succeeded."""
    m = metrics(car(START_X + 10, 30, LEFT, RIGHT), car(START_X + 30, 30, RIGHT))
    assert m["outcome"] == "no_lane_swap" and m["success"] and not m["human_swapped"]
    assert m["min_gap_m"] == pytest.approx(20.0)


def test_accel_and_jerk_rms():
    robot = car(START_X + 10, 30, LEFT, RIGHT, accel=-1.5)
    robot[40:, 4] = 0.5  # one jump of the longitudinal acceleration: jerk 2 m/s² / 0.1 s at one of 79 differences
    m = metrics(robot, car(START_X - 20, 30, RIGHT, LEFT))
    assert m["accel_rms"]["longitudinal"] == pytest.approx(np.sqrt((40 * 1.5**2 + 40 * 0.5**2) / 80))
    assert m["jerk_rms"]["longitudinal"] == pytest.approx(20.0 / np.sqrt(79))


def test_latency_summary():
    s = latency_summary([0.1, 0.2, REPLAN_PERIOD_S + 0.01, 0.5])
    assert s["plans"] == 4 and s["median_s"] == pytest.approx(0.255) and s["deadline_misses"] == 2
    assert latency_summary([]) == {"plans": 0, "median_s": None, "p99_s": None, "deadline_misses": 0}


# ---------------------------------------------------------------- the closed-loop score
def test_score_of_a_clean_comfortable_weave_is_its_weighted_progress():
    robot = car(START_X + 10, 30, LEFT, RIGHT, change=(10, 60))  # 5 s lane change: within the comfort limits
    m = metrics(robot, car(START_X, 30, RIGHT, LEFT, change=(20, 70)))
    score = m["score"]
    assert all(score["multipliers"].values()) and score["ttc"] == 1.0 and score["comfort"] == 1.0
    assert score["comfort_violations"] == 0 and score["steps"] == T and m["lane_reversals"] == 0
    crossed = np.flatnonzero(lane_of(robot[:, 1]) != "left")[0]
    progress = 0.5 * ((CUTOFF_X - robot[crossed, 0]) / (CUTOFF_X - robot[0, 0]) + 1.0)  # speed kept: 1
    assert score["progress"] == pytest.approx(progress)
    assert score["score"] == pytest.approx((SCORE_WEIGHTS["ttc"] + SCORE_WEIGHTS["progress"] * progress
                                            + SCORE_WEIGHTS["comfort"]) / sum(SCORE_WEIGHTS.values()))


def test_an_earlier_swap_at_the_kept_speed_scores_more_progress():
    human = car(START_X, 30, RIGHT, LEFT, change=(20, 70))
    early = metrics(car(START_X + 10, 30, LEFT, RIGHT, change=(5, 55)), human)["score"]
    late = metrics(car(START_X + 10, 30, LEFT, RIGHT, change=(25, 75)), human)["score"]
    slow = metrics(car(START_X + 10, 30, LEFT, RIGHT, change=(5, 55), accel=-1.0), human)["score"]
    assert early["progress"] > late["progress"] and early["progress"] > slow["progress"]


@pytest.mark.parametrize("record, multiplier", [
    (lambda: (car(START_X - 30, 34, LEFT, RIGHT, change=(60, 75)), car(START_X, 28, LEFT)), "no_collision"),
    (lambda: (car(START_X + 10, 30, LEFT, RIGHT, change=(62, 75)), car(START_X, 30, RIGHT, LEFT)), "lane_swap"),
    (lambda: (car(START_X + 10, 30, LEFT, -9.0, change=(15, 40)), car(START_X, 30, RIGHT, LEFT)), "on_road"),
    (lambda: (car(START_X + 10, 10, LEFT, RIGHT, change=(10, 40)), car(START_X, 30, RIGHT, LEFT)), "reaches_cutoff"),
])  # the crawling robot (10 m/s) swaps lanes on the road, but is 55 m short of the cutoff after 8 s
def test_a_collision_no_swap_leaving_the_road_or_not_reaching_the_cutoff_zeroes_the_score(record, multiplier):
    m = metrics(*record())
    score = m["score"]
    assert score["score"] == 0.0 and not score["multipliers"][multiplier]
    assert not m["robot_success"]


def test_a_harsh_lane_change_breaks_comfort_and_a_close_cut_breaks_ttc():
    human = car(START_X - 40, 30, RIGHT, LEFT, change=(20, 70))
    harsh = metrics(car(START_X + 10, 30, LEFT, RIGHT, change=(20, 30)), human)["score"]  # 1 s: over 20 m/s²
    assert harsh["comfort"] == 0.0 and harsh["comfort_violations"] > 0 and harsh["score"] > 0
    by_limit = harsh["comfort_violations_by_limit"]
    assert by_limit["lateral_accel"] > 0 and max(by_limit.values()) <= harsh["comfort_violations"] <= sum(by_limit.values())
    assert comfort_violations(car(START_X, 30, LEFT, RIGHT, change=(20, 30))[:, 4:6]).any()
    # 12 m behind the human in its lane and 3 m/s faster, the robot leaves the lane with 0.9 m to spare
    close = metrics(car(START_X - 12, 31, LEFT, RIGHT, change=(5, 45)), car(START_X, 28, LEFT))
    assert not close["collision"] and close["score"]["ttc"] == 0.0 and close["score"]["score"] > 0
    ttc = time_to_collision(car(START_X - 12, 31, LEFT), car(START_X, 28, LEFT))
    np.testing.assert_allclose(ttc[0], (12 - CAR_LENGTH) / 3.0)
    assert np.isinf(time_to_collision(car(START_X, 31, LEFT), car(START_X - 12, 28, LEFT))).all()  # opening gap


@pytest.mark.parametrize("xdd, ydd, broken", [
    (-5.0, 0.0, {"longitudinal_accel"}),  # braking harder than -4.05 m/s², held: no jerk
    (0.0, 5.0, {"lateral_accel"}),
    ((0.0, 0.5), 0.0, {"longitudinal_jerk"}),  # a 0.5 m/s² step in 0.1 s: 5 m/s³ along, under 8.37 in all
    (0.0, (0.0, 1.0), {"jerk"}),  # 10 m/s³ sideways: only the total jerk has a limit there
    ((0.0, 1.0), 0.0, {"longitudinal_jerk", "jerk"}),
    (2.0, 4.0, set()),
])
def test_comfort_violations_name_the_limit_each_step_breaks(xdd, ydd, broken):
    steps = 10
    column = lambda v: np.full(steps, v) if np.isscalar(v) else np.where(np.arange(steps) < 5, *v)  # noqa: E731
    acc = np.stack([column(xdd), column(ydd)], axis=1)
    by_limit = comfort_violations_by_limit(acc)
    assert set(by_limit) == set(COMFORT_LIMITS) and {k for k, v in by_limit.items() if v.any()} == broken
    np.testing.assert_array_equal(comfort_violations(acc), np.logical_or.reduce(list(by_limit.values())))
    assert not any(v[0] for k, v in by_limit.items() if "jerk" in k)  # no jerk at the first step


def test_lane_reversals_count_turns_back_towards_the_start_lane():
    steps = np.arange(60)
    towards, back = -1.0, 1.0  # from the left lane the target lies at smaller y
    yd = np.where(steps < 20, towards, np.where(steps < 30, back, towards))
    y = LEFT + np.cumsum(yd) * DT
    assert lane_reversals(y, yd) == 1
    assert lane_reversals(y, np.where(steps < 20, towards, 0.1 * back)) == 0  # slower than REVERSAL_SPEED: not counted
    chatter = np.concatenate([np.full(20, towards), np.tile([back, towards], 5)])  # settling with chatter
    assert lane_reversals(LEFT + np.cumsum(chatter) * DT, chatter) == 5


def test_lateral_swings_count_sign_changes_of_the_lateral_acceleration_above_the_threshold():
    from trafficweaving.planning.candidates import KINEMATICS, Action, rollout
    from trafficweaving.sim.metrics import SWING_ACCEL, lateral_swings

    change = rollout(np.array([START_X, RIGHT, 30.0, 0.0, 0.0, 0.0]), np.array([[Action.of(0.0, "left").index] * 15]),
                     KINEMATICS["settled"])[0, :, 5]  # one steady lane change
    assert lateral_swings(change) == 1
    chatter = np.tile([0.7, -0.7, 0.0], 10)
    assert lateral_swings(np.concatenate([change, chatter])) == 1 + 20
    assert lateral_swings(np.concatenate([change, 0.9 * SWING_ACCEL * np.sign(chatter)])) == 1  # below the threshold


# ---------------------------------------------------------------- aggregates
def test_wilson_interval_ends_and_middle():
    for n in (1, 7, 100):
        assert wilson_interval(0, n) == [0.0, pytest.approx(Z95**2 / (n + Z95**2))]
        assert wilson_interval(n, n) == [pytest.approx(n / (n + Z95**2)), 1.0]
    assert wilson_interval(5, 10) == [pytest.approx(0.2366, abs=1e-4), pytest.approx(0.7634, abs=1e-4)]
    assert wilson_interval(0, 0) is None


def test_mean_interval():
    s = mean_interval([1.0, 2.0, 3.0, None])
    assert s["n"] == 3 and s["mean"] == 2.0
    assert s["ci95"] == [pytest.approx(2 - 2.4841, abs=1e-4), pytest.approx(2 + 2.4841, abs=1e-4)]
    assert mean_interval([4.0]) == {"n": 1, "mean": 4.0, "ci95": None}
    assert mean_interval([None]) == {"n": 0, "mean": None, "ci95": None}


def test_aggregate_breakdown():
    """Rates over all episodes, and per (Δv, tco, robot lane) with Δv = 0 merged over tco."""
    good = metrics(car(START_X + 10, 30, LEFT, RIGHT), car(START_X, 30, RIGHT, LEFT))
    crash = metrics(car(START_X - 30, 34, LEFT, RIGHT, change=(60, 75)), car(START_X, 28, LEFT))
    ics = [{"dv": 0.0, "tco": 1.0, "robot_lane": "left"}, {"dv": 0.0, "tco": 3.0, "robot_lane": "left"},
           {"dv": 2.0, "tco": 1.0, "robot_lane": "right"}]
    records = [{"metrics": m, "initial_condition": ic, "latencies_s": lat}
               for m, ic, lat in zip((good, good, crash), ics, ([0.1, 0.2], [0.4], []))]
    s = aggregate(records)
    assert s["episodes"] == 3 and s["collisions"] == 1 and s["near_collisions"] == 1 and s["robot_at_fault_collisions"] == 1
    old_log = [{**r, "metrics": {k: v for k, v in r["metrics"].items() if k != "robot_at_fault"}} for r in records]
    assert aggregate(old_log)["robot_at_fault_collisions"] is None  # unknown, not "not at fault"
    assert s["success_rate"]["count"] == 2 and s["success_rate"]["ci95"] == wilson_interval(2, 3)
    assert s["robot_success_rate"]["count"] == 2 and not crash["robot_success"] and good["robot_success"]
    assert s["outcomes"]["valid"] == 2 and s["outcomes"]["collision"] == 1
    assert s["planner_latency_s"]["plans"] == 3 and s["planner_latency_s"]["median"] == pytest.approx(0.2)
    assert s["deadline_misses"] == 1
    rows = [(r["dv"], r["tco"], r["robot_lane"], r["episodes"]) for r in s["by_initial_condition"]]
    assert rows == [(0.0, None, "left", 2), (2.0, 1.0, "right", 1)]
    assert s["by_initial_condition"][0]["success_rate"]["ci95"] == wilson_interval(2, 2)
    assert s["score"]["n"] == 3 and s["score"]["mean"] == pytest.approx(2 * good["score"]["score"] / 3)
    assert s["score_parts"]["no_collision"]["count"] == 2 and s["score_parts"]["progress"]["n"] == 3
    assert s["lane_reversals"]["at_most_one"]["count"] == 3
    assert s["comfort_violation_steps"]["steps"] == 3 * T
    by_limit = s["comfort_violation_steps"]["by_limit"]
    for k in COMFORT_LIMITS:  # each limit's steps and episodes summed over the three
        assert by_limit[k]["steps"] == sum(r["metrics"]["score"]["comfort_violations_by_limit"][k] for r in records)
        assert by_limit[k]["episodes"] == sum(r["metrics"]["score"]["comfort_violations_by_limit"][k] > 0 for r in records)
    older = [{**r, "metrics": {**r["metrics"], "score": {k: v for k, v in r["metrics"]["score"].items()
                                                         if k != "comfort_violations_by_limit"}}} for r in records]
    assert aggregate(older)["comfort_violation_steps"]["by_limit"] is None  # a log from before the breakdown
    json.dumps(s, allow_nan=False)


# ---------------------------------------------------------------- episodes with scripted agents
class ConstantSpeed:
    """A scripted car that keeps its speed and lane."""

    def reset(self, rng, start, me):
        self.me = me

    def act(self, history):
        return np.zeros((len(history), 2))


class LaneChanger:
    """A scripted car that changes lane with a fixed lateral acceleration profile from step 15
    (+a for 10 steps, −a for 10 steps) towards the other lane."""

    def reset(self, rng, start, me):
        self.direction = np.where(start[:, me, 1] > SWAP_THRESHOLD_Y, -1.0, 1.0)
        self.latencies = [0.0]

    def act(self, history):
        t = history.shape[2]
        a = 4.26 / (10 * DT) ** 2 * (1.0 if 15 <= t < 25 else -1.0 if 25 <= t < 35 else 0.0)
        return np.stack([np.zeros(len(history)), a * self.direction], axis=1)


def test_episode_from_seed_and_index():
    """The initial condition and the robot's car come from (seed, index) alone; the record is a
    valid one-trial dataset with roles and the episode's JSON record."""
    spec = EpisodeSpec("scripted", "scripted", seed=3)
    agents = (LaneChanger(), ConstantSpeed())
    episodes = [run_episode(spec, i, agents) for i in range(12)]
    again = run_episode(spec, 5, (LaneChanger(), ConstantSpeed()))
    np.testing.assert_array_equal(again.trials.states, episodes[5].trials.states)
    assert again.record["metrics"] == episodes[5].record["metrics"]
    assert {e.record["robot_car"] for e in episodes} == {0, 1}
    assert len({e.record["initial_condition"]["index"] for e in episodes}) > 4
    ics = study_initial_conditions()
    for e in episodes:
        ic, robot = e.record["initial_condition"], e.record["robot_car"]
        np.testing.assert_array_equal(e.trials.states[0, :, 0], ics[ic["index"]].start_states())
        assert e.trials.roles[0, robot] == "robot" and e.trials.roles[0, 1 - robot] == "human"
        assert e.trials.start_lanes[0, robot] == ic["robot_lane"] and e.record["latencies_s"] == [0.0]
        assert e.record["metrics"]["robot_swapped"] and not e.record["metrics"]["human_swapped"]
        assert e.trials.sources[0] == f"episode-{e.index:06d}" and e.trials.trial_ids[0] == e.index


# ---------------------------------------------------------------- batches
def tables(out, n: int) -> list:
    """The episode logs' tables without their metadata (latencies differ from run to run)."""
    return [pq.read_table(episode_path(out, i)).replace_schema_metadata(None) for i in range(n)]


def records(out, n: int) -> list[dict]:
    return [load_trials(episode_path(out, i)).metadata["episode"] for i in range(n)]


@pytest.fixture(scope="module")
def inline_run(tmp_path_factory):
    """4 episodes of the rules robot against simulated drivers, in this process."""
    out = tmp_path_factory.mktemp("inline")
    return out, simulate(4, "rules", "synthetic", seed=7, workers=1, out=out)


@pytest.mark.slow
def test_batch_writes_episodes_and_summary(inline_run):
    out, summary = inline_run
    assert sorted(p.name for p in (out / "episodes").iterdir()) == [f"episode_{i:06d}.parquet" for i in range(4)]
    assert json.loads((out / "summary.json").read_text())["success_rate"] == summary["success_rate"]
    assert summary["computed"] == 4 and summary["reused"] == 0 and summary["episodes"] == 4
    for i, record in enumerate(records(out, 4)):
        trials = load_trials(episode_path(out, i))
        assert record["index"] == i and sorted(trials.roles[0]) == ["human", "robot"]
        assert record["metrics"] == episode_metrics(trials.states[0], int(trials.lengths[0]), record["robot_car"])


@pytest.mark.slow
def test_workers_and_pool_give_the_same_episodes(inline_run, tmp_path):
    out, _ = inline_run
    simulate(4, "rules", "synthetic", seed=7, workers=2, out=tmp_path)
    assert all(a.equals(b) for a, b in zip(tables(out, 4), tables(tmp_path, 4)))
    assert [r["metrics"] for r in records(out, 4)] == [r["metrics"] for r in records(tmp_path, 4)]


@pytest.mark.slow
def test_episodes_run_on_two_threads_are_the_same_episodes(inline_run, tmp_path):
    out, _ = inline_run
    before = torch.get_num_threads()
    summary = simulate(4, "rules", "synthetic", seed=7, workers=1, out=tmp_path, threads=2)
    assert summary["threads"] == 2 and torch.get_num_threads() == before  # the caller's setting is restored
    assert all(a.equals(b) for a, b in zip(tables(out, 4), tables(tmp_path, 4)))


@pytest.mark.slow
def test_ray_gives_the_same_episodes(inline_run, tmp_path):
    ray = pytest.importorskip("ray")
    out, _ = inline_run
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        summary = simulate(4, "rules", "synthetic", seed=7, workers=2, engine="ray", out=tmp_path)
    finally:
        ray.shutdown()
    assert summary["engine"] == "ray" and summary["computed"] == 4
    assert all(a.equals(b) for a, b in zip(tables(out, 4), tables(tmp_path, 4)))
    assert [r["metrics"] for r in records(out, 4)] == [r["metrics"] for r in records(tmp_path, 4)]


def test_resume_recomputes_only_missing_episodes(inline_run, tmp_path):
    out, first = inline_run
    for i in range(4):
        (tmp_path / "episodes").mkdir(exist_ok=True)
        episode_path(tmp_path, i).write_bytes(episode_path(out, i).read_bytes())
    episode_path(tmp_path, 2).unlink()
    kept = {i: os.stat(episode_path(tmp_path, i)).st_mtime_ns for i in (0, 1, 3)}
    summary = simulate(4, "rules", "synthetic", seed=7, out=tmp_path)
    assert summary["computed"] == 1 and summary["reused"] == 3
    assert {i: os.stat(episode_path(tmp_path, i)).st_mtime_ns for i in (0, 1, 3)} == kept
    assert tables(tmp_path, 4)[2].equals(tables(out, 4)[2])
    for key in ("success_rate", "collisions", "near_collisions", "min_gap_m", "by_initial_condition"):
        assert summary[key] == first[key]
    with pytest.raises(InputError, match=r"episode_000000\.parquet: an episode of another run"):
        simulate(4, "rules", "synthetic", seed=8, out=tmp_path)


def test_a_run_logged_before_the_precision_option_resumes(inline_run, tmp_path):
    out, _ = inline_run
    (tmp_path / "episodes").mkdir()
    for i in range(4):
        trials = load_trials(episode_path(out, i))
        del trials.metadata["episode"]["spec"]["precision"]  # as logged by the release before it
        trials.write_parquet(episode_path(tmp_path, i))
    assert "precision" not in load_trials(episode_path(tmp_path, 0)).metadata["episode"]["spec"]
    assert simulate(4, "rules", "synthetic", seed=7, out=tmp_path)["reused"] == 4
    with pytest.raises(InputError, match="an episode of another run"):
        simulate(4, "rules", "synthetic", seed=7, out=tmp_path, precision="int8")


def test_a_resumed_episode_is_measured_again_by_this_release(inline_run, tmp_path):
    """An episode logged with other metrics (an earlier release's) gets this release's, in the
    summary and in its rewritten file; files whose metrics agree are left alone."""
    out, first = inline_run
    (tmp_path / "episodes").mkdir()
    for i in range(4):
        episode_path(tmp_path, i).write_bytes(episode_path(out, i).read_bytes())
    stale = load_trials(episode_path(tmp_path, 1))
    del stale.metadata["episode"]["metrics"]["score"]["multipliers"]["reaches_cutoff"]  # as logged before it
    stale.metadata["episode"]["metrics"]["score"]["score"] = 0.123
    stale.write_parquet(episode_path(tmp_path, 1))
    kept = {i: os.stat(episode_path(tmp_path, i)).st_mtime_ns for i in (0, 2, 3)}
    summary = simulate(4, "rules", "synthetic", seed=7, out=tmp_path)
    assert summary["reused"] == 4 and summary["score"] == first["score"]
    assert records(tmp_path, 4)[1]["metrics"] == records(out, 4)[1]["metrics"]
    assert {i: os.stat(episode_path(tmp_path, i)).st_mtime_ns for i in (0, 2, 3)} == kept


@pytest.fixture(scope="module")
def planner_run(tmp_path_factory):
    """One episode of the paper's planner with a tiny budget and a small CVAE human model
    (helpers_model.small_checkpoint), sampling at an explicit float32 (at int8 or bfloat16 it runs the
    compiled decoder steps: minutes on a CPU without AVX-512; int8 sampling itself is tested in
    tests/model/test_predictor.py)."""
    out = tmp_path_factory.mktemp("planner")
    model = small_checkpoint(out / "small.pt", synthetic_trials(4, seed=0))
    return out, simulate(1, "planner", "synthetic", seed=0, out=out / "run", budget=Budget(1, 1, 2), precision="float32",
                         model=str(model))


@pytest.mark.slow
def test_planner_episode_with_a_tiny_budget(planner_run):
    """The planner in the loop: plans are timed and counted."""
    out, summary = planner_run
    record = records(out / "run", 1)[0]
    assert summary["planner_latency_s"]["plans"] == len(record["latencies_s"]) > 10
    assert record["spec"]["budget"] == [1, 1, 2] and summary["deadline_misses"] == record["latency"]["deadline_misses"]


@pytest.mark.slow
def test_the_planner_samples_at_the_precision_asked_for(planner_run, tmp_path):
    """precision reaches the planner's human model and is logged; an unknown one is refused before
    any episode runs."""
    for precision in ("int8", "float32"):
        robot, _ = EpisodeSpec("planner", "synthetic", 0, budget=Budget(1, 1, 2), precision=precision).agents()
        assert robot.planner.human_model.precision == precision
    assert records(planner_run[0] / "run", 1)[0]["spec"]["precision"] == "float32"
    with pytest.raises(InputError, match="precision must be one of"):
        simulate(1, "planner", "synthetic", seed=0, out=tmp_path / "other", precision="fp8")


def test_replaying_an_episode_reproduces_it(inline_run):
    """A replayed human starts from the recording's start; replaying a rules-robot episode against
    the (deterministic) rules robot gives the recorded episode back, the robot as car 0."""
    path = episode_path(inline_run[0], 1)
    recorded = load_trials(path)
    episode = run_episode(EpisodeSpec("rules", f"replay:{path}", seed=0), 5)
    robot = int(np.flatnonzero(recorded.roles[0] == "robot")[0])
    assert episode.record["robot_car"] == 0 and episode.record["initial_condition"]["trial"] == 1
    np.testing.assert_array_equal(episode.trials.states[0], recorded.states[0, [robot, 1 - robot]])
    assert episode.record["metrics"] == recorded.metadata["episode"]["metrics"]


@pytest.fixture
def broken_replay(inline_run, tmp_path) -> str:
    """A recording of 2 trials whose second human accelerates absurdly (its states overflow)."""
    trials = load_trials(episode_path(inline_run[0], 0))
    bad = trials.subset([0])
    bad.states = bad.states.copy()
    bad.states[0, np.flatnonzero(bad.roles[0] == "human")[0], :, 4] = 1.7e308
    path = tmp_path / "replay.parquet"
    TrialSet.concatenate([trials, bad]).write_parquet(path)
    return str(path)


@pytest.mark.slow
def test_failing_episode_stops_the_pool(broken_replay, tmp_path):
    out = tmp_path / "run"
    with pytest.raises(EpisodeFailed, match=r"^episode 1 failed: InputError: history has NaN") as failure:
        simulate(4, "planner-cv", f"replay:{broken_replay}", workers=2, out=out, budget=Budget(1, 1, 1))
    assert failure.value.index == 1
    assert not (out / "summary.json").exists()
    assert all(p.suffix == ".parquet" for p in out.glob("episodes/*"))  # finished episodes only, no temporary files


# ---------------------------------------------------------------- the command
def test_cli_json(tmp_path, capsys):
    assert main(["simulate", "--episodes", "2", "--robot", "rules", "--human", "synthetic", "--seed", "1",
                 "--out", str(tmp_path), "--json"]) == 0
    payload = json.loads(capsys.readouterr().out)
    for key in ("episodes", "collisions", "success_rate", "near_collisions", "min_gap_m", "planner_latency_s",
                "deadline_misses", "by_initial_condition"):
        assert key in payload
    assert payload["episodes"] == 2 and set(payload["success_rate"]) >= {"rate", "ci95"}
    assert set(payload["planner_latency_s"]) >= {"median", "p99"}
    assert main(["simulate", "--episodes", "2", "--robot", "rules", "--human", "synthetic", "--seed", "1",
                 "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert "2 episodes" in text and "2 reused" in text and "success" in text


@pytest.mark.slow
def test_cli_defaults_to_the_real_time_planner_in_a_simulation_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "--episodes", "1", "--human", "synthetic", "--json"]) == 0
    payload = json.loads(capsys.readouterr().out)
    assert payload["robot"] == "planner" and payload["deadline"] == 0.3
    assert (tmp_path / "simulation" / "summary.json").is_file()
    assert main(["simulate", "--episodes", "1", "--robot", "rules", "--human", "synthetic", "--full-budget",
                 "--out", "rules", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["deadline"] is None
    assert main(["simulate", "--episodes", "1", "--full-budget", "--deadline", "0.2"]) == 2
    assert "not allowed with argument" in capsys.readouterr().err


@pytest.mark.filterwarnings("ignore:overflow encountered")
def test_cli_failing_episode(broken_replay, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["simulate", "--episodes", "1", "--robot", "planner-cv", "--human", f"replay:{broken_replay}#1",
                 "--out", str(out), "--json"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("trafficweaving simulate: error: episode 0 failed") and "\n" not in err
    assert not (out / "summary.json").exists()


@pytest.mark.parametrize("options, message", [
    (["--robot", "robot9"], "robot9"),
    (["--human", "alien"], "human 'alien' is unknown"),
    (["--robot", "planner", "--model", "authors:/nonexistent/weights.npz"], "--model authors:/nonexistent/weights.npz: no such file"),
    (["--episodes", "0"], "argument --episodes: expected an integer in 1..100000, got 0"),
    (["--workers", "0"], "argument --workers: expected an integer >= 1, got 0"),
    (["--deadline", "nan"], "argument --deadline: expected a finite number"),
    (["--engine", "local", "--address", "auto"], "applies only to the ray engine"),
    (["--threads", "2", "--workers", "2"], "threads 2 applies to episodes run in this process"),
])
def test_cli_bad_input(options, message, tmp_path, capsys):
    out = tmp_path / "run"
    base = {"--episodes": "2", "--robot": "rules", "--human": "synthetic", "--out": str(out)}
    for name, value in zip(options[::2], options[1::2]):
        base[name] = value
    assert main(["simulate", *[v for item in base.items() for v in item]]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err
    assert not out.exists()  # no partial results


def test_cli_ray_missing(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # as if Ray were not installed
    out = tmp_path / "run"
    assert main(["simulate", "--episodes", "2", "--robot", "rules", "--human", "synthetic", "--engine", "ray",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "trafficweaving simulate: error: `--engine ray` needs Ray: pip install 'trafficweaving[ray]'"
    assert not out.exists()
