"""Robot candidates (planning/candidates.py): counts, sequences, dynamics, each kinematics' limits."""

import numpy as np
import pytest

from trafficweaving.planning.candidates import (ACCELERATIONS, KINEMATICS, N_ACTIONS, N_CANDIDATES, SETTLING_TIME,
                                                WINDOWS, Action, action_sequences, robot_candidates, rollout)
from trafficweaving.planning.planner import Budget
from trafficweaving.planning.steering import optimal_time, steer
from trafficweaving.scenario import DT, HORIZON, LANE_CENTRE_Y

from helpers_planning import LEFT, RIGHT


PRESENT = np.array([-90.0, RIGHT, 29.0, 0.0, 0.0, 0.0])


def test_the_candidate_counts_follow_from_the_horizon_and_the_actions():
    assert (WINDOWS, N_ACTIONS, N_CANDIDATES) == (5, 8, 4096) and WINDOWS * 3 == HORIZON
    assert Budget().futures == 4096 * 16 + 32 * 1024


def test_4096_distinct_candidates_with_the_first_window_fixed():
    first = Action.of(4.0, "right").index
    c = robot_candidates(PRESENT, first)
    assert c.states.shape == (4096, 15, 6) and c.actions.shape == (4096, 5)
    assert (c.actions[:, 0] == first).all() and len({tuple(a) for a in c.actions}) == 4096
    same = c.states[:, :3].copy()
    same[:, 2, 4] = 0.0  # the xdd stored at the window's last step is the next window's acceleration
    np.testing.assert_allclose(same, np.broadcast_to(same[:1], (4096, 3, 6)))
    assert Action(first).acceleration == 4.0 and Action(first).lane == "right"


def test_candidate_longitudinal_dynamics_euler_velocity_trapezoid_position():
    c = robot_candidates(PRESENT, Action.of(0.0, "right").index)
    for k in (0, 1234, 4095):
        acc = np.repeat([ACCELERATIONS[a // 2] for a in c.actions[k]], 3)  # applied from t .. t+14
        xd = np.concatenate([[PRESENT[2]], c.states[k, :, 2]])
        x = np.concatenate([[PRESENT[0]], c.states[k, :, 0]])
        np.testing.assert_allclose(np.diff(xd), DT * acc, atol=1e-12)
        np.testing.assert_allclose(np.diff(x), 0.5 * DT * (xd[1:] + xd[:-1]), atol=1e-12)
        np.testing.assert_allclose(c.states[k, :-1, 4], acc[1:])  # xdd stored at a step = applied from it


def test_candidate_lateral_motion_follows_the_steering_window_by_window():
    actions = np.array([[Action.of(0.0, "right").index, Action.of(0.0, "left").index, Action.of(4.0, "left").index,
                         Action.of(-3.0, "right").index, Action.of(0.0, "left").index]])
    states = rollout(PRESENT, actions)[0]
    lateral = PRESENT[[1, 3, 5]]
    for w, a in enumerate(actions[0]):
        window = steer(lateral, np.array(LANE_CENTRE_Y[Action(int(a)).lane]), DT * np.arange(1, 4))
        np.testing.assert_allclose(states[3 * w:3 * w + 3][:, [1, 3, 5]], window[:, :3], atol=1e-12)
        lateral = window[-1, :3]
    hold = rollout(PRESENT, np.full((1, 5), Action.of(0.0, "right").index))[0]
    np.testing.assert_allclose(hold[:, 1], RIGHT)
    np.testing.assert_allclose(hold[:, 2], PRESENT[2])


def test_action_sequences_order():
    seqs = action_sequences(3)
    assert seqs.shape == (4096, 5) and (seqs[:8, -1] == np.arange(8)).all() and (seqs[-1] == [3, 7, 7, 7, 7]).all()


@pytest.mark.slow
def test_settled_steering_comes_to_rest_on_the_lane_centre_where_the_papers_keeps_chattering():
    """Executed as the world executes a plan (one acceleration a step, trapezoid rule), the paper's
    steering re-solves the sampling's residue on the lane centre every window into ±0.7 m/s²; with
    lateral manoeuvres of at least SETTLING_TIME the same lane change comes to rest."""
    from trafficweaving.dynamics import trapezoid_step

    def executed(kinematics, windows=30):
        state, accelerations = np.array([-300.0, RIGHT, 30.0, 0.0, 0.0, 0.0]), []
        for _ in range(windows):
            for planned in rollout(state, np.array([[Action.of(0.0, "left").index]]), kinematics)[0]:
                y, yd = trapezoid_step(state[1], state[3], state[5], planned[5])
                state = np.array([planned[0], y, planned[2], yd, planned[4], planned[5]])
                accelerations.append(planned[5])
        return np.array(accelerations), state

    paper, _ = executed(KINEMATICS["paper"])
    settled, end = executed(KINEMATICS["settled"])
    assert np.abs(paper[-30:]).max() > 0.5 and np.abs(settled[-30:]).max() < 0.01
    assert abs(end[1] - LANE_CENTRE_Y["left"]) < 0.01 and abs(end[3]) < 0.01
    assert np.abs(settled).max() == pytest.approx(np.abs(paper[:30]).max(), rel=0.1)  # the same lane change
    assert float(optimal_time(np.array([LEFT + 0.01, 0.0, 0.0]), np.array(LEFT), min_time=SETTLING_TIME)) >= SETTLING_TIME


@pytest.mark.slow
def test_comfort_candidates_keep_to_the_comfort_limits_from_every_state_they_reach():
    """From the right lane towards the left one, lane changes turned back included; the paper's
    candidates break the limits in most sequences."""
    from trafficweaving.sim.score import comfort_violations  # the closed loop's own definition

    def onward(present, first, kinematics):  # per candidate: a step over the limits (the present included)
        states = robot_candidates(present, first, kinematics).states
        acc = np.concatenate([np.broadcast_to(present[4:6], (len(states), 1, 2)), states[..., 4:6]], 1)
        return np.array([comfort_violations(a).any() for a in acc]), states

    start = np.array([-100.0, RIGHT, 30.0, 0.0, 0.0, 0.0])
    rng = np.random.default_rng(0)
    presents = [start]
    for first in (0, 1, 3, 6):  # states after a window and after two, as the MPC executes them
        _, states = onward(start, first, KINEMATICS["comfort"])
        picks = rng.choice(len(states), 3, replace=False)
        presents += [states[i, 2] for i in picks] + [states[i, 5] for i in picks]
    assert max(p[3] for p in presents) > 0.5  # some of them under way
    checked = 0
    for present in presents:
        for first in (0, 3, N_ACTIONS - 1):
            violations, _ = onward(present, first, KINEMATICS["comfort"])
            assert not violations.any()
            checked += len(violations)
    assert checked == 3 * len(presents) * N_CANDIDATES
    assert onward(start, 0, KINEMATICS["paper"])[0].mean() > 0.5
    comfort = robot_candidates(presents[-1], 0, KINEMATICS["comfort"]).states
    np.testing.assert_allclose(np.diff(comfort[..., 2], axis=1), DT * comfort[:, :-1, 4], atol=1e-12)  # Euler velocity
