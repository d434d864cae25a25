"""The edge-case library (sim/scenarios.py, ``--human scenario:NAME``): each scenario's start, its
scripted human's behaviour against tiny scripted robots, spec parsing and the ``simulate``
command."""

from __future__ import annotations

import json

import numpy as np
import pytest

from trafficweaving.cli import main
from trafficweaving.dynamics import minimum_jerk_acceleration
from trafficweaving.errors import InputError
from trafficweaving.scenario import (CAR_LENGTH, DT, LANE_CENTRE_Y, LANE_DIVIDER_Y, ROAD_Y_MAX, ROAD_Y_MIN, colliding,
                                     lane_of)
from trafficweaving.sim.episodes import EpisodeSpec, run_episode
from trafficweaving.sim.humans import HUMAN_SPECS, HumanSpec, human_agent, parse_human_spec
from trafficweaving.sim.scenarios import SCENARIOS, SPEED_RANGE, ScriptedHuman
from trafficweaving.sim.world import run_episodes

NAMES = list(SCENARIOS)


class ScriptedRobot:
    """A tiny robot for the tests: accelerations ``[xdd, ydd]`` from ``script(t, start_y)`` (the
    step and the robot's start ``y`` of each episode)."""

    def __init__(self, script=lambda t, start_y: (0.0, 0.0)):
        self.script = script

    def reset(self, rng, start, me):
        self.me, self.start_y = me, start[:, me, 1].copy()

    def act(self, history):
        t = history.shape[2] - 1
        return np.array([self.script(t, y) for y in self.start_y], dtype=float)


def merging(step: int, duration: float = 2.5):
    """A robot script: at ``step`` it begins a lane change to the other lane over ``duration`` s."""
    def script(t, start_y):
        other = LANE_CENTRE_Y["right" if lane_of(start_y) == "left" else "left"]
        s = np.clip((t + 1 - step) * DT / duration, 0.0, 1.0)
        return 0.0, float(minimum_jerk_acceleration(other - start_y, s, duration))
    return script


def drive(name: str, robot: ScriptedRobot, m: int = 40, seed: int = 0) -> tuple[np.ndarray, dict]:
    """``m`` episodes of scenario ``name`` from its drawn starts against ``robot``: both cars'
    states ``[m, 2, T, 6]`` (the world to its last step) and the human's parameters."""
    rng = np.random.default_rng(seed)
    start, parameters = SCENARIOS[name].draw(rng, m)
    human = SCENARIOS[name].agent()
    human.bound = parameters
    world = run_episodes(start, [robot, human], rng, until_max_steps=True)
    return world.states, parameters


# ------------------------------------------------------------------ the starts
@pytest.mark.parametrize("name", NAMES)
def test_a_scenario_starts_on_the_road_in_lane_centres_with_the_robot_in_car_0(name):
    scenario = SCENARIOS[name]
    start, parameters = scenario.draw(np.random.default_rng(1), 200)
    robot, human = start[:, 0], start[:, 1]
    centres = sorted(LANE_CENTRE_Y.values())
    assert np.isin(robot[:, 1], centres).all() and np.isin(human[:, 1], centres).all()
    assert (lane_of(robot[:, 1]) != lane_of(human[:, 1])).all()  # the human in the other lane: both must swap
    assert {"left", "right"} == set(lane_of(robot[:, 1]))  # the robot's lane is drawn
    assert not colliding(robot, human).any()
    assert (start[..., 3:] == 0).all()  # no lateral motion, no acceleration
    assert scenario.robot_x[0] <= robot[:, 0].min() and robot[:, 0].max() <= scenario.robot_x[1]
    dx, dv = human[:, 0] - robot[:, 0], human[:, 2] - robot[:, 2]
    assert scenario.dx[0] <= dx.min() and dx.max() <= scenario.dx[1] and np.ptp(dx) > 0  # 200 episodes vary
    assert scenario.dv[0] <= dv.min() and dv.max() <= scenario.dv[1]
    assert 27.0 <= robot[:, 2].min() and robot[:, 2].max() <= 31.0
    assert list(parameters) == [p[0] for p in scenario.parameters]
    again = scenario.draw(np.random.default_rng(1), 200)
    np.testing.assert_array_equal(again[0], start)
    assert all(np.array_equal(again[1][k], v) for k, v in parameters.items())


@pytest.mark.parametrize("name", NAMES)
def test_a_scenario_episode_is_reproducible_and_records_what_is_acceptable(name):
    spec = EpisodeSpec("rules", f"scenario:{name}", seed=3)
    first, second = run_episode(spec, 5), run_episode(spec, 5)
    np.testing.assert_array_equal(first.trials.states, second.trials.states)
    record = first.record
    assert record["robot_car"] == 0 and list(first.trials.roles[0]) == ["robot", "human"]
    scenario = SCENARIOS[name]
    assert record["initial_condition"] == {
        "index": None, "dv": None, "tco": None, "robot_lane": str(lane_of(first.trials.states[0, 0, 0, 1])),
        "scenario": name, "avoidable": scenario.avoidable, "acceptable": scenario.acceptable}
    start, _ = scenario.draw(np.random.default_rng([3, 5]), 1)  # the episode's first draws
    np.testing.assert_array_equal(first.trials.states[0, :, 0], start[0])
    states = first.trials.states[0, :, : first.trials.lengths[0]]
    assert (ROAD_Y_MIN <= states[1, :, 1]).all() and (states[1, :, 1] <= ROAD_Y_MAX).all()


@pytest.mark.parametrize("name", NAMES)
def test_a_scripted_human_stays_physical_whatever_the_robot_does(name):
    """Against a robot that brakes to a stop, and one that accelerates hard, the human keeps to the
    road, to its speed range and to lateral accelerations a car can make."""
    for script in (lambda t, y: (-6.0, 0.0), lambda t, y: (4.0, 0.0)):
        states, _ = drive(name, ScriptedRobot(script), m=20)
        human = states[:, 1]
        assert (ROAD_Y_MIN <= human[..., 1]).all() and (human[..., 1] <= ROAD_Y_MAX).all()
        assert SPEED_RANGE[0] - 1.0 <= human[..., 2].min() and human[..., 2].max() <= SPEED_RANGE[1] + 1.0
        assert np.abs(human[..., 5]).max() <= 6.5  # m/s²: the hardest, the aborted change's final one


# ------------------------------------------------------------------ the scripted behaviours
def test_late_cut_in_cuts_into_the_robot_lane_at_its_x_without_looking():
    keep, brake = ScriptedRobot(), ScriptedRobot(lambda t, y: (-4.0, 0.0))
    states, parameters = drive("late-cut-in", keep)
    braked, _ = drive("late-cut-in", brake)
    np.testing.assert_array_equal(states[:, 1], braked[:, 1])  # it does not look at the robot
    human, robot = states[:, 1], states[:, 0]
    assert (lane_of(human[:, -1, 1]) == lane_of(robot[:, 0, 1])).all()  # ends in the robot's start lane
    moves = np.abs(human[..., 5]) > 1e-9
    first = moves.argmax(axis=1)
    rows = np.arange(len(human))
    assert (human[rows, first - 1, 0] >= parameters["cut_x"]).all()  # the step it decided at
    assert (human[rows, first - 2, 0] < parameters["cut_x"]).all()
    assert np.ptp(human[..., 2], axis=1).max() == 0  # keeps its speed
    crossed = (lane_of(human[..., 1]) == lane_of(robot[:, :1, 1])).argmax(axis=1)
    assert ((crossed - first) * DT <= 1.5).all()  # in the robot's lane within 1.5 s


def test_aborted_change_reaches_the_divider_swerves_back_and_changes_for_good():
    states, parameters = drive("aborted-change", ScriptedRobot(lambda t, y: (-3.0, 0.0) if t < 20 else (0.0, 0.0)))
    human, robot = states[:, 1], states[:, 0]
    home = np.sign(human[:, 0, 1] - LANE_DIVIDER_Y)[:, None]  # +1: the human starts left of the divider
    side = np.sign(human[..., 1] - LANE_DIVIDER_Y) * home  # +1 on its own side
    for k in range(len(human)):
        crossed = np.flatnonzero(side[k] < 0)[0]
        back = crossed + np.flatnonzero(side[k, crossed:] > 0)[0]  # it turns back at the divider
        assert np.abs(human[k, crossed:back, 1] - LANE_DIVIDER_Y).max() < 1.6  # half-way, no further
        final = back + np.flatnonzero(side[k, back:] < 0)[0]
        assert human[k, final, 0] >= parameters["final_x"][k]
    assert (lane_of(human[:, -1, 1]) == lane_of(robot[:, 0, 1])).all()


def test_brake_after_merge_brakes_only_once_the_robot_merged_behind():
    never, _ = drive("brake-after-merge", ScriptedRobot())
    assert (never[:, 1, :, 4] == 0).all()  # a robot that never merges: no braking ...
    human = never[:, 1]
    assert (lane_of(human[:, -1, 1]) != lane_of(human[:, 0, 1])).all()  # ... and it changes lanes anyway
    states, parameters = drive("brake-after-merge", ScriptedRobot(merging(step=3)))
    human, robot = states[:, 1], states[:, 0]
    braking = human[..., 4] < 0
    assert braking.any(axis=1).all()
    first = braking.argmax(axis=1)
    # the decision at step first - 1 saw the robot merged (within 0.5 m of the lane centre) and behind
    merged = (np.abs(robot[..., 1] - human[:, :1, 1]) < 0.5) & (robot[..., 0] < human[..., 0])
    steps = braking.sum(axis=1)
    np.testing.assert_array_equal(steps, np.round(parameters["brake_s"] / DT))  # 1.0-1.5 s ...
    for k in range(len(human)):
        assert merged[k, first[k] - 1] and not merged[k, : first[k] - 1].any()  # decided once merged
        assert (human[k, first[k]:first[k] + steps[k], 4] == -8.0).all()  # ... at 8 m/s²
        assert np.abs(human[k, first[k] + steps[k]:, 5]).max() > 1.0  # then it changes lanes
    assert human[..., 2].min() > 11.0
    assert (lane_of(human[:, -1, 1]) == lane_of(robot[:, 0, 1])).all()


def test_never_yield_changes_lanes_at_its_x_whatever_the_robot_does():
    states, parameters = drive("never-yield", ScriptedRobot())
    braked, _ = drive("never-yield", ScriptedRobot(lambda t, y: (-6.0, 0.0)))
    np.testing.assert_array_equal(states[:, 1], braked[:, 1])
    human = states[:, 1]
    assert (human[..., 4] == 0).all()  # never brakes
    first = (np.abs(human[..., 5]) > 1e-9).argmax(axis=1)
    rows = np.arange(len(human))
    assert (human[rows, first - 1, 0] >= parameters["change_x"]).all()
    assert (human[rows, first - 2, 0] < parameters["change_x"]).all()
    overlap = np.abs(states[:, 0, :, 1] - human[..., 1]) < 1.8  # beside a robot that keeps its lane
    assert overlap.any(axis=1).all() and (overlap.argmax(axis=1) * DT >= 2.2 - 1e-9).all()  # 2.2 s of warning


def test_mirror_copies_the_robot_longitudinally_with_a_delay_and_changes_lanes_once_clear():
    pulse = lambda t, y: (-4.0 if 5 <= t < 15 else 2.0 if 15 <= t < 25 else 0.0, 0.0)  # noqa: E731
    states, _ = drive("mirror", ScriptedRobot(pulse))
    human, robot = states[:, 1], states[:, 0]
    mirroring = human[:, 3:-1, 0] <= -50.0  # at the steps that decided
    np.testing.assert_allclose(human[:, 4:, 4][mirroring], robot[:, 1:-3, 4][mirroring])  # 0.3 s later
    assert (human[:, 1:, 4][human[:, :-1, 0] > -50.0] == 0).all()  # then keeps its speed
    changing = np.abs(human[..., 5]) > 1e-9
    gap = np.abs(human[..., 0] - robot[..., 0]) - CAR_LENGTH
    assert changing.any()
    for k in np.flatnonzero(changing.any(axis=1)):
        decided = changing[k].argmax() - 1
        assert gap[k, decided] > 5.0
    braking = ScriptedRobot(lambda t, y: (-6.0, 0.0))  # a robot that brakes to a stop: the copy stops at 10 m/s
    assert drive("mirror", braking, m=5)[0][:, 1, :, 2].min() >= SPEED_RANGE[0] - 1.0


def test_block_drives_alongside_a_robot_that_moves_over():
    states, _ = drive("block", ScriptedRobot(merging(step=5, duration=4.0)))
    human, robot = states[:, 1], states[:, 0]
    assert (human[:, 1:5, 4] > 0).all()  # 3-8 m behind: it accelerates
    assert human[..., 4].max() == pytest.approx(3.0)
    alongside = np.abs(human[..., 0] - robot[..., 0]) < CAR_LENGTH
    assert alongside[:, :40].any(axis=1).all()  # it comes alongside within 4 s
    assert (np.abs(human[..., 4]) <= 3.0 + 1e-9).all()


# ------------------------------------------------------------------ specs and the command
def test_scenario_specs_parse_and_build_their_humans():
    for name in NAMES:
        assert parse_human_spec(f"scenario:{name}") == HumanSpec("scenario", scenario=name)
        agent = human_agent(f"scenario:{name}")
        assert isinstance(agent, ScriptedHuman) and agent.scenario is SCENARIOS[name]
        assert name in HUMAN_SPECS
    assert "scenario:NAME" in HUMAN_SPECS and "replay:FILE@T,V" in HUMAN_SPECS
    for bad in ("scenario:", "scenario:bogus", "scenario:Mirror"):
        with pytest.raises(InputError) as info:
            parse_human_spec(bad)
        assert str(info.value) == (f"human {bad!r}: no such scenario (expected scenario:NAME, NAME one of: "
                                   f"{', '.join(NAMES)})")


def test_simulate_runs_a_scenario_with_the_rule_robot(capsys, tmp_path):
    argv = ["simulate", "--robot", "rules", "--human", "scenario:late-cut-in", "--episodes", "2", "--out",
            str(tmp_path / "run"), "--json"]
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["episodes"] == 2 and summary["human"] == "scenario:late-cut-in" and summary["computed"] == 2
    assert [row["dv"] for row in summary["by_initial_condition"]] == [None] * len(summary["by_initial_condition"])
    assert main(argv) == 0  # the logs read back: a rerun reuses them
    assert json.loads(capsys.readouterr().out)["reused"] == 2
    assert main([*argv[:4], "scenario:nope", *argv[6:]]) == 2
    assert capsys.readouterr().err.count("\n") == 1
